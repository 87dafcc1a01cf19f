"""evaluate.chamfer and toolkit.evaluation on hand-made clouds with known answers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from shapely.geometry import box

from plugins.evaluate_chamfer import Chamfer
from toolkit.errors import SceneError
from toolkit.evaluation import metrics as M
from toolkit.evaluation import truth as T
from toolkit.io.cloud import write_ply
from toolkit.observe import NullObserver
from toolkit.types import Grid, Matches, OverviewSegments, Registration, Scene, SceneFiles, StreetSegments

UTM = np.array([500_000.0, 4_400_000.0, 200.0])


# --- the metric -------------------------------------------------------------------------------
def test_mutual_nn_keeps_only_mutual_pairs():
    a = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    b = np.array([[0.1, 0, 0]])
    r = M.mutual_nn_chamfer(a, b, cutoff_m=10)
    # a1's nearest is b0, but b0's nearest is a0: only (0, 0) is mutual
    assert r.pairs.tolist() == [[0, 0]]
    assert r.distances == pytest.approx([0.1])
    s = r.summary(cutoff_m=10)
    assert s["paired_fraction"] == pytest.approx(0.5)
    assert s["paired_fraction_reference"] == pytest.approx(1.0)


def test_cutoff_drops_far_pairs():
    a = np.array([[0.0, 0, 0], [100.0, 0, 0]])
    b = np.array([[0.0, 0, 0.5], [100.0, 0, 20.0]])
    r = M.mutual_nn_chamfer(a, b, cutoff_m=10)
    assert r.pairs.tolist() == [[0, 0]]
    s = r.summary(cutoff_m=10)
    assert s["mean_m"] == pytest.approx(0.5)
    assert s["std_m"] == pytest.approx(0.0)
    assert s["n_pairs"] == 1
    # with a larger cutoff the 20 m pair counts
    s2 = M.mutual_nn_chamfer(a, b, cutoff_m=25).summary()
    assert s2["mean_m"] == pytest.approx(10.25)
    assert s2["std_m"] == pytest.approx(9.75)


def test_2d_ignores_height_3d_does_not():
    a = np.array([[0.0, 0, 0], [5.0, 0, 0]])
    b = np.array([[0.0, 0, 3.0], [5.0, 0.4, 0]])
    s3 = M.mutual_nn_chamfer(a, b, 10).summary()
    s2 = M.mutual_nn_chamfer(a[:, :2], b[:, :2], 10).summary()
    assert s3["mean_m"] == pytest.approx((3.0 + 0.4) / 2)
    assert s3["std_m"] == pytest.approx(1.3)
    assert s2["mean_m"] == pytest.approx(0.2)
    assert s2["std_m"] == pytest.approx(0.2)


def test_matches_brute_force_and_survives_utm_offsets():
    rng = np.random.default_rng(3)
    a = rng.uniform(0, 20, (300, 3))
    b = rng.uniform(0, 20, (250, 3))
    d = np.linalg.norm(a[:, None] - b[None], axis=2)
    nn_ab, nn_ba = d.argmin(1), d.argmin(0)
    expected = {(i, int(nn_ab[i])) for i in range(len(a)) if nn_ba[nn_ab[i]] == i and d[i, nn_ab[i]] <= 1.5}
    r = M.mutual_nn_chamfer(a, b, cutoff_m=1.5)
    assert {tuple(p) for p in r.pairs.tolist()} == expected
    assert len(expected) > 20
    r_utm = M.mutual_nn_chamfer(a + UTM, b + UTM, cutoff_m=1.5)
    assert np.array_equal(r_utm.pairs, r.pairs)
    assert np.allclose(r_utm.distances, r.distances, atol=1e-8)


def test_matches_plain_two_tree_version_on_larger_clouds():
    """Leaf-order queries and the mark array instead of np.unique leave pairs and distances unchanged."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(5)
    a = rng.uniform(0, 60, (20_000, 3)) + UTM
    b = np.concatenate([rng.uniform(0, 60, (15_000, 3)), rng.uniform(100, 120, (500, 3))]) + UTM
    for dims in (3, 2):
        a_, b_ = a[:, :dims], b[:, :dims]
        origin = b_.mean(axis=0)
        d, j = cKDTree(b_ - origin).query(a_ - origin, distance_upper_bound=2.0)
        i_idx = np.flatnonzero(np.isfinite(d))
        uniq, inverse = np.unique(j[i_idx], return_inverse=True)
        back = cKDTree(a_ - origin).query(b_[uniq] - origin)[1]
        mutual = back[inverse] == i_idx
        r = M.mutual_nn_chamfer(a_, b_, cutoff_m=2.0)
        assert np.array_equal(r.pairs, np.column_stack([i_idx[mutual], j[i_idx][mutual]]))
        assert np.array_equal(r.distances, d[i_idx][mutual])
        assert r.n_pairs > 1000


def test_histogram_counts_all_pairs():
    a = np.array([[0.0, 0, 0], [10.0, 0, 0], [20.0, 0, 0]])
    b = a + [0.1, 0, 0]
    b[2] += [0, 0, 1.05]
    h = M.mutual_nn_chamfer(a, b, 10).summary(hist_bin_m=0.5, cutoff_m=10)["histogram"]
    assert len(h["edges_m"]) == len(h["counts"]) + 1
    assert sum(h["counts"]) == 3
    assert h["counts"][0] == 2 and h["counts"][2] == 1


def test_empty_clouds_give_no_pairs():
    r = M.mutual_nn_chamfer(np.zeros((0, 3)), np.ones((4, 3)), 10)
    s = r.summary(cutoff_m=10)
    assert s["n_pairs"] == 0 and s["mean_m"] is None


def test_subsample_deterministic_and_bounded():
    pts = np.arange(3000.0).reshape(-1, 3)
    i1, i2 = M.subsample(pts, 100, seed=1), M.subsample(pts, 100, seed=1)
    assert np.array_equal(i1, i2) and len(i1) == 100 and np.all(np.diff(i1) > 0)
    assert len(M.subsample(pts, 0)) == 1000 and len(M.subsample(pts, 5000)) == 1000


# --- errors and rigid fit ---------------------------------------------------------------------
def test_error_stats_and_within_fractions():
    err = np.array([0.0, 0.4, 0.9, 1.5, 3.0])
    s = M.point_error_summary(err, err / 2)
    assert s["error_3d"]["mean_m"] == pytest.approx(1.16)
    assert s["error_3d"]["median_m"] == pytest.approx(0.9)
    assert s["error_3d"]["max_m"] == pytest.approx(3.0)
    assert s["within_m"]["0.5"]["3d"] == pytest.approx(0.4)
    assert s["within_m"]["1"]["3d"] == pytest.approx(0.6)
    assert s["within_m"]["1"]["horizontal"] == pytest.approx(0.8)
    assert s["within_m"]["2"]["3d"] == pytest.approx(0.8)


def test_error_stats_leaves_input_alone_and_matches_numpy():
    rng = np.random.default_rng(2)
    err = rng.gamma(2.0, 1.0, 10_001)
    err[[3, 50]] = [np.nan, np.inf]
    before = err.copy()
    s = M.error_stats(err)
    assert np.array_equal(err, before, equal_nan=True)
    finite = before[np.isfinite(before)]
    p50, p90, p95 = np.percentile(finite, [50, 90, 95])
    assert (s["mean_m"], s["median_m"], s["p90_m"], s["p95_m"], s["max_m"], s["n"]) == (
        round(finite.mean(), 6), round(p50, 6), round(p90, 6), round(p95, 6), round(finite.max(), 6), 9_999)


def test_point_errors_chunks_do_not_change_values():
    rng = np.random.default_rng(4)
    est, true = rng.normal(size=(1000, 3)) * 1e5, rng.normal(size=(1000, 3)) * 1e5
    e3, eh = M.point_errors(est, true, chunk=7)
    diff = est - true
    assert np.array_equal(e3, np.sqrt(diff[:, 0] ** 2 + diff[:, 1] ** 2 + diff[:, 2] ** 2))
    assert np.array_equal(eh, np.sqrt(diff[:, 0] ** 2 + diff[:, 1] ** 2))


def test_rigid_fit_recovers_transform_at_utm_scale():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    src = rng.normal(size=(500, 3)) * 50
    R = Rotation.from_euler("zyx", [37, 4, -3], degrees=True).as_matrix()
    t = UTM + [12.0, -7.0, 3.0]
    dst = src @ R.T + t
    Tm = M.rigid_fit(src, dst)
    assert np.allclose(Tm[:3, :3], R, atol=1e-9)
    assert np.allclose(Tm[:3, 3], t, atol=1e-6)
    assert np.allclose(M.apply_transform(Tm, src), dst, atol=1e-6)
    # a reflection is never returned
    assert np.linalg.det(M.rigid_fit(src, src * [1, 1, -1])[:3, :3]) == pytest.approx(1.0)


# --- truth helpers ----------------------------------------------------------------------------
def _write_images_txt(path: Path, names, R, t):
    from toolkit.io.colmap import rotmat_to_qvec

    q = rotmat_to_qvec(R)
    lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"]
    for k, n in enumerate(names):
        lines.append(" ".join(map(str, [k + 1, *q[k], *t[k], 1, n])))
        lines.append("")
    path.write_text("\n".join(lines) + "\n")


def test_camera_centre_error_by_name(tmp_path):
    R = np.repeat(np.eye(3)[None], 3, axis=0)
    centres = UTM + np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0]])
    t = -centres  # R = I → t = −C
    _write_images_txt(tmp_path / "cameras.txt", ["a.jpg", "b.jpg", "c.jpg"], R, t)
    poses = T.read_images_txt(tmp_path / "cameras.txt")
    assert poses.names == ("a.jpg", "b.jpg", "c.jpg")
    assert np.allclose(poses.centres, centres)
    est_c = centres[[2, 0]] + [[3.0, 4.0, 0.0], [0.0, 0.0, 2.0]]
    res = T.camera_centre_errors(("c.jpg", "a.jpg", "zzz.jpg"), np.repeat(np.eye(3)[None], 3, 0),
                                 -np.vstack([est_c, UTM]), poses)
    assert res["n"] == 2 and res["n_missing"] == 1
    assert res["error_3d"]["mean_m"] == pytest.approx(3.5)
    assert res["horizontal"]["mean_m"] == pytest.approx(2.5)


def _grid():
    return Grid((1.0, 0.0, 1000.0, 0.0, -1.0, 2040.0), 40, 40, "EPSG:32617")


def test_overview_segments_map_to_buildings_by_iou():
    grid = _grid()
    ids = np.array([7, 9])
    geoms = [box(1002, 2002, 1012, 2012), box(1022, 2022, 1032, 2032)]  # 10×10 px each
    bidx = T.rasterise_buildings(ids, geoms, grid)
    assert (bidx == 0).sum() == 100 and (bidx == 1).sum() == 100
    labels = np.full((40, 40), -1, np.int32)
    rows0 = slice(40 - 12, 40 - 2)
    labels[rows0, 2:12] = 0                      # exactly building 7
    labels[40 - 32:40 - 22, 22:26] = 1           # 40 % of building 9: IoU 0.4 < 0.5
    seg_b, iou = T.overview_to_building(labels, 2, bidx, 2)
    assert seg_b.tolist() == [0, -1]
    assert iou == pytest.approx([1.0, 0.4])


def test_street_segment_majority_ignores_noise():
    point_labels = np.array([0, 0, 0, 1, 1, 1, -1, 2])
    true_labels = np.array([5, 5, 6, -2, -2, 8, 5, 3])
    assert T.street_to_building(point_labels, true_labels, 4).tolist() == [5, -1, 3, -1]


# --- the stage on a hand-made scene ----------------------------------------------------------
def _street(n_points: int, point_labels: np.ndarray, S: int) -> StreetSegments:
    return StreetSegments(
        origin=np.zeros(3), up_rotation=np.eye(3), point_labels=point_labels, carrier=point_labels,
        ids=np.arange(S, dtype=np.int64) + 100, boundary_xy=tuple(np.zeros((1, 2)) for _ in range(S)),
        centroids=np.zeros((S, 2)), extent_m=np.ones(S), ground_z=np.zeros(S),
        ground_normal=np.tile([0.0, 0, 1], (S, 1)))


def _overview(grid: Grid) -> OverviewSegments:
    labels = np.full((grid.height, grid.width), -1, np.int32)
    labels[40 - 12:40 - 2, 2:12] = 0
    labels[40 - 32:40 - 22, 22:32] = 1
    return OverviewSegments(grid=grid, label_image=labels, ids=np.array([11, 12]),
                            boundary_px=(np.zeros((1, 2), np.int32),) * 2,
                            centroids=np.array([[1007.0, 2007], [1027, 2027]]), polygons=(None, None),
                            ground_height=np.zeros(2), ground_normal=np.tile([0.0, 0, 1], (2, 1)))


def _matches(segment_match) -> Matches:
    S = len(segment_match)
    return Matches(edge_label=np.zeros(0, int), segment_match=np.array(segment_match),
                   confidence=np.ones(S), T2d=np.tile(np.eye(3), (S, 1, 1)), cost=np.full(S, 0.2),
                   energy=0.0, energy_trace=np.zeros(1), iterations=1, converged=True)


def _buildings_geojson(path: Path, crs: str):
    from pyproj import Transformer

    inv = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    feats = []
    for bid, (x0, y0, x1, y1) in ((7, (1002, 2002, 1012, 2012)), (9, (1022, 2022, 1032, 2032))):
        ring = [inv.transform(x, y) for x, y in ((x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0))]
        feats.append({"type": "Feature", "properties": {"id": bid},
                      "geometry": {"type": "Polygon", "coordinates": [[list(p) for p in ring]]}})
    path.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))


@pytest.fixture
def scene(tmp_path) -> Scene:
    rng = np.random.default_rng(1)
    n = 400
    true = np.column_stack([rng.uniform(1000, 1040, n), rng.uniform(2000, 2040, n), rng.uniform(0, 10, n)])
    lidar = true + rng.normal(0, 0.01, true.shape)
    write_ply(tmp_path / "lidar.ply", lidar)
    np.save(tmp_path / "street_points.npy", true)
    labels = np.full(n, -1, np.int32)
    labels[:100], labels[100:200], labels[200:260] = 7, 9, -2
    np.save(tmp_path / "street_labels.npy", labels)
    _buildings_geojson(tmp_path / "buildings.geojson", "EPSG:32617")
    names = [f"img{k:03d}.jpg" for k in range(4)]
    _write_images_txt(tmp_path / "cameras.txt", names, np.repeat(np.eye(3)[None], 4, 0),
                      -np.column_stack([np.arange(4.0) * 5 + 1000, np.full(4, 2010.0), np.full(4, 2.0)]))
    files = SceneFiles(truth_lidar=tmp_path / "lidar.ply", truth_street_points=tmp_path / "street_points.npy",
                       truth_street_labels=tmp_path / "street_labels.npy",
                       truth_buildings=tmp_path / "buildings.geojson", truth_cameras=tmp_path / "cameras.txt")
    return Scene(root=tmp_path, name="hand", crs="EPSG:32617", files=files)


def _registration(points, scene: Scene, shift=(0.0, 0.0, 0.0)):
    poses = T.read_images_txt(scene.files.truth_cameras)
    c = poses.centres + shift
    return Registration(points=points, image_names=poses.names, R=poses.R,
                        t=-np.einsum("cij,cj->ci", poses.R, c), point_segment=np.zeros(len(points), int))


@pytest.mark.parametrize("S", [5, 2 ** 15 + 3])
def test_segment_error_columns_per_segment(S):
    """Per-segment mean/median errors are those of each segment's points (int16 fast path and not)."""
    from toolkit.evaluation.scoring import segments_table

    rng = np.random.default_rng(S)
    labels = rng.integers(-2, S, 4 * S).astype(np.int32)
    labels[:S] = np.arange(S)  # every segment has points
    err = rng.gamma(2.0, 1.0, len(labels))
    rows = segments_table(_street(len(labels), labels, S), None, None, None, err, None)
    for s in (0, 1, S // 2, S - 1):
        mine = err[labels == s]
        assert rows[s]["n_points"] == len(mine)
        assert rows[s]["error_mean_m"] == round(float(mine.mean()), 6)
        assert rows[s]["error_median_m"] == round(float(np.median(mine)), 6)


def test_stage_on_hand_made_scene(scene):
    true = np.load(scene.files.truth_street_points)
    shift = np.array([0.3, 0.4, 1.2])  # 0.5 m horizontal, 1.3 m 3D
    reg = _registration(true + shift, scene, shift=shift)
    point_labels = np.full(len(true), -1, np.int32)
    point_labels[:100], point_labels[100:200] = 0, 1
    street = _street(len(true), point_labels, 2)
    grid = _grid()
    overview = _overview(grid)
    metrics = Chamfer()(reg, scene, NullObserver(), matches=_matches([0, 0]), street=street, overview=overview)
    v = metrics.values
    json.dumps(v)  # JSON-able
    assert v["reference"]["source"] == "truth_lidar"
    pe = v["truth"]
    assert pe["error_3d"]["mean_m"] == pytest.approx(1.3, abs=1e-9)
    assert pe["horizontal"]["p95_m"] == pytest.approx(0.5, abs=1e-9)
    assert pe["within_m"]["1"]["horizontal"] == pytest.approx(1.0)
    assert pe["within_m"]["1"]["3d"] == pytest.approx(0.0)
    assert pe["within_m"]["2"]["3d"] == pytest.approx(1.0)
    assert metrics.per_point_error_m.shape == (len(true),)
    sm = v["matching"]
    # street seg 0 (building 7) → overview 0 (building 7): correct; seg 1 (building 9) → overview 0: wrong
    assert sm["n_matched"] == 2 and sm["n_correct"] == 1
    assert sm["precision"] == pytest.approx(0.5) and sm["recall"] == pytest.approx(0.5)
    assert [r["correct"] for r in v["segments"]] == [True, False]
    assert v["segments"][0]["error_mean_m"] == pytest.approx(1.3)
    cam = v["cameras"]["registered"]
    assert cam["n"] == 4 and cam["error_3d"]["mean_m"] == pytest.approx(1.3)
    # the paper's metric: a uniform offset is seen, but only up to the density of the clouds
    c3 = v["chamfer"]["3d"]
    assert 0 < c3["mean_m"] <= 1.3 + 0.05 and c3["n_pairs"] > 0
    assert v["chamfer"]["2d"]["mean_m"] <= c3["mean_m"]


def test_stage_perfect_registration_scores_zero(scene):
    true = np.load(scene.files.truth_street_points)
    v = Chamfer()(_registration(true, scene), scene, NullObserver()).values
    assert v["truth"]["error_3d"]["max_m"] == pytest.approx(0.0)
    assert v["chamfer"]["3d"]["mean_m"] < 0.05
    assert v["chamfer"]["3d"]["paired_fraction"] > 0.95
    assert v["matching"] is None and any("segment-match" in n for n in v["notes"])


def test_misplaced_points_stop_pairing(scene):
    true = np.load(scene.files.truth_street_points).copy()
    moved = true.copy()
    moved[:200] += [0.0, 0.0, 50.0]  # far beyond the cutoff
    v = Chamfer()(_registration(moved, scene), scene, NullObserver()).values
    c = v["chamfer"]["3d"]
    assert c["mean_m"] < 0.05  # the mean alone flatters ...
    assert c["paired_fraction"] < 0.55  # ... the pair fraction tells
    assert v["truth"]["error_3d"]["mean_m"] == pytest.approx(25.0, abs=0.01)


def test_reference_path_and_errors(scene, tmp_path):
    true = np.load(scene.files.truth_street_points)
    write_ply(tmp_path / "other.ply", true + [0.0, 0.0, 2.0])
    st = Chamfer(Chamfer.Params(reference=str(tmp_path / "other.ply"), max_points=150))
    v = st(_registration(true, scene), scene, NullObserver()).values
    assert v["reference"]["n_used"] == 150 and v["street"]["n_used"] == 150
    assert v["chamfer"]["2d"]["mean_m"] < v["chamfer"]["3d"]["mean_m"]
    with pytest.raises(SceneError, match="overview_cloud"):
        Chamfer(Chamfer.Params(reference="overview_cloud"))(_registration(true, scene), scene, NullObserver())
    with pytest.raises(SceneError, match="nope.ply"):
        Chamfer(Chamfer.Params(reference="nope.ply"))(_registration(true, scene), scene, NullObserver())
    assert Chamfer.scene_needs(Chamfer.Params(reference="truth_lidar")) == ("truth_lidar",)


def test_scene_without_truth_or_reference(tmp_path):
    sc = Scene(root=tmp_path, name="bare", crs="EPSG:32617", files=SceneFiles())
    pts = np.zeros((5, 3))
    reg = Registration(points=pts, image_names=(), R=np.zeros((0, 3, 3)), t=np.zeros((0, 3)),
                       point_segment=np.zeros(5, int))
    m = Chamfer()(reg, sc, NullObserver())
    assert m.values["chamfer"] is None and m.values["truth"] is None and m.per_point_error_m is None
    assert len(m.values["notes"]) == 2


def test_match_to_a_merged_overview_segment_counts_for_every_building_it_covers():
    """One over-view segment drawn around two buildings (a merged OSM outline) is the counterpart of
    both; the strict one-to-one IoU rule (precision_iou) calls the second building's match wrong."""
    grid = _grid()
    ids = np.array([7, 9])
    geoms = [box(1002, 2002, 1012, 2012), box(1012, 2002, 1020, 2012)]  # 10×10 and 8×10 px, touching
    labels = np.full((40, 40), -1, np.int32)
    labels[40 - 12:40 - 2, 2:20] = 0             # the merged outline around both
    labels[40 - 32:40 - 22, 22:32] = 1           # a segment with no building
    overview = OverviewSegments(grid=grid, label_image=labels, ids=np.array([11, 12]),
                                boundary_px=(np.zeros((1, 2), np.int32),) * 2,
                                centroids=np.array([[1011.0, 2007], [1027, 2027]]), polygons=(None, None),
                                ground_height=np.zeros(2), ground_normal=np.tile([0.0, 0, 1], (2, 1)))
    true_labels = np.r_[np.full(50, 7), np.full(50, 9), np.full(50, 9)].astype(np.int32)
    point_labels = np.repeat(np.arange(3), 50).astype(np.int32)
    street = _street(150, point_labels, 3)
    sm = T.segment_match_scores(_matches([0, 0, 1]), street, overview, true_labels, ids, geoms)
    assert sm["n_matched"] == 3 and sm["n_correct"] == 2          # seg 2 → the empty segment is wrong
    assert sm["precision"] == pytest.approx(2 / 3) and sm["recall"] == pytest.approx(2 / 3)
    # strict rule: the merged segment belongs to building 7 only (IoU 100/180 ≥ 0.5; 9 has 80/180)
    assert sm["precision_iou"] == pytest.approx(1 / 3) and sm["recall_iou"] == pytest.approx(1.0)
    assert list(sm["_per_segment"]["correct"]) == [True, True, False]
