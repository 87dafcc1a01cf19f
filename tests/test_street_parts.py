"""Unit tests of the street segmentation helpers (toolkit/street/*)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from toolkit.errors import StageError
from toolkit.street.absorb import absorb_leftovers
from toolkit.street.associate import ground_statistics, group_median, nearest_segment
from toolkit.street.growing import components, grow_regions
from toolkit.street.merge import merge_segments
from toolkit.street.normals import coordinate_columns, neighbourhood_covariance, symmetric_eigenvalues
from toolkit.street.order import morton_codes, prepare
from toolkit.street.outline import boundary_points, diameters, relabel_by_size
from toolkit.street.score import angle_deg, score_segments
from toolkit.testing.street_toy import random_rotation
from toolkit.street.vertical import estimate_up, fibonacci_sphere
from toolkit.types import StreetSegments


def test_morton_codes_interleave_bits():
    cells = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [2, 0, 0]])
    assert morton_codes(cells).tolist() == [1, 2, 4, 7, 8]


def test_prepare_sorts_and_inverts():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 50, (5000, 3)) + [4e5, 5e6, 100]
    origin = np.median(pts, axis=0)
    cloud = prepare(pts, origin, 0.0, "who")
    np.testing.assert_allclose(cloud.points[cloud.inverse], pts - origin)
    # consecutive points of the Morton order are much closer than random pairs
    step = np.linalg.norm(np.diff(cloud.points, axis=0), axis=1).mean()
    assert step < 0.5 * np.linalg.norm(np.diff(pts, axis=0), axis=1).mean()


def test_prepare_voxel_centroids():
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.02, 0.01], [0.51, 0.01, 0.01], [5.0, 5.0, 5.0]])
    cloud = prepare(pts, np.zeros(3), 0.1, "who")
    assert len(cloud.points) == 3
    assert cloud.inverse[0] == cloud.inverse[1] != cloud.inverse[2]
    np.testing.assert_allclose(cloud.points[cloud.inverse[0]], [0.02, 0.015, 0.01])
    with pytest.raises(StageError, match="voxel_m"):
        prepare(np.array([[0.0, 0, 0], [1e6, 0, 0]]), np.zeros(3), 0.1, "steps.street")


def test_eigenvalues_match_numpy():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(500, 3, 3))
    cov = a @ a.transpose(0, 2, 1)
    cov[:3] = np.diag([2.0, 2.0, 2.0])  # degenerate: all equal
    np.testing.assert_allclose(symmetric_eigenvalues(cov), np.linalg.eigvalsh(cov), atol=1e-9)


def test_neighbourhood_covariance_matches_numpy():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(200, 3)) + [1e3, 2e3, 0]
    idx = rng.integers(0, 200, (30, 12))
    cov = neighbourhood_covariance(coordinate_columns(pts - pts.mean(axis=0)), idx)
    want = np.stack([np.cov(pts[i].T, bias=True) for i in idx])
    np.testing.assert_allclose(cov, want, atol=1e-5)


def _box_world(rng: np.random.Generator, n: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """Ground plane and walls in two directions with their exact normals (z up)."""
    g = np.c_[rng.uniform(-40, 40, (n, 2)), rng.normal(0, 0.02, n)]
    gn = np.tile([0.0, 0.0, 1.0], (n, 1))
    wx = np.c_[rng.uniform(-40, 40, n // 2), np.full(n // 2, 12.0), rng.uniform(0, 10, n // 2)]
    wy = np.c_[np.full(n // 2, -15.0), rng.uniform(-40, 40, n // 2), rng.uniform(0, 10, n // 2)]
    pts = np.concatenate([g, wx, wy])
    normals = np.concatenate([gn, np.tile([0, 1.0, 0], (n // 2, 1)), np.tile([1.0, 0, 0], (n // 2, 1))])
    normals += rng.normal(0, 0.03, normals.shape)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals *= rng.choice([-1.0, 1.0], (len(normals), 1))  # PCA normals have no sign
    return pts, normals


@pytest.mark.parametrize("seed", range(6))
def test_estimate_up_finds_axis_and_sign(seed):
    rng = np.random.default_rng(seed)
    pts, normals = _box_world(rng)
    rot = random_rotation(rng, 180.0 if seed % 2 else 45.0)  # odd seeds: any orientation at all
    v = estimate_up(pts @ rot.T, normals @ rot.T)
    assert v is not None
    assert angle_deg(v.up, rot @ [0, 0, 1.0]) < 0.3
    assert v.agreement > 0.9


def test_estimate_up_without_structure_has_low_support():
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(20000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    v = estimate_up(rng.normal(size=(20000, 3)), normals)
    assert v is None or v.support < 0.2


def test_fibonacci_sphere_is_unit_and_even():
    s = fibonacci_sphere(2000)
    np.testing.assert_allclose(np.linalg.norm(s, axis=1), 1.0)
    assert abs(s[:, 2].mean()) < 1e-3


@pytest.mark.parametrize("seed", range(3))
def test_components_match_scipy(seed):
    rng = np.random.default_rng(seed)
    n, k = 3000, 6
    idx = np.clip(np.arange(n)[:, None] + rng.integers(-40, 40, (n, k)), 0, n - 1).astype(np.int32)
    keep = rng.random((n, k)) < 0.15
    indptr = np.concatenate([[0], np.cumsum(keep.sum(axis=1))])
    ours = components(n, indptr, idx[keep])
    graph = csr_matrix((np.ones(int(keep.sum())), idx[keep], indptr), shape=(n, n))
    count, theirs = connected_components(graph, directed=False)
    assert len(np.unique(ours)) == count
    assert len(np.unique(ours.astype(np.int64) * n + theirs)) == count  # same partition
    assert np.array_equal(ours, theirs)  # and numbered the same way


def _planes_graph(pts: np.ndarray, normals: np.ndarray, k: int = 10):
    from scipy.spatial import cKDTree

    _, idx = cKDTree(pts).query(pts, k=k + 1)
    return idx[:, 1:].astype(np.int32)


def test_grow_regions_splits_sharp_corner():
    rng = np.random.default_rng(4)
    a = np.c_[rng.uniform(0, 10, 4000), np.zeros(4000), rng.uniform(0, 6, 4000)]
    b = np.c_[np.zeros(4000), rng.uniform(0.05, 10, 4000), rng.uniform(0, 6, 4000)]
    pts = np.concatenate([a, b])
    normals = np.concatenate([np.tile([0, 1.0, 0], (4000, 1)), np.tile([1.0, 0, 0], (4000, 1))]).astype(np.float32)
    graph = _planes_graph(pts, normals)
    az = np.arctan2(normals[:, 1], normals[:, 0])
    labels = grow_regions(normals, graph, np.arange(len(pts)), len(pts), np.zeros(len(pts), np.float32),
                          10.0, 0.1, az, 30.0)
    assert labels[0] != labels[4000]
    assert len(np.unique(labels[:4000])) == 1 and len(np.unique(labels[4000:])) == 1


def test_grow_regions_cuts_curved_facade_by_bend():
    rng = np.random.default_rng(5)
    theta = rng.uniform(0, np.pi, 20000)  # a half cylinder of radius 20 m: smooth, bends 180°
    z = rng.uniform(0, 6, 20000)
    pts = np.c_[20 * np.cos(theta), 20 * np.sin(theta), z]
    normals = np.c_[np.cos(theta), np.sin(theta), np.zeros_like(theta)].astype(np.float32)
    graph = _planes_graph(pts, normals)
    labels = grow_regions(normals, graph, np.arange(len(pts)), len(pts), np.zeros(len(pts), np.float32),
                          10.0, 0.1, theta, 180.0)
    assert len(np.unique(labels)) == 1  # no bend limit: one smooth region
    labels = grow_regions(normals, graph, np.arange(len(pts)), len(pts), np.zeros(len(pts), np.float32),
                          10.0, 0.1, theta, 30.0)
    for lab in np.unique(labels):
        t = theta[labels == lab]
        assert np.ptp(t) <= np.radians(30) + 0.05
    assert len(np.unique(labels)) >= 6


def test_grow_regions_rough_points_join_their_neighbours():
    rng = np.random.default_rng(6)
    pts = np.c_[rng.uniform(0, 10, 3000), np.zeros(3000), rng.uniform(0, 6, 3000)]
    normals = np.tile(np.float32([0, 1, 0]), (3000, 1))
    curv = np.where(rng.random(3000) < 0.2, 0.3, 0.01).astype(np.float32)
    labels = grow_regions(normals, _planes_graph(pts, normals), np.arange(3000), 3000, curv, 10.0, 0.1,
                          np.full(3000, np.pi / 2), 30.0)
    assert (labels >= 0).all() and len(np.unique(labels)) == 1


def _wall(rng, start, end, height, n):
    t = rng.uniform(0, 1, n)
    xy = np.asarray(start) + t[:, None] * (np.asarray(end) - np.asarray(start))
    z = rng.uniform(0, height, n)
    z[:20] = height  # the wall top is seen
    d = np.asarray(end, float) - start
    return xy, z, np.full(n, np.arctan2(d[0], -d[1]))


def test_absorb_leftovers_follows_agreeing_short_links_only():
    """A wall row x = 0..19 (0.3 m apart): points 0-9 in segment 0, fragment 10-14 left over with the
    wall's normal, 15-16 turned 60°, 17-19 beyond a 2 m gap. Graph: each point's 2 nearest on the row."""
    from scipy.spatial import cKDTree

    x = np.concatenate([np.arange(17) * 0.3, 16 * 0.3 + 2.0 + np.arange(3) * 0.3])
    xyz = np.column_stack([x, np.zeros(20), np.full(20, 3.0)])
    normals = np.tile([0.0, 1.0, 0.0], (20, 1))
    normals[15:17] = [np.sin(np.radians(60)), np.cos(np.radians(60)), 0.0]
    _, nn = cKDTree(xyz).query(xyz, k=3)
    graph = nn[:, 1:].astype(np.int32)
    labels = np.full(20, -1, np.int32)
    labels[:10] = 0
    index = np.arange(20, dtype=np.int32)
    out = absorb_leftovers(labels, graph, index, 20, xyz, normals, 20.0, 1.0, hops=10)
    assert out[:15].tolist() == [0] * 15  # the agreeing fragment, hop by hop
    assert out[15:].tolist() == [-1] * 5  # turned normals stop it; the gap is longer than a link
    assert absorb_leftovers(labels, graph, index, 20, xyz, normals, 20.0, 1.0, hops=2)[:15].tolist() \
        == [0] * 12 + [-1] * 3  # two links reach two points further
    assert absorb_leftovers(labels, graph, index, 20, xyz, normals, 20.0, 1.0, hops=0).tolist() == labels.tolist()
    normals[15:17] = normals[0]  # now agreeing: absorbed up to the gap only
    _, nn = cKDTree(xyz).query(xyz, k=4)  # 3 neighbours: point 17 is linked to 16 across the gap
    graph = nn[:, 1:].astype(np.int32)
    out = absorb_leftovers(labels, graph, index, 20, xyz, normals, 20.0, 1.0, hops=10)
    assert out.tolist() == [0] * 17 + [-1] * 3
    out = absorb_leftovers(labels, graph, index, 20, xyz, normals, 20.0, 2.5, hops=10)
    assert out.tolist() == [0] * 20


def test_merge_at_corners_joins_one_building_only():
    rng = np.random.default_rng(7)
    parts = [_wall(rng, (0, 0), (10, 0), 9.0, 2000),       # building A, front
             _wall(rng, (10, 0.3), (10, 4), 9.0, 800),     # building A, side wall round the corner
             _wall(rng, (10.6, 0), (20, 0), 7.0, 2000),    # building B: touches A's side wall, lower
             _wall(rng, (0, 0.4), (0, 6), 15.0, 800),      # building C: meets A at a corner, higher
             _wall(rng, (-10.6, 0), (-0.6, 0), 9.0, 2000)]  # building D: as high as A, in line with it
    xy = np.concatenate([p[0] for p in parts])
    z = np.concatenate([p[1] for p in parts])
    az = np.concatenate([p[2] for p in parts])
    labels = np.repeat(np.arange(5), [2000, 800, 2000, 800, 2000]).astype(np.int32)
    out = merge_segments(xy, z, az, labels, 1.0, 0.0, 1.0, 45.0, 30)
    seg = [out[labels == i][0] for i in range(5)]
    assert seg[0] == seg[1]
    assert len({seg[0], seg[2], seg[3], seg[4]}) == 4
    assert np.array_equal(merge_segments(xy, z, az, labels, 0.0, 0.0, 1.0, 45.0, 30), labels)


def test_merge_segments_joins_pieces_of_one_wall():
    rng = np.random.default_rng(8)
    parts = [_wall(rng, (0, 0), (10, 0), 9.0, 2000),       # one wall, occluded between x = 10 and 11.5
             _wall(rng, (11.5, 0), (20, 0), 9.0, 2000),
             _wall(rng, (21.5, 0.8), (30, 0.8), 9.0, 2000),  # a step of 0.8 m: another façade
             _wall(rng, (-3, 0), (-1.5, 0), 5.0, 500)]       # in line but lower: another building
    xy = np.concatenate([p[0] for p in parts])
    z = np.concatenate([p[1] for p in parts])
    az = np.concatenate([p[2] for p in parts])
    labels = np.repeat(np.arange(4), [2000, 2000, 2000, 500]).astype(np.int32)
    out = merge_segments(xy, z, az, labels, 1.0, 2.0, 1.0, 45.0, 30)
    seg = [out[labels == i][0] for i in range(4)]
    assert seg[0] == seg[1] and len({seg[0], seg[2], seg[3]}) == 3
    off = merge_segments(xy, z, az, labels, 1.0, 0.0, 1.0, 45.0, 30)
    assert len(np.unique(off)) == 4


def test_outline_helpers():
    rng = np.random.default_rng(8)
    xy = rng.uniform(0, 10, (3000, 2))
    labels = rng.integers(0, 3, 3000)
    d = diameters(xy, labels, 3)
    for i in range(3):
        p = xy[labels == i]
        brute = np.max(np.linalg.norm(p[:, None] - p[None], axis=2))
        assert brute * 0.99 <= d[i] <= brute + 1e-9
    b = boundary_points(xy, labels, 3, 0.5, 50)
    assert [len(x) for x in b] == [50, 50, 50]
    assert boundary_points(xy, labels, 3, 0.5, 50)[1].tobytes() == b[1].tobytes()
    lab = np.array([5, 5, -1, 2, 2, 2, 7])
    assert relabel_by_size(lab).tolist() == [1, 1, -1, 0, 0, 0, 2]


def test_group_median_and_ground_statistics():
    rng = np.random.default_rng(9)
    v = rng.normal(size=1001)
    g = rng.integers(-1, 4, 1001)
    med = group_median(v, g, 5)
    for i in range(4):
        assert med[i] == pytest.approx(np.median(v[g == i]))
    assert np.isnan(med[4])
    z, n = ground_statistics(v, np.tile([0.1, 0.0, 1.0], (1001, 1)), g, 5)
    np.testing.assert_array_equal(z, med)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    assert n[4].tolist() == [0.0, 0.0, 1.0]


def test_nearest_segment_respects_radius():
    pts = np.array([[0.0, 0, 5], [9.0, 0, 0], [100.0, 0, 0]])
    seg_xy = np.array([[0.0, 1.0], [10.0, 0.0]])
    out = nearest_segment(pts, np.eye(3)[:2], seg_xy, np.array([3, 4]), radius_m=20.0)
    assert out.tolist() == [3, 4, -1]


def test_score_segments_counts_precision_recall_and_coverage():
    pts = np.c_[np.linspace(0, 20, 10), np.zeros(10), np.zeros(10)]
    truth = np.array([0, 0, 0, 0, 1, 1, 1, -1, -1, -2])
    pred = np.array([0, 0, 0, -2, 1, 1, 0, -1, -1, 1])
    seg = StreetSegments(origin=np.zeros(3), up_rotation=np.eye(3), point_labels=pred, carrier=pred,
                         ids=np.arange(2), boundary_xy=(np.zeros((1, 2)),) * 2, centroids=np.zeros((2, 2)),
                         extent_m=np.ones(2), ground_z=np.zeros(2), ground_normal=np.tile([0, 0, 1.0], (2, 1)))
    s = score_segments(seg, truth, pts, min_facade_m=5.0)
    assert s.facade_precision == pytest.approx(6 / 7)
    assert s.facade_recall == pytest.approx(6 / 7)
    assert s.buildings_eligible == 1  # building 1 spans 4.4 m only
    assert s.buildings_covered == 0  # segment 0 is 3/4 building 0: not ≥ 95 % pure
    assert s.segments_pure == 0
