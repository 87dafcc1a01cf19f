"""Eq. 5 composition, 2D exhaustive search, 3D ground step and neighbour consistency (unit level)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial.transform import Rotation

from toolkit.capture import StreetCapture
from toolkit.refine.consistency import reject_inconsistent, reject_minor_components, reject_route_minorities
from toolkit.refine.ground3d import GroundParams, HeightGrid, ground_step, trimmed_mean
from toolkit.refine.search2d import SearchParams, search_segment
from toolkit.refine.transforms import apply, compose_eq5, rigid2d, rotation_between
from toolkit.types import Grid


def test_compose_eq5_is_2d_block_times_tilt_with_stacked_translation():
    rng = np.random.default_rng(0)
    theta, t2d, t_z = 0.7, np.array([3.0, -2.0]), 1.5
    R_z = Rotation.from_rotvec([0.02, -0.01, 0.0]).as_matrix()
    T = compose_eq5(rigid2d(theta, t2d), R_z, t_z)
    A = np.eye(3)
    A[:2, :2] = rigid2d(theta, np.zeros(2))[:2, :2]
    assert np.allclose(T[:3, :3], A @ R_z)
    assert np.allclose(T[:3, 3], [*t2d, t_z])
    # about a centre c: c keeps its height change t_z and its 2D image under (R2d, t2d)
    c = rng.normal(size=3) * 50
    Tc = compose_eq5(rigid2d(theta, t2d), R_z, t_z, c)
    assert np.allclose(Tc[:3, :3], A @ R_z)
    assert np.allclose(apply(Tc, c[None])[0], [*(A[:2, :2] @ c[:2] + t2d), c[2] + t_z])


def test_rotation_between_maps_a_onto_b():
    rng = np.random.default_rng(1)
    for _ in range(20):
        a, b = rng.normal(size=3), rng.normal(size=3)
        R = rotation_between(a, b)
        assert np.allclose(R @ (a / np.linalg.norm(a)), b / np.linalg.norm(b))
        assert np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(rotation_between([0, 0, 1.0], [0, 0, -1.0]) @ [0, 0, 1.0], [0, 0, -1.0])


def _building(grid_shape=(300, 300), box=(500040.2, 500070.3, 4400100.1, 4400125.7)):
    g = Grid((0.5, 0, 500000.0, 0, -0.5, 4400150.0), grid_shape[1], grid_shape[0], "EPSG:32617")
    rows, cols = np.mgrid[0:grid_shape[0], 0:grid_shape[1]]
    xy = g.pixel_to_world(rows.ravel(), cols.ravel())
    lab = -np.ones(grid_shape, np.int32)
    inside = (xy[:, 0] > box[0]) & (xy[:, 0] < box[1]) & (xy[:, 1] > box[2]) & (xy[:, 1] < box[3])
    lab.ravel()[inside] = 0
    rr, cc = np.nonzero(lab == 0)
    a, b = g.pixel_to_world(rr.min(), cc.min()), g.pixel_to_world(rr.max(), cc.max())
    edges = (a[0] - 0.25, b[0] + 0.25, b[1] - 0.25, a[1] + 0.25)   # xmin, xmax, ymin, ymax of the mask
    return g, lab, edges


def _l_shape(edges, rng, n=1200, noise=0.05):
    xmin, xmax, ymin, ymax = edges
    south = np.column_stack([rng.uniform(xmin, xmax, 2 * n // 3), np.full(2 * n // 3, ymin)])
    west = np.column_stack([np.full(n // 3, xmin), rng.uniform(ymin, ymax, n // 3)])
    return np.vstack([south, west]) + rng.normal(0, noise, (n, 2))


@pytest.mark.parametrize("dtheta_deg,dxy", [(4.0, (2.0, -1.5)), (-9.0, (-4.0, 3.0)), (0.3, (0.2, 0.1))])
def test_search2d_recovers_a_known_transform(dtheta_deg, dxy):
    rng = np.random.default_rng(2)
    g, lab, edges = _building()
    world = _l_shape(edges, rng)
    T_true = rigid2d(0.7, np.array([500055.0, 4400110.0]))
    street = (world - T_true[:2, 2]) @ T_true[:2, :2]
    seed = rigid2d(0.7 + np.radians(dtheta_deg), T_true[:2, 2] + dxy)
    res = search_segment(street, seed, g, lab, 0, ndimage.find_objects(lab + 1)[0], SearchParams())
    err = np.linalg.norm(street @ res.T2d[:2, :2].T + res.T2d[:2, 2] - world, axis=1)
    assert err.max() < 0.05
    assert res.inlier_ratio > 0.95 and res.cost_m < 0.1 < res.seed_cost_m


def test_search2d_grid_only_is_within_a_pixel_and_a_step():
    rng = np.random.default_rng(3)
    g, lab, edges = _building()
    world = _l_shape(edges, rng)
    T_true = rigid2d(-0.2, np.array([500050.0, 4400120.0]))
    street = (world - T_true[:2, 2]) @ T_true[:2, :2]
    seed = rigid2d(-0.2 + np.radians(5.5), T_true[:2, 2] + [1.3, 2.2])
    res = search_segment(street, seed, g, lab, 0, ndimage.find_objects(lab + 1)[0], SearchParams(subpixel=False))
    err = np.linalg.norm(street @ res.T2d[:2, :2].T + res.T2d[:2, 2] - world, axis=1)
    assert err.max() < 0.5 + 30 * np.radians(0.5)   # half a pixel plus half a degree over the wall


def test_search2d_keeps_the_seed_along_a_single_straight_wall():
    rng = np.random.default_rng(4)
    g, lab, edges = _building()
    xmin, _, ymin, _ = edges
    world = np.column_stack([rng.uniform(xmin + 8, xmin + 16, 500), np.full(500, ymin)])
    street = world - [500000.0, 4400000.0]
    seed = rigid2d(0.0, np.array([500000.0 + 1.0, 4400000.0 + 0.8]))   # 1 m along the wall, 0.8 m off it
    res = search_segment(street, seed, g, lab, 0, ndimage.find_objects(lab + 1)[0], SearchParams())
    moved = street @ res.T2d[:2, :2].T + res.T2d[:2, 2] - world
    assert np.abs(moved[:, 1]).max() < 0.05          # snapped onto the wall
    assert np.allclose(moved[:, 0].mean(), 1.0, atol=0.1)   # no reason to slide along it


def test_search2d_ignores_footprint_parts_missing_from_the_overview():
    rng = np.random.default_rng(5)
    g, lab, edges = _building()
    world = _l_shape(edges, rng)
    clutter = rng.uniform([edges[0], edges[2] - 12], [edges[1], edges[2] - 4], (300, 2))   # 20 % off-wall points
    street = np.vstack([world, clutter]) - [500000.0, 4400000.0]
    seed = rigid2d(np.radians(3.0), np.array([500000.0 + 1.5, 4400000.0 - 1.0]))
    res = search_segment(street, seed, g, lab, 0, ndimage.find_objects(lab + 1)[0], SearchParams())
    err = np.linalg.norm(street[:len(world)] @ res.T2d[:2, :2].T + res.T2d[:2, 2] - world, axis=1)
    assert np.median(err) < 0.05 and err.max() < 0.15


def _ground_patch(rng, n=800):
    xy = rng.uniform([-15, -10], [15, 0], (n, 2))
    return xy


def test_ground_step_recovers_tilt_and_height():
    rng = np.random.default_rng(6)
    g = Grid((0.5, 0, -50.0, 0, -0.5, 50.0), 200, 200, "EPSG:32617")
    rows, cols = np.mgrid[0:200, 0:200]
    wxy = g.pixel_to_world(rows.ravel(), cols.ravel())
    slope = np.array([0.03, -0.01])
    dsm = (230.0 + wxy @ slope).reshape(200, 200)
    dsm[70:98, 80:120] += 12                         # a building block just north of the road (y 1..15 m)
    dsm += rng.normal(0, 0.1, dsm.shape)
    heights = HeightGrid(dsm, g)
    xy = _ground_patch(rng)
    z_true = 230.0 + xy @ slope
    truth = np.column_stack([xy, z_true])
    tilt = Rotation.from_rotvec([0.015, 0.02, 0.0]).as_matrix()       # ~1.4° street tilt
    street = (truth - truth.mean(0)) @ tilt.T + truth.mean(0) - [0, 0, 231.7]
    n_true = np.array([-slope[0], -slope[1], 1.0]) / np.linalg.norm([-slope[0], -slope[1], 1.0])
    normals = np.tile(tilt @ n_true, (len(xy), 1)) + rng.normal(0, 0.02, (len(xy), 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    res = ground_step(street, normals, np.eye(3), heights, np.array([0, 0, 1.0]), np.nan, GroundParams())
    fixed = (street - res.centre) @ res.R_z.T + res.centre + [0, 0, res.t_z]
    assert np.abs(fixed[:, 2] - z_true).max() < 0.15
    assert abs(np.median(fixed[:, 2] - z_true)) < 0.05


def test_ground_step_without_heights_uses_the_overview_height_and_level():
    rng = np.random.default_rng(7)
    xy = _ground_patch(rng)
    street = np.column_stack([xy, np.full(len(xy), 5.0)])
    res = ground_step(street, None, np.eye(3), None, np.array([0, 0, 1.0]), 230.0, GroundParams())
    assert np.allclose(res.R_z, np.eye(3)) and np.isclose(res.t_z, 225.0)
    few = ground_step(street[:5], None, np.eye(3), None, np.array([0, 0, 1.0]), 230.0, GroundParams())
    assert np.isnan(few.t_z)          # too few ground points: left to the neighbours


def test_trimmed_mean_takes_the_10_to_60_percent_slice():
    x = np.arange(100.0)
    assert trimmed_mean(x, 0.1, 0.6) == pytest.approx(np.arange(10, 60).mean())
    assert trimmed_mean(np.array([np.nan, 1.0]), 0.1, 0.6) == 1.0


def _chain(n=8, spacing=30.0, drift_deg_per_seg=0.3):
    """Segments along a drifting route: the street frame's heading error grows along the route,
    so segment i's transform (street → truth) rotates by -heading_i and meets the truth at s_i."""
    s = np.arange(n) * spacing
    truth = np.column_stack([s, np.zeros(n), np.zeros(n)])
    heading = np.radians(drift_deg_per_seg) * np.arange(n)
    street = np.zeros((n, 3))
    for i in range(1, n):      # integrate the drifted steps
        street[i] = street[i - 1] + spacing * np.array([np.cos(heading[i - 1]), np.sin(heading[i - 1]), 0])
    T = np.repeat(np.eye(4)[None], n, axis=0)
    for i in range(n):
        T[i, :3, :3] = Rotation.from_euler("z", -heading[i]).as_matrix()
        T[i, :3, 3] = truth[i] - T[i, :3, :3] @ street[i]
    return street, T


def test_consistency_rejects_the_one_bad_segment_only():
    anchors, T = _chain()
    T[3, :3, 3] += [12.0, 5.0, 0.0]
    valid, score = reject_inconsistent(T, np.ones(len(T), bool), anchors, k=4, tol_m=3.0, tol_ratio=0.05)
    assert valid.tolist() == [True, True, True, False, True, True, True, True]
    assert np.nanmax(score[valid]) <= 1.0


def test_consistency_keeps_a_smoothly_drifting_chain():
    anchors, T = _chain(drift_deg_per_seg=0.8)
    valid, _ = reject_inconsistent(T, np.ones(len(T), bool), anchors, k=4, tol_m=3.0, tol_ratio=0.05)
    assert valid.all()


def test_consistency_rejects_a_self_consistent_group_of_wrong_matches():
    street, T = _chain(n=14)
    for i in (5, 6, 7):                              # matched one block over, all three alike
        T[i, :3, 3] += [0.0, 40.0, 0.0]
    valid = np.ones(len(T), bool)
    greedy, _ = reject_inconsistent(T, valid, street, k=4, tol_m=3.0, tol_ratio=0.05)
    assert greedy[6]                                 # each agrees with its nearest two: survives the median test
    support = np.ones(len(T))
    kept = reject_minor_components(T, greedy, street, support, k=4, tol_m=3.0, tol_ratio=0.05)
    assert not kept[[5, 6, 7]].any() and kept[[0, 1, 2, 3, 4, 8, 9, 10, 11, 12, 13]].all()


def test_consistency_keeps_a_distant_group_it_cannot_compare():
    street, T = _chain(n=8)
    far = street + [0.0, 5000.0, 0.0]               # another, separate street: no neighbour pairs across
    T2 = T.copy()
    T2[:, :3, 3] += [0.0, 777.0, 0.0]
    anchors = np.vstack([street, far])
    kept = reject_minor_components(np.concatenate([T, T2]), np.ones(16, bool), anchors, np.ones(16), k=4,
                                   tol_m=3.0, tol_ratio=0.05)
    assert kept.all()


def test_route_window_outvotes_a_run_of_wrong_matches():
    street, T = _chain(n=20)
    for i in (8, 9, 10, 11):                         # four in a row, all placed one block over
        T[i, :3, 3] += [0.0, 40.0, 0.0]
    valid = np.ones(20, bool)
    local, _ = reject_inconsistent(T, valid, street, k=4, tol_m=3.0, tol_ratio=0.05)
    assert local[[9, 10]].all()                      # the k-nearest test alone keeps the run's middle
    route_s = np.arange(20) * 30.0
    kept = reject_route_minorities(T, local, street, route_s, np.ones(20), 150.0, 3.0, 0.05)
    assert not kept[[8, 9, 10, 11]].any() and kept[[0, 1, 2, 3, 4, 5, 6, 7, 12, 13, 14, 15, 16, 17, 18, 19]].all()
    protected = np.zeros(20, bool)
    protected[[8, 9, 10, 11]] = True
    assert reject_route_minorities(T, local, street, route_s, np.ones(20), 150.0, 3.0, 0.05, protected)[[9, 10]].all()


def test_route_positions_follow_the_cameras_that_observe_each_segment(tmp_path):
    from toolkit.io.cloud import write_ply
    from toolkit.io.colmap import write_model
    from toolkit.refine.route import neighbour_keys, route_positions
    from toolkit.scene import load_scene, write_manifest
    from toolkit.types import Camera, SparseModel, StreetSegments

    rng = np.random.default_rng(0)
    # three segments; the third lies next to the first but is seen at the end of the route
    pts = np.vstack([np.column_stack([rng.uniform(0, 10, 200), np.full(200, 5.0), rng.uniform(0, 5, 200)]),
                     np.column_stack([rng.uniform(40, 50, 200), np.full(200, 5.0), rng.uniform(0, 5, 200)]),
                     np.column_stack([rng.uniform(0, 10, 200), np.full(200, 6.0), rng.uniform(0, 5, 200)])])
    labels = np.repeat(np.arange(3, dtype=np.int32), 200)
    C = np.column_stack([np.r_[np.linspace(0, 50, 51), np.linspace(50, 0, 51)], np.zeros(102), np.zeros(102)])
    seen_by = {0: 5, 1: 45, 2: 97}                       # camera index observing each segment
    obs = np.array([[seen_by[s], 10 * s + j, 100.0, 100.0] for s in range(3) for j in range(10)]
                   + [[seen_by[s] + 1, 10 * s + j, 101.0, 100.0] for s in range(3) for j in range(10)])
    sparse_xyz = np.vstack([pts[200 * s:200 * s + 10] for s in range(3)])
    model = SparseModel(cameras={1: Camera(1, "PINHOLE", 640, 480, np.array([500.0, 500, 320, 240]))},
                        image_names=tuple(f"{k}.jpg" for k in range(102)), image_ids=np.arange(1, 103),
                        camera_ids=np.ones(102, int), R=np.repeat(np.eye(3)[None], 102, axis=0), t=-C,
                        points3d_ids=np.arange(1, 31), points3d=sparse_xyz, points3d_rgb=np.zeros((30, 3), np.uint8),
                        observations=obs.astype(float))
    root = tmp_path / "route"
    (root / "street").mkdir(parents=True)
    write_ply(root / "street/cloud.ply", pts)
    write_model(model, root / "street/sparse", binary=True)
    write_manifest(root, "route", "EPSG:32617", {"street": {"cloud": "street/cloud.ply", "sparse": "street/sparse"}})
    street = StreetSegments(origin=np.zeros(3), up_rotation=np.eye(3), point_labels=labels, carrier=labels.copy(),
                            ids=np.arange(3), boundary_xy=tuple(pts[labels == s, :2] for s in range(3)),
                            centroids=np.array([[5.0, 5.0], [45.0, 5.0], [5.0, 6.0]]), extent_m=np.full(3, 10.0),
                            ground_z=np.zeros(3), ground_normal=np.tile([0, 0, 1.0], (3, 1)))
    s = route_positions(street, StreetCapture(load_scene(root)).sparse, pts)
    assert np.allclose(s, [5.5, 45.5, 97.5 - 0.0], atol=1.0)
    keys = neighbour_keys(np.column_stack([street.centroids, np.zeros(3)]), s)
    d = np.linalg.norm(keys[:, None] - keys[None], axis=2)
    assert d[0, 1] < d[0, 2]                         # the far-along-the-route pass is the farther neighbour


@pytest.mark.parametrize("direct", [True, False])
def test_batched_correlation_equals_the_sum_over_every_offset(direct):
    from toolkit.refine.search2d import _correlate_valid

    rng = np.random.default_rng(11)
    sub = rng.random((23, 31))
    k = np.zeros((5, 9, 12))
    k[rng.random(k.shape) < 0.2] = 1.0
    k *= rng.random(k.shape)
    A, KH, KW = k.shape
    ref = np.array([[[np.sum(sub[i:i + KH, j:j + KW] * k[a]) for j in range(sub.shape[1] - KW + 1)]
                     for i in range(sub.shape[0] - KH + 1)] for a in range(A)])
    got = _correlate_valid(sub, k, max_direct_offsets=10**6 if direct else 0)
    assert got.shape == ref.shape and np.allclose(got, ref, atol=1e-10)


def test_clamped_distance_transform_is_exact_up_to_the_clamp():
    from toolkit.refine.search2d import _clamped_edt

    rng = np.random.default_rng(12)
    for _ in range(15):
        features = rng.random((rng.integers(1, 50), rng.integers(1, 50))) < rng.uniform(0.005, 0.3)
        features[0, 0] |= not features.any()
        clamp = int(rng.integers(1, 8))
        ref = ndimage.distance_transform_edt(~features)
        got = _clamped_edt(features, clamp)
        band = ref <= clamp
        assert np.array_equal(got[band], ref[band])
        assert np.all((got[~band] > clamp) & (got[~band] <= clamp + 1))


def test_outline_field_cut_from_the_whole_grid_matches_a_window_of_its_own():
    from toolkit.refine.search2d import AllOutlines, OutlineField

    g, lab, _ = _building()
    lab[40:60, 200:240] = 1                                   # a second building
    whole = AllOutlines(g, lab, truncate_m=3.0)
    r0, c0, r1, c1 = 20, 60, 160, 260
    cut = whole.field(r0, c0, r1, c1, 3.0)
    own = OutlineField(g, lab[r0:r1, c0:c1] >= 0, r0, c0)
    inner = (slice(8, -8), slice(8, -8))                       # away from the window's edge
    band = np.abs(own.sdf[inner]) <= 3.0 + 2 * g.gsd_m
    assert np.array_equal(cut.sdf[inner][band], own.sdf[inner][band])
    assert np.array_equal(cut.truncated(3.0)[inner], np.minimum(np.abs(own.sdf[inner]), 3.0))
    near = np.abs(own.sdf[inner]) < 1.0 + g.gsd_m
    assert np.allclose(cut.grad_x[inner][near], own.grad_x[inner][near])
    assert whole.field(-1, 0, 10, 10, 3.0) is None             # leaves the image: computed on its own


def test_search_with_the_shared_outline_field_finds_the_same_transform():
    from toolkit.refine.search2d import AllOutlines

    rng = np.random.default_rng(13)
    g, lab, edges = _building()
    world = _l_shape(edges, rng)
    street = world - [500000.0, 4400000.0]
    seed = rigid2d(np.radians(-2.0), np.array([500000.0 - 1.0, 4400000.0 + 2.0]))
    box = ndimage.find_objects(lab + 1)[0]
    own = search_segment(street, seed, g, lab, None, box, SearchParams())
    shared = search_segment(street, seed, g, lab, None, box, SearchParams(), AllOutlines(g, lab, 3.0))
    assert np.allclose(own.T2d, shared.T2d, atol=1e-9) and own.inlier_ratio == shared.inlier_ratio


def test_thinning_by_counting_equals_thinning_by_sorting():
    from toolkit.refine.segments import thin_columns, thin_xy

    rng = np.random.default_rng(14)
    xy = rng.normal(0, 20, (5000, 2)) + [3e5, 4e6]
    cell = np.floor(xy / 0.5).astype(np.int64)
    _, inv, counts = np.unique(cell, axis=0, return_inverse=True, return_counts=True)
    ref = np.column_stack([np.bincount(inv.ravel(), xy[:, 0]), np.bincount(inv.ravel(), xy[:, 1])]) / counts[:, None]
    assert np.array_equal(thin_xy(xy, 0.5, 10**6), ref)
    assert np.array_equal(thin_columns(xy[:, 0].copy(), xy[:, 1].copy(), 0.5, 10**6), ref)
    assert np.array_equal(thin_xy(xy, 0.5, 100), ref[np.linspace(0, len(ref) - 1, 100).astype(np.int64)])
    sparse = np.vstack([xy[:10], xy[:1] + 5e4])                # a key range far too wide to count
    assert len(thin_xy(sparse, 0.5, 10**6)) == len(np.unique(np.floor(sparse / 0.5), axis=0))


def test_outline_tiles_give_the_whole_grid_field():
    from toolkit.refine.search2d import AllOutlines

    g, lab, _ = _building()
    lab[150:170, 20:90] = 3
    one = AllOutlines(g, lab, 3.0, tile_px=1000)              # a single tile: the whole grid at once
    tiled = AllOutlines(g, lab, 3.0, tile_px=37)
    a, b = one.field(5, 7, 290, 280, 3.0), tiled.field(5, 7, 290, 280, 3.0)
    band = np.abs(a.sdf) <= 3.0 + 2 * g.gsd_m
    assert np.array_equal(a.sdf[band], b.sdf[band]) and np.array_equal(a.truncated(3.0), b.truncated(3.0))
    near = np.abs(a.sdf) < 1.0 + g.gsd_m
    assert np.array_equal(a.grad_x[near], b.grad_x[near]) and np.array_equal(a.grad_y[near], b.grad_y[near])


def test_vectorised_consistency_scores_match_a_per_segment_loop():
    from toolkit.refine.consistency import gap_matrix

    rng = np.random.default_rng(15)
    street, T = _chain(n=14)
    T = T.copy()
    T[[3, 9], :3, 3] += rng.normal(0, 4.0, (2, 3))           # two bad ones
    valid = np.ones(14, bool)
    valid[5] = False
    extra = [set() for _ in range(14)]
    extra[0].add(13)
    _, score = reject_inconsistent(T, valid, street, 3, 3.0, 0.05, 2, extra)
    # reference: one segment at a time, on the segments left valid when scoring stopped
    kept, _ = reject_inconsistent(T, valid, street, 3, 3.0, 0.05, 2, extra)
    idx = np.flatnonzero(kept)
    from scipy.spatial import cKDTree
    _, nn = cKDTree(street[idx]).query(street[idx], k=4)
    for row, i in enumerate(idx):
        nb = {int(j) for j in idx[nn[row]] if j != i} | {j for j in extra[i] if kept[j] and j != i}
        nb = np.array(sorted(nb))
        gaps = gap_matrix(T, street, np.column_stack([np.full(len(nb), i), nb]))
        ref = np.percentile(gaps / (3.0 + 0.05 * np.linalg.norm(street[nb] - street[i], axis=1)), 50, method="lower")
        assert score[i] == pytest.approx(ref)


def test_route_position_comes_from_the_facade_not_the_ground_it_carries(tmp_path):
    """Where the route loops back, the later pass's ground is carried by the earlier pass's façade
    next to it: the segment's route position is still where its façade was seen; a segment without
    a façade point near a sparse one takes its position from what it carries."""
    from toolkit.io.cloud import write_ply
    from toolkit.io.colmap import write_model
    from toolkit.refine.route import route_positions
    from toolkit.scene import load_scene, write_manifest
    from toolkit.types import Camera, SparseModel, StreetSegments

    rng = np.random.default_rng(3)
    facade0 = np.column_stack([rng.uniform(0, 10, 100), np.full(100, 5.0), rng.uniform(0, 5, 100)])
    ground0 = np.column_stack([rng.uniform(0, 10, 300), rng.uniform(0, 4, 300), np.zeros(300)])
    facade1 = np.column_stack([rng.uniform(40, 50, 100), np.full(100, 5.0), rng.uniform(0, 5, 100)])
    ground1 = np.column_stack([rng.uniform(40, 50, 100), rng.uniform(0, 4, 100), np.zeros(100)])
    pts = np.vstack([facade0, ground0, facade1, ground1])
    labels = np.concatenate([np.zeros(100), np.full(300, -1), np.ones(100), np.full(100, -1)]).astype(np.int32)
    carrier = np.concatenate([np.zeros(400), np.ones(200)]).astype(np.int32)
    C = np.column_stack([np.r_[np.linspace(0, 50, 51), np.linspace(50, 0, 51)], np.zeros(102), np.zeros(102)])
    # segment 0: 5 façade points seen at s = 5 m, 20 of its ground points seen again at s ≈ 95 m;
    # segment 1: only ground points near sparse ones, seen at s = 45 m
    sparse_rows = np.r_[0:5, 100:120, 500:510]
    cam_of = np.r_[np.full(5, 5), np.full(20, 96), np.full(10, 45)]
    obs = np.array([[c + k, j, 100.0, 100.0] for j, c in enumerate(cam_of) for k in (0, 1)])
    model = SparseModel(cameras={1: Camera(1, "PINHOLE", 640, 480, np.array([500.0, 500, 320, 240]))},
                        image_names=tuple(f"{k}.jpg" for k in range(102)), image_ids=np.arange(1, 103),
                        camera_ids=np.ones(102, int), R=np.repeat(np.eye(3)[None], 102, axis=0), t=-C,
                        points3d_ids=np.arange(1, len(sparse_rows) + 1), points3d=pts[sparse_rows],
                        points3d_rgb=np.zeros((len(sparse_rows), 3), np.uint8), observations=obs.astype(float))
    root = tmp_path / "route"
    (root / "street").mkdir(parents=True)
    write_ply(root / "street/cloud.ply", pts)
    write_model(model, root / "street/sparse", binary=True)
    write_manifest(root, "route", "EPSG:32617", {"street": {"cloud": "street/cloud.ply", "sparse": "street/sparse"}})
    street = StreetSegments(origin=np.zeros(3), up_rotation=np.eye(3), point_labels=labels, carrier=carrier,
                            ids=np.arange(2), boundary_xy=(facade0[:, :2], facade1[:, :2]),
                            centroids=np.array([[5.0, 5.0], [45.0, 5.0]]), extent_m=np.full(2, 10.0),
                            ground_z=np.zeros(2), ground_normal=np.tile([0, 0, 1.0], (2, 1)))
    s = route_positions(street, StreetCapture(load_scene(root)).sparse, pts)
    assert np.allclose(s, [5.5, 45.5], atol=1.0), s
