"""How many true buildings a street-only segmentation can separate at all (a diagnostic, not a test).

Issue 5 asks that ≥ 90 % of the true buildings with ≥ 5 m of visible façade get a segment ≥ 95 %
from that building. In a terrace the houses share one façade plane, so a segment can only stop at a
house boundary where the cloud shows something there. This script measures, from the truth
(noise-free ``truth/street_points.npy`` with ``truth/street_labels.npy``; walls are the points whose
true surface is steep, as in ``bench/street_accuracy.py``), at every contact between two buildings'
walls that face the same way (within ``--parallel-deg``; walls turning at a corner are told apart
by their normals already):

- the step of the façade top (median over 0.5 m cells of the highest wall point) within
  ``--window-m`` on either side of the contact,
- the step across the wall (set-back: median distance of each side's wall cells from the contact
  along the common normal),
- the turn between the two sides' wall directions,
- the step of the highest building point (roof seen from the street) within the window.

A contact is *separable* when any step exceeds its threshold (``--top-m``, ``--setback-m``,
``--turn-deg``, ``--roof-m``: well above the 3-10 cm noise of the street clouds). Buildings joined
by inseparable contacts form groups that no geometric street-only rule can cut. Two ceilings:

- whole-group: a building is coverable when it holds ≥ 95 % of its group's wall points;
- stage segments cut there (unless ``--no-oracle``): street.region_growing runs with the terrace
  split off, and its segments are cut by the truth exactly along every boundary between groups
  (pieces narrower than 5 m dropped, clutter joining the largest piece); covered as scored by
  ``toolkit.street.score``. With every contact cut ("perfect") this is what an ideal splitter of
  these segments could reach; the rest are lost to narrow walls, occlusion and growing.

It also counts eligible buildings (≥ 5 m wide over all their points, as in ``toolkit.street.score``)
whose visible walls span under 5 m: a segment built from walls cannot cover them purely.
The truth-side measures are approximate (0.5 m cells, 3 m windows; the turn between LoD2 faces is
not always visible in the cloud). ``--dump`` writes the contact table.

usage: python bench/street_terrace_ceiling.py [SCENE ...] [--window-m 3] [--top-m 0.3] ...
       (default scene: data/bench-DenHaag_01-0, built from ../shared's Den Haag LoD2 model when absent)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from scipy.spatial import cKDTree  # noqa: E402

from toolkit.io.cloud import read_points  # noqa: E402
from toolkit.scene import load_array, load_scene  # noqa: E402
from toolkit.street.growing import components  # noqa: E402
from toolkit.street.outline import diameters  # noqa: E402
from toolkit.street.score import steep_truth  # noqa: E402

CELL_M = 0.5


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="*")
    ap.add_argument("--window-m", type=float, default=3.0)
    ap.add_argument("--contact-m", type=float, default=0.75)
    ap.add_argument("--parallel-deg", type=float, default=20.0)
    ap.add_argument("--top-m", type=float, default=0.3)
    ap.add_argument("--setback-m", type=float, default=0.2)
    ap.add_argument("--turn-deg", type=float, default=3.0)
    ap.add_argument("--roof-m", type=float, default=0.5)
    ap.add_argument("--dump", help="write the contact table (text) here")
    ap.add_argument("--no-oracle", dest="oracle", action="store_false",
                    help="skip running the stage (the oracle cut of its segments)")
    args = ap.parse_args()
    if not args.scenes:
        sys.path.insert(0, str(REPO / "bench"))
        from _common import city_scene

        args.scenes = [str(city_scene())]
    for path in args.scenes:
        ceiling(Path(path), args)


def _cells(xyz: np.ndarray, lab: np.ndarray, azim2: np.ndarray):
    """Per (building, 0.5 m cell): mean xy, highest z, mean doubled azimuth (cos, sin), building."""
    c = np.floor(xyz[:, :2] / CELL_M).astype(np.int64)
    c -= c.min(axis=0)
    key = (lab.astype(np.int64) * (c[:, 0].max() + 1) + c[:, 0]) * (c[:, 1].max() + 1) + c[:, 1]
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    m = len(cnt)
    xy = np.stack([np.bincount(inv, xyz[:, i], m) / cnt for i in range(2)], axis=1)
    top = np.full(m, -np.inf)
    np.maximum.at(top, inv, xyz[:, 2])
    a2 = np.stack([np.bincount(inv, np.cos(azim2), m), np.bincount(inv, np.sin(azim2), m)], axis=1)
    b = np.zeros(m, dtype=np.int64)
    b[inv] = lab
    return xy, top, np.arctan2(a2[:, 1], a2[:, 0]), b


def ceiling(root: Path, args) -> None:
    import open3d as o3d

    scene = load_scene(root)
    pts = np.asarray(load_array(scene, "truth_street_points"), dtype=np.float64)
    lab = np.asarray(load_array(scene, "truth_street_labels")).astype(np.int64)
    walls = steep_truth(pts, read_points(scene.files.truth_lidar))
    on_b = lab >= 0
    b_ids, b_inv = np.unique(lab[on_b], return_inverse=True)
    extent = diameters(pts[on_b, :2], b_inv, len(b_ids))
    eligible = extent >= 5.0
    w = on_b & walls
    wxyz, wlab = pts[w], lab[w]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(wxyz - wxyz.mean(axis=0)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(12))
    nrm = np.asarray(pcd.normals)
    azim2 = 2.0 * np.arctan2(nrm[:, 1], nrm[:, 0])
    cxy, ctop, caz2, cb = _cells(wxyz, wlab, azim2)
    # highest point of any kind (walls and roofs) per building cell: the roof seen from the street
    rxy, rtop, _, rb = _cells(pts[on_b], lab[on_b], np.zeros(int(on_b.sum())))

    pairs = cKDTree(cxy).query_pairs(args.contact_m, output_type="ndarray")
    a, b = cb[pairs[:, 0]], cb[pairs[:, 1]]
    turn = np.abs(np.mod(caz2[pairs[:, 0]] - caz2[pairs[:, 1]] + np.pi, 2 * np.pi) - np.pi) / 2
    keep = (a != b) & (turn <= np.radians(args.parallel_deg))
    pairs, a, b = pairs[keep], a[keep], b[keep]
    key = np.minimum(a, b) * (lab.max() + 1) + np.maximum(a, b)
    _, first = np.unique(key, return_index=True)
    tree_c, tree_r = cKDTree(cxy), cKDTree(rxy)
    rows = []
    for i in first:  # one contact per building pair (a few hundred at most)
        p, q = pairs[i]
        centre = (cxy[p] + cxy[q]) / 2
        mean2 = np.arctan2(np.sin(caz2[[p, q]]).sum(), np.cos(caz2[[p, q]]).sum())
        near = np.asarray(tree_c.query_ball_point(centre, args.window_m), dtype=np.int64)
        # only this façade's cells: not the side walls round a corner within the window
        near = near[np.abs(np.mod(caz2[near] - mean2 + np.pi, 2 * np.pi) - np.pi) / 2
                    <= np.radians(args.parallel_deg)]
        mean2 = np.arctan2(np.sin(caz2[near]).sum(), np.cos(caz2[near]).sum())  # steadier than 2 cells
        near_r = np.asarray(tree_r.query_ball_point(centre, args.window_m), dtype=np.int64)
        normal = np.array([np.cos(mean2 / 2), np.sin(mean2 / 2)])
        side = []
        for bid in (cb[p], cb[q]):
            s = near[cb[near] == bid]
            r = near_r[rb[near_r] == bid]
            az = np.arctan2(np.sin(caz2[s]).sum(), np.cos(caz2[s]).sum()) / 2
            side.append((np.median(ctop[s]), np.median((cxy[s] - centre) @ normal), az,
                         rtop[r].max() if len(r) else np.nan))
        (t0, o0, a0, r0), (t1, o1, a1, r1) = side
        d_turn = np.degrees(np.abs(np.mod(2 * (a0 - a1) + np.pi, 2 * np.pi) - np.pi) / 2)
        rows.append((cb[p], cb[q], abs(t0 - t1), abs(o0 - o1), d_turn, abs(r0 - r1)))
    rows = np.array(rows, dtype=np.float64).reshape(-1, 6)
    d_top, d_off, d_turn, d_roof = rows[:, 2], rows[:, 3], rows[:, 4], np.nan_to_num(rows[:, 5])
    by_top, by_off = d_top >= args.top_m, d_off >= args.setback_m
    by_turn, by_roof = d_turn >= args.turn_deg, d_roof >= args.roof_m
    separable = by_top | by_off | by_turn | by_roof
    print(f"== {scene.name}: {len(b_ids)} buildings seen, {int(eligible.sum())} eligible (≥ 5 m); "
          f"{len(rows)} same-direction wall contacts")
    print(f"contacts separable by façade-top step ≥ {args.top_m} m: {int(by_top.sum())}, set-back ≥ "
          f"{args.setback_m} m: {int(by_off.sum())}, turn ≥ {args.turn_deg}°: {int(by_turn.sum())}, roof step ≥ "
          f"{args.roof_m} m: {int(by_roof.sum())}; any: {int(separable.sum())}/{len(rows)}")
    if len(rows):
        print("  façade-top step quantiles 10/25/50/75/90 %: "
              + " ".join(f"{v:.2f}" for v in np.quantile(d_top, [0.1, 0.25, 0.5, 0.75, 0.9])) + " m")
    if args.dump:
        np.savetxt(args.dump, rows, fmt="%.3f", header="building_a building_b d_top_m d_setback_m d_turn_deg d_roof_m")
    touching = np.isin(b_ids, rows[:, :2].astype(np.int64))
    print(f"eligible buildings without a same-direction wall contact: {int((eligible & ~touching).sum())}")
    seg = _stage_labels(scene) if args.oracle else None
    for name, cut in (("no evidence", np.zeros(len(rows), bool)), ("façade top", by_top),
                      ("top or set-back", by_top | by_off), ("top or turn", by_top | by_turn),
                      ("top or roof", by_top | by_roof), ("any evidence", separable),
                      ("perfect (oracle)", np.ones(len(rows), bool))):
        group = _groups(b_ids, rows[~cut, :2].astype(np.int64))
        covered = _coverable(group, b_inv[walls[on_b]])
        line = (f"contacts cut by {name:16s}: whole-group ceiling {int((covered & eligible).sum())}/"
                f"{int(eligible.sum())} ({(covered & eligible).sum() / max(eligible.sum(), 1):.3f})")
        if seg is not None:
            ok = _oracle_split(seg, lab, pts, b_ids, group) & eligible
            line += f"; stage segments cut there: {int(ok.sum())} ({ok.sum() / max(eligible.sum(), 1):.3f})"
        print(line)
    wb = b_inv[walls[on_b]]
    wall_width = np.zeros(len(b_ids))
    present = np.unique(wb)
    wall_width[present] = diameters(pts[on_b][walls[on_b]][:, :2], np.searchsorted(present, wb), len(present))
    narrow = eligible & (wall_width < 5.0)
    print(f"eligible buildings whose visible walls span < 5 m (roofs make them eligible): {int(narrow.sum())}")
    if seg is not None:
        missed = eligible & ~ok
        print(f"not covered even by the perfect cut: {int(missed.sum())}, of them walls < 5 m: "
              f"{int((missed & narrow).sum())}; the rest have < 5 m of wall in segments (occlusion, "
              f"growing) or clutter over 5 %")


def _stage_labels(scene) -> tuple[np.ndarray, np.ndarray]:
    """street.region_growing (defaults, terrace split off) on the scene's street cloud: point labels,
    levelled xy."""
    from plugins.street_region_growing import RegionGrowing
    from toolkit.observe import NullObserver
    from toolkit.scene import load_points

    points = load_points(scene, "street_cloud")
    seg = RegionGrowing.from_config({"split_window_m": 0}).segment(points, NullObserver())
    return np.asarray(seg.point_labels).astype(np.int64), seg.level(points)[:, :2]


def _oracle_split(seg, lab: np.ndarray, pts: np.ndarray, b_ids: np.ndarray, group: np.ndarray) -> np.ndarray:
    """(B,) covered when the stage's segments are cut along every boundary between building groups:
    pieces = (segment, group) narrower than 5 m dropped; clutter/ground points in a segment go with
    the segment's largest piece; covered = holds ≥ 95 % of some kept piece."""
    pred, xy = seg
    in_seg = pred >= 0
    s, t, xy = pred[in_seg], lab[in_seg], xy[in_seg]
    g = np.full(len(t), -1, dtype=np.int64)
    on = t >= 0
    g[on] = group[np.searchsorted(b_ids, t[on])]
    n_g = int(group.max()) + 2
    key = s * n_g + g + 1
    # clutter points join the largest building piece of their segment
    pk, pc = np.unique(key[on], return_counts=True)
    order = np.lexsort((-pc, pk // n_g))
    first = order[np.unique((pk // n_g)[order], return_index=True)[1]]
    biggest = dict(zip((pk // n_g)[first].tolist(), pk[first].tolist()))
    key[~on] = np.array([biggest.get(v, -1) for v in s[~on].tolist()], dtype=np.int64)
    keep = key >= 0
    keys, kinv = np.unique(key[keep], return_inverse=True)
    wide = diameters(xy[keep], kinv, len(keys)) >= 5.0
    covered = np.zeros(len(b_ids), dtype=bool)
    pairs, counts = np.unique(np.stack([kinv[on[keep]], t[keep][on[keep]]], axis=1), axis=0, return_counts=True)
    size = np.bincount(kinv, minlength=len(keys))
    pure = wide[pairs[:, 0]] & (counts >= 0.95 * size[pairs[:, 0]])
    covered[np.searchsorted(b_ids, pairs[pure, 1])] = True
    return covered


def _groups(b_ids: np.ndarray, joined: np.ndarray) -> np.ndarray:
    """(B,) group of each building: components of the inseparable contacts ``joined`` (pairs of ids)."""
    n = len(b_ids)
    a, b = np.searchsorted(b_ids, joined[:, 0]), np.searchsorted(b_ids, joined[:, 1])
    src, dst = np.concatenate([a, b]), np.concatenate([b, a])
    order = np.argsort(src, kind="stable")
    indptr = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=n))])
    return components(n, indptr, dst[order].astype(np.int32)).astype(np.int64)


def _coverable(group: np.ndarray, wall_b: np.ndarray) -> np.ndarray:
    """(B,) bool: the building holds ≥ 95 % of the wall points of its group of inseparable buildings."""
    n = len(group)
    count = np.bincount(wall_b, minlength=n)
    group_count = np.bincount(group, weights=count, minlength=n)
    return count >= 0.95 * group_count[group]


if __name__ == "__main__":
    main()
