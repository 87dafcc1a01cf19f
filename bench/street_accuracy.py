"""street.region_growing accuracy against truth/street_labels.npy (not a test).

Prints, per scene: vertical error and sign over random initial rotations (any yaw, tilt ≤ 45°,
the cloud rotated about its centroid), façade precision/recall (all building points, and walls
only: building points whose noise-free truth/lidar.ply surface is steep), and the share of true
buildings with ≥ 5 m of visible façade that get a ≥ 95 % pure segment.

usage: python bench/street_accuracy.py [SCENE ...] [--rotations 20] [--seed 0] [-s key=value ...]
       (default scene: data/campus)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from plugins.street_region_growing import RegionGrowing
from toolkit.io.cloud import read_points
from toolkit.observe import NullObserver
from toolkit.scene import load_array, load_points, load_scene
from toolkit.street.score import angle_deg, found_up, score_segments, steep_truth, true_up
from toolkit.testing.street_toy import random_rotation


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="*", default=[str(REPO / "data" / "campus")])
    ap.add_argument("--rotations", type=int, default=20)
    ap.add_argument("--max-tilt-deg", type=float, default=45.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("-s", "--set", action="append", default=[], help="stage parameter key=value")
    args = ap.parse_args()
    params = {}
    for kv in args.set:
        key, value = kv.split("=", 1)
        params[key] = _parse(value)
    stage = RegionGrowing.from_config(params)
    for path in args.scenes:
        evaluate(Path(path), stage, args.rotations, args.max_tilt_deg, args.seed)


def _parse(value: str):
    import yaml

    return yaml.safe_load(value)


def evaluate(root: Path, stage: RegionGrowing, rotations: int, max_tilt_deg: float, seed: int) -> None:
    scene = load_scene(root)
    points = load_points(scene, "street_cloud")
    labels = load_array(scene, "truth_street_labels")
    truth_points = load_array(scene, "truth_street_points")
    walls = steep_truth(truth_points, read_points(scene.files.truth_lidar)) if scene.has("truth_lidar") else None
    up = true_up(points, truth_points)
    print(f"== {scene.name}: {len(points)} points, {len(np.unique(labels[labels >= 0]))} buildings seen")
    t0 = time.perf_counter()
    seg = stage.segment(points, NullObserver())
    seconds = time.perf_counter() - t0
    print(f"as given: vertical error {angle_deg(found_up(seg), up):.3f}°, {seconds:.1f} s")
    print(f"as given: {score_segments(seg, labels, points, walls=walls).line()}")
    rng = np.random.default_rng(seed)
    centre = points.mean(axis=0)
    errors, flips, scores = [], 0, []
    for i in range(rotations):
        rot = random_rotation(rng, max_tilt_deg)
        moved = (points - centre) @ rot.T + centre
        seg = stage.segment(moved, NullObserver())
        err = angle_deg(found_up(seg), rot @ up)
        flips += err > 90
        errors.append(min(err, 180 - err))
        scores.append(score_segments(seg, labels, moved, walls=walls))
        print(f"  rotation {i:2d}: tilt {angle_deg(rot @ [0, 0, 1.0], [0, 0, 1.0]):5.1f}°, "
              f"vertical error {err:.3f}°, {scores[-1].line()}")
    if rotations:
        e = np.array(errors)
        print(f"rotations: {rotations}, vertical error max {e.max():.3f}° mean {e.mean():.3f}°, "
              f"sign wrong {flips}; façade precision min {min(s.facade_precision for s in scores):.3f}, "
              f"wall recall min {min(s.wall_recall for s in scores):.3f}, "
              f"coverage min {min(s.coverage for s in scores):.3f}")


if __name__ == "__main__":
    main()
