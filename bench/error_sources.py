"""Where a run's error comes from: per-point truth errors split by what moved each point.

    .venv/bin/python bench/error_sources.py OUT_DIR [OUT_DIR ...] [--scene SCENE]

For each run folder (``crossview run`` output of a scene with truth/street_points.npy and
truth/cameras.txt), every street point falls in one class:
  matched-good  its street segment has a valid transform and the segment's median horizontal error ≤ 1 m;
  matched-bad   valid transform, segment median > 1 m (a wrong match or a poor refinement);
  unregistered  a street segment without a valid transform (moved by the blended neighbours);
  background    no street segment (ground, vegetation; moved by the blend).
The street labels are recomputed by the run's own street step (recipe.yaml), ~10-30 s a scene. The
blended classes are also split by the route distance to the nearest registered segment (route
position = arc length of the truth camera track at the camera nearest to the point's true XY).
Printed per run: each class's point share, horizontal median / p95, and its share of the points
over 1.5 m (what makes the p95 miss the bar); the background points by route gap; the points
carried by a registered segment moved by that segment's own transform (transforms.json) beside the
same points as registered (after the blend and the bundle adjustment); and every point by where
along the route its capturing camera was (truth/drift.npz ``camera_index``; tenths of the route, the
first and last twentieth apart: the ends of a route have neighbours on one side only).
The scene: --scene, else the data/cities scene whose name starts the run folder's name.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import laspy
import numpy as np
from scipy.spatial import cKDTree

from _common import REPO, truth_centres  # noqa: F401  (REPO puts the repository on sys.path)

BAD_SEGMENT_M = 1.0
OVER_M = 1.5
GAP_BINS_M = (0.0, 10.0, 30.0, 100.0, np.inf)
ROUTE_BINS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 1.0 + 1e-9)


def scene_of(out: Path, given: str | None) -> Path:
    """--scene, else the matrix scene whose name prefixes the run folder (bench/cities.py layout)."""
    if given:
        return Path(given)
    cities = REPO / "data" / "cities"
    names = [p.name for p in cities.iterdir() if (p / "scene.yaml").is_file()] if cities.is_dir() else []
    hits = sorted((n for n in names if out.name.startswith(n + "-")), key=len)
    if not hits:
        raise SystemExit(f"{out}: which scene? pass --scene")
    return cities / hits[-1]


def camera_arc(scene: Path) -> tuple[np.ndarray, np.ndarray]:
    """(truth camera XY (m,2), arc length (m,) in metres along their track)."""
    cams = truth_centres(scene / "truth" / "cameras.txt")[:, :2]
    return cams, np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(cams, axis=0), axis=1))])


def route_positions(truth_xy: np.ndarray, scene: Path) -> np.ndarray:
    """Arc length (m) along the truth camera track at the camera nearest to each point."""
    cams, arc = camera_arc(scene)
    return arc[cKDTree(cams).query(truth_xy, workers=-1)[1]]


def street_step(out: Path, scene: Path):
    """The street stage's output and the input street points (metres), recomputed from the run's recipe."""
    from toolkit.observe import NullObserver
    from toolkit.recipe import load_recipe
    from toolkit.runner import build
    from toolkit.scene import load_points

    plan = build(load_recipe(out / "recipe.yaml"), scene)
    spec, stage = next((sp, st) for sp, st in plan.stages if sp.name == "street")
    return stage(plan.scene, plan.capture, NullObserver()), load_points(plan.scene)


def captured_route_fraction(scene: Path) -> np.ndarray | None:
    """(n,) route fraction (0 start, 1 end) of each point's capturing camera, None without
    truth/drift.npz."""
    drift = scene / "truth" / "drift.npz"
    if not drift.is_file():
        return None
    _, arc = camera_arc(scene)
    return arc[np.load(drift)["camera_index"]] / max(arc[-1], 1e-9)


def own_transform_errors(street, points: np.ndarray, truth: np.ndarray, segments: list[dict]) -> np.ndarray:
    """(n,) horizontal error of each point carried by a registered segment, moved by that segment's own
    transform alone; NaN for the other points."""
    T = np.array([s["transform"] for s in segments], np.float64)
    valid = np.array([s["valid"] for s in segments], bool)
    carrier = np.asarray(street.carrier, np.int64)
    ok = carrier >= 0
    ok[ok] = valid[carrier[ok]]
    c = carrier[ok]
    moved = np.einsum("nij,nj->ni", T[c, :3, :3], points[ok]) + T[c, :3, 3]
    out = np.full(len(points), np.nan)
    out[ok] = np.linalg.norm(moved[:, :2] - truth[ok, :2], axis=1)
    return out


def classify(out: Path, scene: Path) -> dict:
    las = laspy.read(out / "registered.laz")
    xyz = np.column_stack([las.x, las.y, las.z])
    street, points = street_step(out, scene)
    seg = np.asarray(street.point_labels, np.int64)
    truth = np.load(scene / "truth" / "street_points.npy")
    h = np.linalg.norm(xyz[:, :2] - truth[:, :2], axis=1)
    segments = json.loads((out / "transforms.json").read_text())["segments"]
    valid = {s["segment"] for s in segments if s["valid"]}
    in_valid = np.isin(seg, sorted(valid)) & (seg >= 0)
    seg_median = {s: float(np.median(h[seg == s])) for s in valid if np.any(seg == s)}
    bad = np.isin(seg, [s for s, m in seg_median.items() if m > BAD_SEGMENT_M]) & in_valid
    cls = np.full(len(h), "background", dtype=object)
    cls[(seg >= 0) & ~in_valid] = "unregistered"
    cls[in_valid & ~bad] = "matched-good"
    cls[bad] = "matched-bad"
    s = route_positions(truth[:, :2], scene)
    reg_s = np.sort(s[in_valid]) if in_valid.any() else np.array([np.inf])
    k = np.clip(np.searchsorted(reg_s, s), 1, len(reg_s) - 1) if len(reg_s) > 1 else np.zeros(len(s), int)
    gap = np.minimum(np.abs(s - reg_s[k]), np.abs(s - reg_s[np.maximum(k - 1, 0)]))
    return {"h": h, "cls": cls, "gap": gap, "own": own_transform_errors(street, points, truth, segments),
            "captured_at": captured_route_fraction(scene),
            "n_bad_segments": int(sum(m > BAD_SEGMENT_M for m in seg_median.values())), "n_valid": len(valid)}


def report(out: Path, r: dict) -> None:
    h, cls, over = r["h"], r["cls"], r["h"] > OVER_M
    print(f"\n{out.name}: h median {np.median(h):.2f} m, p95 {np.percentile(h, 95):.2f} m, "
          f"{r['n_valid']} registered segments ({r['n_bad_segments']} with median > {BAD_SEGMENT_M} m)")
    print(f"  {'class':<14}{'points':>8}{'median':>8}{'p95':>8}{'of >1.5 m':>11}")
    for c in ("matched-good", "matched-bad", "unregistered", "background"):
        m = cls == c
        if m.any():
            print(f"  {c:<14}{m.mean():>8.1%}{np.median(h[m]):>8.2f}{np.percentile(h[m], 95):>8.2f}"
                  f"{(over & m).sum() / max(over.sum(), 1):>11.1%}")
    blended = (cls == "background") | (cls == "unregistered")
    for lo, hi in zip(GAP_BINS_M[:-1], GAP_BINS_M[1:]):
        m = blended & (r["gap"] >= lo) & (r["gap"] < hi)
        if m.any():
            print(f"  blended, route gap {lo:>3.0f}-{hi:<4.0f} m{m.mean():>7.1%}{np.median(h[m]):>8.2f}"
                  f"{np.percentile(h[m], 95):>8.2f}{(over & m).sum() / max(over.sum(), 1):>11.1%}")
    own = r["own"]
    m = np.isfinite(own)
    if m.any():
        print(f"  carried by a registered segment ({m.mean():.0%} of the points): own transform median "
              f"{np.median(own[m]):.2f} p95 {np.percentile(own[m], 95):.2f} m; as registered median "
              f"{np.median(h[m]):.2f} p95 {np.percentile(h[m], 95):.2f} m")
    at = r["captured_at"]
    if at is not None:
        print("  captured along the route (fraction)")
        for lo, hi in zip(ROUTE_BINS[:-1], ROUTE_BINS[1:]):
            m = (at >= lo) & (at < hi)
            if m.any():
                print(f"    {lo:4.2f}-{min(hi, 1.0):4.2f}{m.mean():>12.1%}{np.median(h[m]):>8.2f}"
                      f"{np.percentile(h[m], 95):>8.2f}{(over & m).sum() / max(over.sum(), 1):>11.1%}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("outs", nargs="+")
    ap.add_argument("--scene")
    args = ap.parse_args()
    for o in args.outs:
        out = Path(o)
        report(out, classify(out, scene_of(out, args.scene)))


if __name__ == "__main__":
    main()
