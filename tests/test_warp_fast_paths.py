"""The warp's fast paths give exactly (bit for bit) what their plain definitions give, on random input.

Plain definitions: KD-tree queries per footprint, a ``np.unique`` of (anchor, cell) keys, the
per-segment neighbour search, ``StreetSegments.level``.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from toolkit.refine.consistency import gap_matrix
from toolkit.refine.segments import input_anchors
from toolkit.types import SegmentTransforms, StreetSegments
from toolkit.warp.blend import blend_points, footprint_distances, inverse_log_weights, point_distances
from toolkit.arrays import column_bounds, dense_rank
from toolkit.warp.cells import cell_blocks, levelled_xy
from toolkit.warp.index import SegmentIndex, footprint_gaps


def _random_street(seed: int, n_seg: int = 14, n_points: int = 30_000):
    """Segments scattered along a 300 m street (footprints of 1–150 points), far from the origin
    and tilted like a real street frame; some transforms invalid, some points without a carrier."""
    rng = np.random.default_rng(seed)
    centres = np.column_stack([np.linspace(0, 300, n_seg), rng.uniform(-15, 15, n_seg)])
    boundary = tuple(c + rng.normal(0, rng.uniform(1, 12), (int(rng.integers(1, 150)), 2)) for c in centres)
    carrier = rng.integers(-1, n_seg, n_points).astype(np.int32)
    xy = np.where(carrier[:, None] >= 0, centres[np.maximum(carrier, 0)], rng.uniform(0, 300, (n_points, 2)))
    xy = xy + rng.normal(0, 8, (n_points, 2))
    up = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
    origin = np.array([512_345.6, 4_400_123.4, 87.0])
    levelled = np.column_stack([xy, rng.uniform(0, 12, n_points)])
    points = levelled @ up + origin
    street = StreetSegments(
        origin=origin, up_rotation=up, point_labels=carrier.copy(), carrier=carrier, ids=np.arange(n_seg),
        boundary_xy=boundary, centroids=np.array([b.mean(axis=0) for b in boundary]),
        extent_m=np.full(n_seg, 20.0), ground_z=np.zeros(n_seg), ground_normal=np.tile([0, 0, 1.0], (n_seg, 1)))
    # one street-to-scene motion, disturbed per segment about the segment (metres at the segments)
    base = np.eye(4)
    base[:3, :3] = Rotation.from_euler("z", rng.uniform(0, 360), degrees=True).as_matrix()
    base[:3, 3] = [480_000.0, 4_300_000.0, 10.0]
    T = np.repeat(base[None], n_seg, axis=0)
    at = np.column_stack([centres, np.zeros(n_seg)]) @ up + origin
    for i in range(n_seg):
        d = np.eye(4)
        d[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.003, 3)).as_matrix()
        d[:3, 3] = at[i] - d[:3, :3] @ at[i] + rng.normal(0, 0.7, 3)
        T[i] = base @ d
    valid = rng.uniform(size=n_seg) > 0.2
    valid[0] = True
    transforms = SegmentTransforms(T=T, valid=valid, cost=np.zeros(n_seg), confidence=np.ones(n_seg))
    return street, transforms, points


def test_dense_rank_counts_or_sorts_like_unique():
    rng = np.random.default_rng(0)
    for n_keys in (50, 10**9):                      # counting, then the np.unique fallback
        key = rng.integers(0, n_keys, 5000)
        occupied, rank = dense_rank(key, n_keys)
        uniq, inv = np.unique(key, return_inverse=True)
        assert np.array_equal(occupied, uniq) and np.array_equal(rank, inv.ravel())


@pytest.mark.parametrize("spread_m", [30.0, 3e5], ids=["dense", "sparse"])
def test_cell_blocks_group_points_like_a_unique_of_anchor_and_cell(spread_m):
    rng = np.random.default_rng(1)
    xy = rng.uniform(-spread_m, spread_m, (20000, 2))
    xy[:100] = rng.uniform(-1, 1, (100, 2))           # some cells with several anchors
    anchors = rng.choice([-3, 0, 2, 7, 40], len(xy))
    blocks = cell_blocks(xy, anchors, 0.5)
    ij = np.floor(xy / 0.5).astype(np.int64)
    uniq, inv = np.unique(np.column_stack([anchors, ij]), axis=0, return_inverse=True)
    assert np.array_equal(blocks.rows, inv.ravel())
    assert np.array_equal(blocks.anchor, uniq[:, 0]) and np.array_equal(blocks.cells_ij[blocks.cell], uniq[:, 1:])
    assert np.array_equal(blocks.table[:, 1:], (uniq[:, 1:] + 0.5) * 0.5)
    assert [r[0] for r in blocks.anchor_ranges()] == [-3, 0, 2, 7, 40]


def test_column_bounds_are_min_and_max():
    rng = np.random.default_rng(2)
    for n in (1, 7, 512, 1023, 5000):
        v = rng.normal(size=(n, 2)) * 100
        lo, hi = column_bounds(v)
        assert np.array_equal(lo, v.min(axis=0)) and np.array_equal(hi, v.max(axis=0))


def test_levelled_xy_is_the_levelled_frame():
    # Bit-equal with this numpy/BLAS build (checked when it was written); a BLAS that sums the
    # 3-term products in another order may differ in the last bit, which no output depends on.
    street, _, points = _random_street(3)
    for chunk in (1 << 16, 1000, 7):
        np.testing.assert_allclose(levelled_xy(street, points, chunk), street.level(points)[:, :2],
                                   rtol=1e-14, atol=1e-9)


def test_brute_force_footprint_distances_equal_kd_tree_queries():
    rng = np.random.default_rng(4)
    footprints = [rng.normal(c, s, (n, 2)) for c, s, n in ((50, 3, 40), (-20, 10, 1), (5, 30, 150), (70, 1, 2))]
    cells = rng.integers(-300, 300, (3000, 2))
    xy = rng.uniform(-200, 200, (3000, 2))
    cell_m = 0.5
    by_cell = footprint_distances(cells, cell_m, footprints, chunk_elems=4096)
    by_point = point_distances(xy, footprints, chunk_elems=4096)
    for col, fp in enumerate(footprints):
        tree = cKDTree(fp)
        # bit-equal with scipy 1.17 (no fused multiply-add in its distance); last-bit tolerance otherwise
        np.testing.assert_allclose(by_cell[:, col], tree.query((cells + 0.5) * cell_m)[0], rtol=1e-14)
        np.testing.assert_allclose(by_point[:, col], tree.query(xy)[0], rtol=1e-14)


def test_footprint_gaps_are_the_least_distances_between_footprints():
    rng = np.random.default_rng(5)
    fps = [rng.normal(rng.uniform(0, 100, 2), 5, (int(rng.integers(1, 60)), 2)) for _ in range(6)]
    start = np.concatenate([[0], np.cumsum([len(f) for f in fps])])
    trees = {i: cKDTree(f) for i, f in enumerate(fps)}
    owner = np.array([0, 0, 1, 3, 3, 3, 5])
    other = np.array([1, 4, 0, 0, 2, 5, 4])
    gap = footprint_gaps(owner, other, np.concatenate(fps), start, trees)
    plain = [trees[j].query(fps[i])[0].min() for i, j in zip(owner, other)]
    assert np.array_equal(gap, plain)


def _plain_neighbours(street, transforms, k, agree_tol_m, agree_ratio, max_gap_m, index):
    """The per-segment neighbour search (one centre query and one KD query per pair)."""
    valid = index.valid
    cent = np.asarray(street.centroids, np.float64)[valid]
    ctree = cKDTree(cent)
    anchors = input_anchors(street)
    out = {}
    for row, i in enumerate(valid):
        pre = valid[np.atleast_1d(ctree.query(cent[row], k=min(3 * k + 1, len(valid)))[1])]
        pre = pre[pre != i]
        if np.isfinite(agree_tol_m) and len(pre):
            disagree = gap_matrix(transforms.T, anchors, np.column_stack([np.full(len(pre), i), pre]))
            dist = np.linalg.norm(anchors[pre] - anchors[i], axis=1)
            pre = pre[disagree <= agree_tol_m + agree_ratio * dist]
        gap = np.array([index.trees[int(j)].query(index.trees[int(i)].data)[0].min() for j in pre])
        order = np.argsort(gap, kind="stable")[:k]
        out[int(i)] = pre[order][gap[order] <= max_gap_m]
    return out


@pytest.mark.parametrize("k, agree_tol_m, max_gap_m", [(2, np.inf, np.inf), (4, 3.0, np.inf), (8, 1.0, 20.0),
                                                      (30, np.inf, 5.0)])
def test_segment_neighbours_match_the_per_segment_search(k, agree_tol_m, max_gap_m):
    street, transforms, _ = _random_street(6)
    index = SegmentIndex.build(street, transforms, k, agree_tol_m=agree_tol_m, agree_ratio=0.05, max_gap_m=max_gap_m)
    plain = _plain_neighbours(street, transforms, k, agree_tol_m, 0.05, max_gap_m, index)
    assert index.neighbours.keys() == plain.keys()
    for i, nb in plain.items():
        assert np.array_equal(index.neighbours[i], nb) and index.neighbours[i].dtype == nb.dtype


def test_anchors_by_lookup_equal_the_general_rule():
    street, transforms, points = _random_street(7)
    index = SegmentIndex.build(street, transforms, 4)
    xy = street.level(points)[:, :2]
    carrier = np.asarray(street.carrier, np.int64)
    odd = carrier.copy()
    odd[::50] = len(carrier) + 5                     # out of range: the general path, nearest segment
    for c in (carrier, odd):
        ok = (c >= 0) & (c < len(transforms.valid))
        ok[ok] = transforms.valid[c[ok]]
        plain = np.where(ok, c, index.all_seg[index.all_tree.query(xy)[1]])
        assert np.array_equal(index.anchors(xy, c, transforms.valid), plain)


@pytest.mark.parametrize("cell_m", [0.5, 1.0, 8.0])
def test_nearest_segment_by_cells_equals_per_point_queries(cell_m):
    street, transforms, _ = _random_street(9)
    index = SegmentIndex.build(street, transforms, 4)
    rng = np.random.default_rng(9)
    xy = np.vstack([rng.uniform(-30, 330, (40000, 2)), rng.normal(street.centroids[3], 2, (20000, 2))])
    plain = index.all_seg[index.all_tree.query(xy)[1]]
    assert len(np.unique(plain)) > 5
    assert np.array_equal(index.nearest(xy, cell_m), plain)


def _plain_blend(points, xy, anchors, T, index, k, d_min, cell_m):
    """Cell-wise Eq. 6 as first written: unique (anchor, cell) keys, KD queries per anchor."""
    ij = np.floor(xy / cell_m).astype(np.int64)
    uniq, rows = np.unique(np.column_stack([anchors, ij]), axis=0, return_inverse=True)
    rows = rows.ravel()
    origin = T[index.valid, :3, 3].mean(axis=0)
    A, b = np.empty((len(uniq), 3, 3)), np.empty((len(uniq), 3))
    for a in np.unique(uniq[:, 0]):
        sel = np.flatnonzero(uniq[:, 0] == a)
        cand = index.candidates(int(a), k)
        if len(cand) == 1:
            A[sel], b[sel] = T[cand[0], :3, :3], T[cand[0], :3, 3] - origin
            continue
        w = inverse_log_weights(index.distances(cand, (uniq[sel, 1:] + 0.5) * cell_m), d_min)
        w /= w.sum(axis=1, keepdims=True)
        A[sel] = np.einsum("uk,kab->uab", w, T[cand, :3, :3])
        b[sel] = w @ (T[cand, :3, 3] - origin)
    return np.einsum("nab,nb->na", A[rows], points) + b[rows] + origin


@pytest.mark.parametrize("k", [1, 4, 8])
def test_blend_points_equal_the_plain_cell_blend_bit_for_bit(k):
    street, transforms, points = _random_street(8)
    T = np.asarray(transforms.T)
    index = SegmentIndex.build(street, transforms, k, agree_tol_m=3.0, agree_ratio=0.05)
    xy = levelled_xy(street, points)
    anchors = index.anchors(xy, street.carrier, transforms.valid)
    fast = blend_points(points, xy, anchors, T, index, k, 1.5, cell_m=0.5, chunk=4096)
    assert np.array_equal(fast, _plain_blend(points, xy, anchors, T, index, k, 1.5, 0.5))


def test_neighbours_of_another_pass_of_the_route_are_left_out():
    street, transforms, _ = _random_street(6)
    k = 4
    plain = SegmentIndex.build(street, transforms, k)
    S = len(street)
    route_s = np.arange(S, dtype=np.float64) * 100.0          # segment i captured at 100·i m
    route_s[1] = np.nan                                       # unknown: never excluded
    index = SegmentIndex.build(street, transforms, k, route_s=route_s, route_gap_m=250.0)
    for i, nb in index.neighbours.items():
        with np.errstate(invalid="ignore"):
            assert not np.any(np.abs(route_s[nb] - route_s[i]) > 250.0)
        # the same search among the same-pass candidates: a subset of the plain candidates' order
        same = [j for j in plain.neighbours[i] if not abs(route_s[j] - route_s[i]) > 250.0]
        assert list(nb[:len(same)]) == same[:len(nb)] or set(same) <= set(nb)
    assert SegmentIndex.build(street, transforms, k, route_s=route_s).neighbours.keys() == plain.neighbours.keys()
    for i, nb in SegmentIndex.build(street, transforms, k, route_s=route_s).neighbours.items():
        assert np.array_equal(nb, plain.neighbours[i])       # no gap given: unchanged


def test_camera_spread_is_zero_for_agreeing_transforms_and_grows_with_disagreement():
    from toolkit.warp.blend import blend_rigid

    street, transforms, points = _random_street(4)
    index = SegmentIndex.build(street, transforms, 4)
    cams = points[:50]
    xy = street.level(cams)[:, :2]
    anchors = index.nearest(xy)
    same = np.repeat(transforms.T[index.valid[:1]], len(transforms.T), axis=0)
    pos, R, spread = blend_rigid(cams, xy, anchors, same, index, 4, 1.5)
    assert np.allclose(spread, 0.0, atol=1e-6)
    assert np.allclose(pos, cams @ same[0, :3, :3].T + same[0, :3, 3])
    off = same.copy()
    off[index.valid[1::2], :3, 3] += [0.0, 2.0, 0.0]          # every other segment placed 2 m off
    _, _, spread2 = blend_rigid(cams, xy, anchors, off, index, 4, 1.5)
    assert np.all(spread2 <= 1.0 + 1e-9) and spread2.max() > 0.3    # ≤ half the gap, weighted RMS


def _flat_street(boundaries: tuple[np.ndarray, ...], centroids: np.ndarray) -> StreetSegments:
    """Segments given by their 2-D footprints only, in an unlevelled frame (no points)."""
    labels = np.zeros(0, np.int32)
    n = len(boundaries)
    return StreetSegments(origin=np.zeros(3), up_rotation=np.eye(3), point_labels=labels, carrier=labels,
                          ids=np.arange(n), boundary_xy=boundaries, centroids=np.asarray(centroids, np.float64),
                          extent_m=np.array([np.linalg.norm(np.ptp(b, axis=0)) for b in boundaries]),
                          ground_z=np.zeros(n), ground_normal=np.tile([0.0, 0.0, 1.0], (n, 1)))


def test_a_small_fragment_weighs_less_at_a_camera_far_from_its_centre():
    """A camera 6 m off a 40 m façade (exact transform) and 19 m from a 3 m fragment whose transform is
    turned by 3° about the fragment: the fragment's error is small on itself and large at the camera,
    so the lever weighting puts the camera nearer its true place than 1/log d alone, and it leaves
    transforms that agree alone."""
    from toolkit.warp.blend import blend_rigid

    wall = np.column_stack([np.linspace(0.0, 40.0, 81), np.zeros(81)])
    frag = np.column_stack([np.linspace(58.0, 61.0, 7), np.full(7, 12.0)])
    street = _flat_street((wall, frag), [[20.0, 0.0], [59.5, 12.0]])
    T = np.repeat(np.eye(4)[None], 2, axis=0)
    pivot = np.array([59.5, 12.0, 0.0])
    T[1, :3, :3] = Rotation.from_euler("z", 3, degrees=True).as_matrix()
    T[1, :3, 3] = pivot - T[1, :3, :3] @ pivot
    transforms = SegmentTransforms(T=T, valid=np.ones(2, bool), cost=np.zeros(2), confidence=np.ones(2))
    index = SegmentIndex.build(street, transforms, 1)
    cam = np.array([[40.0, 6.0, 2.0]])
    off = np.linalg.norm(frag - cam[0, :2], axis=1).min()
    assert off > 15 and np.linalg.norm(T[1, :2, :2] @ cam[0, :2] + T[1, :2, 3] - cam[0, :2]) > 0.9  # precondition
    plain, _, _ = blend_rigid(cam, cam[:, :2], np.array([0]), T, index, 1, 10.0)
    lever, _, _ = blend_rigid(cam, cam[:, :2], np.array([0]), T, index, 1, 10.0, lever=True)
    # the camera's true place is where it is: every transform is the identity there but the fragment's
    assert np.linalg.norm(lever[0] - cam[0]) < 0.6 * np.linalg.norm(plain[0] - cam[0])
    same = np.repeat(T[:1], 2, axis=0)
    exact, _, _ = blend_rigid(cam, cam[:, :2], np.array([0]), same, index, 1, 10.0, lever=True)
    assert np.allclose(exact, cam)


def test_the_lever_weighting_stays_finite_for_one_point_footprints_under_the_camera():
    """Footprints of a single point (extent 0) with the camera right on one of them: the weights do
    not become 0 / 0 and the camera moves with the transforms' mean."""
    from toolkit.warp.blend import blend_rigid

    fps = (np.array([[0.0, 0.0]]), np.array([[5.0, 0.0]]))
    street = _flat_street(fps, [[0.0, 0.0], [5.0, 0.0]])
    T = np.repeat(np.eye(4)[None], 2, axis=0)
    T[:, 0, 3] = [1.0, 3.0]
    transforms = SegmentTransforms(T=T, valid=np.ones(2, bool), cost=np.zeros(2), confidence=np.ones(2))
    index = SegmentIndex.build(street, transforms, 1)
    cam = np.array([[0.0, 0.0, 2.0]])
    pos, R, spread = blend_rigid(cam, cam[:, :2], np.array([0]), T, index, 1, 10.0, lever=True)
    assert np.isfinite(pos).all() and np.isfinite(R).all() and np.isfinite(spread).all()
    assert 1.0 < pos[0, 0] < 3.0
