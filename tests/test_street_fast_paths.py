"""Fast paths of the street helpers against their plain definitions, bit for bit (toolkit/street/*)."""

from __future__ import annotations

import numpy as np
import pytest

from toolkit.street import order
from toolkit.street.associate import group_quantile, nearest_segment, sort_within_groups
from toolkit.arrays import sorted_unique


def _plain_morton(cells: np.ndarray) -> np.ndarray:
    code = np.zeros(len(cells), dtype=np.uint64)
    for bit in range(order.MORTON_BITS):
        for axis in range(3):
            b = (cells[:, axis].astype(np.uint64) >> np.uint64(bit)) & np.uint64(1)
            code |= b << np.uint64(3 * bit + axis)
    return code


def test_morton_codes_match_bit_interleaving():
    rng = np.random.default_rng(0)
    cells = rng.integers(0, 2**order.MORTON_BITS, (2000, 3))
    cells[:3] = [[0, 0, 0], [2**21 - 1, 0, 5], [2**21 - 1] * 3]
    assert np.array_equal(order.morton_codes(cells), _plain_morton(cells))


def _plain_voxels(points, origin, rotation, voxel_m, chunk):
    """The voxel reduction as first written: one sort of all codes, then full-length chunk sums."""
    lo, _ = order._bounds(points, origin, rotation)
    codes = order._codes(points, origin, rotation, lo, voxel_m)
    uniq, inverse = np.unique(codes, return_inverse=True)
    sums, counts = np.zeros((len(uniq), 3)), np.zeros(len(uniq))
    for s in range(0, len(points), chunk):
        inv = inverse[s:s + chunk]
        counts += np.bincount(inv, minlength=len(uniq))
        moved = order._moved(points[s:s + chunk], origin, rotation)
        for axis in range(3):
            sums[:, axis] += np.bincount(inv, weights=moved[:, axis], minlength=len(uniq))
    return sums / counts[:, None], inverse.astype(np.int32)


@pytest.mark.parametrize("rotated", [False, True])
def test_voxel_centroids_are_bitwise_the_plain_sums(monkeypatch, rotated):
    monkeypatch.setattr(order, "CHUNK", 997)  # many chunks sharing voxels, in shuffled input order
    rng = np.random.default_rng(1)
    # near 0, coordinates keep all their mantissa bits: summation order shows in the centroids
    pts = np.concatenate([rng.uniform(0, 4, (6000, 3)), rng.normal(2, 0.05, (3000, 3))])
    pts = pts[rng.permutation(len(pts))]
    origin = np.median(pts, axis=0)
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0] if rotated else None
    cloud = order.prepare(pts, origin, 0.3, "who", rotation=rotation)
    want_points, want_inverse = _plain_voxels(pts, origin, rotation, 0.3, 997)
    assert cloud.points.tobytes() == want_points.tobytes()
    assert np.array_equal(cloud.inverse, want_inverse)


def test_sorted_unique_is_numpy_unique():
    rng = np.random.default_rng(2)
    cases = (rng.integers(-50, 50, 3000), rng.integers(0, 2**40, 500), np.zeros(0, np.int64), np.array([7]))
    for values in cases:
        assert np.array_equal(sorted_unique(values), np.unique(values))


@pytest.mark.parametrize("case", ["ties", "float32", "zeros", "nan", "ints", "many_groups"])
def test_sort_within_groups_is_lexsort(case):
    rng = np.random.default_rng(3)
    n_groups = 40_000 if case == "many_groups" else 7
    groups = rng.integers(0, n_groups, 5000)
    values = np.round(rng.normal(size=5000), 2)  # many equal values
    values[values == 0] = 0.5  # no ±0: the fast path
    if case == "float32":
        values = values.astype(np.float32)
    elif case == "zeros":
        values[::7] = 0.0
        values[::11] = -0.0
    elif case == "nan":
        values[::13] = np.nan
    elif case == "ints":
        values = rng.integers(-5, 5, 5000)
    want = values[np.lexsort((values, groups))]
    assert sort_within_groups(values, groups).tobytes() == want.tobytes()


def test_group_quantile_matches_numpy_quantile():
    rng = np.random.default_rng(4)
    v = np.round(rng.normal(size=3000), 1)
    g = rng.integers(-1, 6, 3000)
    q = group_quantile(v, g, 7, 0.98)
    for i in range(6):
        assert q[i] == pytest.approx(np.quantile(v[g == i], 0.98))
    assert np.isnan(q[6])


def test_nearest_segment_skip_leaves_other_rows_unchanged():
    rng = np.random.default_rng(5)
    pts = rng.uniform(0, 100, (5000, 3))
    seg_xy = rng.uniform(20, 80, (300, 2))
    seg_lab = rng.integers(0, 9, 300)
    skip = rng.random(5000) < 0.4
    full = nearest_segment(pts, np.eye(3)[:2], seg_xy, seg_lab, 10.0, chunk=1000)
    part = nearest_segment(pts, np.eye(3)[:2], seg_xy, seg_lab, 10.0, chunk=1000, skip=skip)
    assert np.array_equal(part[~skip], full[~skip])
    assert (part[skip] == -1).all()
    assert (full >= 0).any() and (full == -1).any()
