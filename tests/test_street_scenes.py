"""street.region_growing on generated scenes, against truth/street_labels.npy (skipped when absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from plugins.street_region_growing import RegionGrowing
from toolkit.io.cloud import read_points
from toolkit.observe import NullObserver
from toolkit.scene import load_array, load_points, load_scene
from toolkit.street.score import angle_deg, found_up, score_segments, steep_truth, true_up
from toolkit.testing.street_toy import random_rotation

DATA = Path(__file__).resolve().parents[1] / "data"


def _scene(name: str):
    if name == "tiny":
        from tests.conftest import synthetic_scene

        root = synthetic_scene("tiny")  # generated once (seconds)
    else:
        root = DATA / name
        if not (root / "scene.yaml").is_file():
            pytest.skip(f"{name} scene not generated (minutes): run `crossview synth --preset {name} "
                        f"--seed 0 --out {root}` to include this check")
    scene = load_scene(root)
    points = np.asarray(load_points(scene, "street_cloud"))
    truth_points = load_array(scene, "truth_street_points")
    walls = steep_truth(truth_points, read_points(scene.files.truth_lidar))
    return scene, points, load_array(scene, "truth_street_labels"), true_up(points, truth_points), walls


def _check(points, labels, up, walls, min_wall_recall):
    seg = RegionGrowing().segment(points, NullObserver())
    assert angle_deg(found_up(seg), up) <= 0.5
    s = score_segments(seg, labels, points, walls=walls)
    assert s.facade_precision >= 0.95, s.line()
    assert s.wall_recall >= min_wall_recall, s.line()
    assert s.coverage >= 0.9, s.line()
    return s


def test_tiny_scene():
    _, points, labels, up, walls = _scene("tiny")
    # the acceptance target (0.9) is met on tiny too, but with little margin: keep a lower bar here
    _check(points, labels, up, walls, min_wall_recall=0.85)


def test_tiny_scene_rotated():
    _, points, labels, up, walls = _scene("tiny")
    rot = random_rotation(np.random.default_rng(11), 45.0)
    centre = points.mean(axis=0)
    _check((points - centre) @ rot.T + centre, labels, rot @ up, walls, min_wall_recall=0.85)


@pytest.mark.slow
def test_campus_scene():
    _, points, labels, up, walls = _scene("campus")
    _check(points, labels, up, walls, min_wall_recall=0.88)
