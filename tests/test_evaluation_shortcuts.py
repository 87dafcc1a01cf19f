"""toolkit.evaluation.nearest and the exact shortcuts of the evaluation: each against its plain form."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from toolkit.evaluation import metrics as M
from toolkit.evaluation import nearest as N
from toolkit.evaluation import truth as T

TREE_ARGS = dict(leafsize=32, balanced_tree=False, compact_nodes=False)


def _surface_clouds(seed: int, n: int = 30_000):
    """Two noisy samplings of a few planes plus far outliers: close and far neighbours both occur."""
    rng = np.random.default_rng(seed)
    out = []
    for count in (n, n // 2):
        xy = rng.uniform(0, 50, (count, 2))
        z = np.where(xy[:, 0] < 25, 0.0, (xy[:, 0] - 25) * 0.5) + rng.normal(0, 0.05, count)
        pts = np.column_stack([xy, z])
        pts[: count // 50] += rng.uniform(-20, 20, (count // 50, 3))  # scattered points far off the planes
        out.append(pts)
    return out


@pytest.mark.parametrize("dims", [3, 2])
@pytest.mark.parametrize("cutoff_m", [10.0, 0.3, 0.05])
def test_nearest_up_to_equals_one_plain_query(dims, cutoff_m):
    a, b = (c[:, :dims] for c in _surface_clouds(1))
    tree = cKDTree(b, **TREE_ARGS)
    q = a[cKDTree(a, **TREE_ARGS).indices]
    d, j = N.nearest_up_to(tree, q, cutoff_m)
    d_ref, j_ref = tree.query(q, k=1, distance_upper_bound=cutoff_m)
    assert np.array_equal(d, d_ref) and np.array_equal(j, j_ref)
    assert np.isinf(d).any() or cutoff_m == 10.0  # points beyond the cutoff are reported as missing


def test_nearest_up_to_without_any_neighbour_in_reach():
    tree = cKDTree(np.zeros((5, 3)))
    d, j = N.nearest_up_to(tree, np.full((200, 3), 100.0), 1.0)
    assert np.isinf(d).all() and (j == 5).all()


@pytest.mark.parametrize("dims", [3, 2])
def test_nearest_within_equals_plain_query_for_tight_and_loose_bounds(dims):
    a, b = (c[:, :dims] for c in _surface_clouds(2))
    tree = cKDTree(a, **TREE_ARGS)
    d_true, j_true = tree.query(b, k=1)
    # the tightest bound: the nearest distance itself, as the tree returned it
    assert np.array_equal(N.nearest_within(tree, b, d_true), j_true)
    # looser bounds: the distance to some other point of the tree
    other = np.random.default_rng(0).integers(0, len(a), len(b))
    loose = np.linalg.norm(b - a[other], axis=1)
    assert np.array_equal(N.nearest_within(tree, b, loose), j_true)


def test_nearest_within_rejects_a_bound_below_the_answer():
    tree = cKDTree(np.array([[0.0, 0, 0], [10.0, 0, 0]]))
    with pytest.raises(ValueError, match="bound"):
        N.nearest_within(tree, np.array([[4.0, 0, 0]]), np.array([1.0]))
    assert N.nearest_within(tree, np.zeros((0, 3)), np.zeros(0)).shape == (0,)


@pytest.mark.parametrize("dims", [3, 2])
def test_mutual_pairs_equal_the_plain_two_query_version_on_surfaces(dims):
    a, b = (c[:, :dims] + 500_000.0 for c in _surface_clouds(3))
    origin = b.mean(axis=0)
    d, j = cKDTree(b - origin).query(a - origin, distance_upper_bound=10.0)
    i_idx = np.flatnonzero(np.isfinite(d))
    back = cKDTree(a - origin).query(b[j[i_idx]] - origin)[1]
    mutual = back == i_idx
    r = M.mutual_nn_chamfer(a, b, cutoff_m=10.0)
    assert np.array_equal(r.pairs, np.column_stack([i_idx[mutual], j[i_idx][mutual]]))
    assert np.array_equal(r.distances, d[i_idx][mutual])


def test_subsample_is_the_sorted_random_choice():
    pts = np.zeros((100_000, 3))
    for seed in (0, 1, 7):
        plain = np.sort(np.random.default_rng(seed).choice(len(pts), size=30_000, replace=False))
        assert np.array_equal(M.subsample(pts, 30_000, seed), plain)


def test_within_fractions_equal_boolean_means():
    err = np.random.default_rng(4).gamma(1.0, 1.0, 100_003)
    within = M.point_error_summary(err, err / 3)["within_m"]
    for t in M.WITHIN_THRESHOLDS_M:
        assert within[f"{t:g}"]["3d"] == round(float((err <= t).mean()), 6)
        assert within[f"{t:g}"]["horizontal"] == round(float((err / 3 <= t).mean()), 6)


def _street_to_building_by_unique(point_labels, true_labels, n_segments):
    """The plain majority vote over the ids present (np.unique), as the dense table must reproduce."""
    sel = point_labels >= 0
    seg, lab = point_labels[sel].astype(np.int64), true_labels[sel].astype(np.int64)
    values, code = np.unique(lab, return_inverse=True)
    counts = np.bincount(seg * len(values) + code, minlength=n_segments * len(values)).reshape(n_segments, -1)
    winner = values[counts.argmax(axis=1)]
    return np.where((counts.sum(axis=1) == 0) | (winner < 0), -1, winner)


@pytest.mark.parametrize("id_span", [5, 600, 10**9])
def test_street_majority_equals_the_vote_over_present_ids(id_span):
    rng = np.random.default_rng(id_span)
    n_segments, n = 40, 5_000
    point_labels = rng.integers(-2, n_segments - 3, n).astype(np.int32)  # the last 3 segments are empty
    ids = np.r_[-2, -1, rng.integers(0, id_span, 8)]
    true_labels = ids[rng.integers(0, len(ids), n)]  # few ids: many ties between them
    got = T.street_to_building(point_labels, true_labels, n_segments)
    assert np.array_equal(got, _street_to_building_by_unique(point_labels, true_labels, n_segments))
    assert (got[-3:] == -1).all()


def test_overview_to_building_with_a_given_overlap():
    rng = np.random.default_rng(6)
    labels = rng.integers(-1, 6, (50, 60)).astype(np.int32)
    buildings = rng.integers(-1, 4, (50, 60)).astype(np.int32)
    overlap = T.overlap_pixels(labels, 6, buildings, 4)
    plain = T.overview_to_building(labels, 6, buildings, 4, min_iou=0.1)
    given = T.overview_to_building(labels, 6, buildings, 4, min_iou=0.1, overlap=overlap)
    assert all(np.array_equal(x, y) for x, y in zip(plain, given))


def test_common_rows_are_those_of_intersect1d():
    from toolkit.evaluation.scoring import common_rows

    rng = np.random.default_rng(4)
    for _ in range(200):
        a = np.unique(rng.integers(0, 100, rng.integers(0, 60)))
        b = np.unique(rng.integers(0, 100, rng.integers(0, 60)))
        _, ia, ib = np.intersect1d(a, b, assume_unique=True, return_indices=True)
        got = common_rows(a, b, len(b))
        assert np.array_equal(got[0], ia) and np.array_equal(got[1], ib)
        n = int(rng.integers(0, 100))       # b None: the truth holds rows 0..n-1
        _, ia, ib = np.intersect1d(a, np.arange(n), assume_unique=True, return_indices=True)
        got = common_rows(a, None, n)
        assert np.array_equal(got[0], ia) and np.array_equal(got[1], ib)
