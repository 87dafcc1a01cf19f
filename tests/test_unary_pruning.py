"""unary.distance_map candidate pruning: the blockwise / KD-tree shortcuts equal the plain all-pairs tests."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from plugins.unary_distance_map import DistanceMap
from toolkit.matching.candidates import near_gps_midpoint, prune_pairs


def _problem(seed: int, n_edges: int = 150, n_labels: int = 900):
    rng = np.random.default_rng(seed)
    n_seg, n_ov = 60, 120
    j, k = rng.integers(0, n_seg, n_edges), rng.integers(0, n_seg, n_edges)
    lp = rng.integers(0, n_ov, (n_labels, 2))
    return dict(s_len=rng.uniform(0, 80, n_edges), o_len=rng.uniform(0, 80, n_labels),
                street=SimpleNamespace(extent_m=rng.uniform(2, 40, n_seg)), lp=lp, j=j, k=k,
                rho=rng.uniform(1, 15, n_ov), diam=rng.uniform(2, 40, n_ov))


def _all_pairs(stage: DistanceMap, a: dict) -> tuple[np.ndarray, np.ndarray]:
    p, lp = stage.params.prune, a["lp"]
    tol = (p.length_tolerance_m + p.length_tolerance_fraction * a["o_len"][None, :]
           + p.centroid_slack * (a["rho"][lp[:, 0]] + a["rho"][lp[:, 1]])[None, :])
    keep = np.abs(a["s_len"][:, None] - a["o_len"][None, :]) <= tol
    ext = a["street"].extent_m
    keep &= ext[a["j"]][:, None] <= a["diam"][lp[:, 0]][None, :] + p.extent_tolerance_m
    keep &= ext[a["k"]][:, None] <= a["diam"][lp[:, 1]][None, :] + p.extent_tolerance_m
    return np.nonzero(keep)


def test_blockwise_prune_equals_the_all_pairs_test_in_row_major_order():
    stage = DistanceMap.from_config({})
    for seed in range(3):
        a = _problem(seed)
        want_e, want_l = _all_pairs(stage, a)
        assert 0 < len(want_e) < a["s_len"].size * a["o_len"].size  # the test keeps some, not all
        for rows in (1, 7, 64, 1000):
            got_e, got_l = prune_pairs(**a, prune=stage.params.prune, rows_per_block=rows)
            np.testing.assert_array_equal(got_e, want_e)
            np.testing.assert_array_equal(got_l, want_l)


def test_prune_among_given_pairs_keeps_exactly_those_that_pass():
    stage = DistanceMap.from_config({})
    a = _problem(4)
    rng = np.random.default_rng(9)
    E, L = a["s_len"].size, a["o_len"].size
    flat = np.sort(rng.choice(E * L, size=E * L // 3, replace=False))
    among = (flat // L, flat % L)
    got_e, got_l = prune_pairs(**a, among=among, prune=stage.params.prune)
    want = set(zip(*(x.tolist() for x in _all_pairs(stage, a)))) & set(zip(among[0].tolist(), among[1].tolist()))
    assert list(zip(got_e.tolist(), got_l.tolist())) == sorted(want)


def test_pairs_near_the_gps_midpoint_contain_every_pair_the_exact_test_keeps():
    rng = np.random.default_rng(2)
    n_seg, n_edges, n_labels = 50, 200, 3000
    prior = SimpleNamespace(position=rng.uniform(0, 2000, (n_seg, 2)) + [5.0e5, 5.7e6])
    seg_radius = rng.uniform(5, 60, n_seg)
    j, k = rng.integers(0, n_seg, n_edges), rng.integers(0, n_seg, n_edges)
    o_mid_world = rng.uniform(0, 2000, (n_labels, 2)) + [5.0e5, 5.7e6]
    window = rng.uniform(0, 25, n_labels)
    window[::97] = np.nan  # a label without a window never passes; it must not widen the search
    e, lab = near_gps_midpoint(prior, seg_radius, j, k, o_mid_world, window)
    assert np.all(np.diff(e * n_labels + lab) > 0)  # row-major, no repeats
    g_mid = (prior.position[j] + prior.position[k]) / 2
    exact = (np.linalg.norm(o_mid_world[None, :, :] - g_mid[:, None, :], axis=2)
             <= np.maximum(seg_radius[j], seg_radius[k])[:, None] + window[None, :])
    want = set(zip(*(x.tolist() for x in np.nonzero(exact))))
    got = set(zip(e.tolist(), lab.tolist()))
    assert want and want <= got
    assert len(got) < n_edges * n_labels / 4  # and it is a real cut, not every pair
