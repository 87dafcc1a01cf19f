"""Solvers against brute force and pgmpy: exact on trees, consistent ordering and bounds on loops."""

from __future__ import annotations

import math

import numpy as np
import pytest

from toolkit.matching.mrf import build_mrf
from toolkit.matching.solvers_bp import loopy_bp
from toolkit.matching.solvers_local import greedy, icm
from toolkit.matching.solvers_pgmpy import mplp
from toolkit.testing.solvers_synth import synthetic_problem
from toolkit.matching.solvers_trws import trws


def _mrf(p):
    return build_mrf(p.graphs, p.costs, c1=0.1, c2=0.6, theta_th_deg=10.0, t_th_m=100.0)


def brute_force(m) -> float:
    """Minimum energy by enumerating every labelling (in batches)."""
    grids = np.stack(np.meshgrid(*[np.arange(k) for k in m.n_act], indexing="ij"), axis=-1).reshape(-1, m.n_nodes)
    return float(min(m.energy(m.to_global(grids[i:i + 20000])).min() for i in range(0, len(grids), 20000)))


def _small(topology, seed, n=5):
    p = synthetic_problem(n_matched=n, n_street_only=1, n_overview_only=1, k=3, topology=topology, seed=seed,
                          decoy_rate=0.25, length_tol_m=20)
    m = _mrf(p)
    assert np.prod(m.n_act.astype(float)) < 5e4, "test problem too big to enumerate"
    return m


@pytest.mark.parametrize("seed", range(4))
def test_chain_exact(seed):
    """On a chain (a tree) loopy BP, TRW-S and pgmpy Mplp all reach the global minimum."""
    m = _small("path", seed)
    opt = brute_force(m)
    assert loopy_bp(m).energy == pytest.approx(opt)
    t = trws(m)
    assert t.energy == pytest.approx(opt)
    assert t.lower_bound == pytest.approx(opt)  # the bound is tight on a tree
    assert mplp(m).energy == pytest.approx(opt)


@pytest.mark.parametrize("seed", range(3))
def test_cycle_bounds_and_order(seed):
    m = _small("cycle", seed)
    opt = brute_force(m)
    t, b, i, g = trws(m), loopy_bp(m, damping=0.5), icm(m), greedy(m)
    assert t.lower_bound <= opt + 1e-9
    assert t.energy >= opt - 1e-9 and b.energy >= opt - 1e-9
    assert i.energy <= g.energy + 1e-12
    assert mplp(m).energy == pytest.approx(opt)


@pytest.mark.parametrize("seed", [0, 1, 3, 4, 5])
def test_loopy_knn_agrees_with_pgmpy(seed):
    """K-NN street graphs give conjugate graphs full of triangles. pgmpy Mplp with triplet tightening
    certifies the optimum on these seeds (its bound meets its energy); TRW-S finds that optimum, and
    every solver's energy sits above both solvers' bounds."""
    p = synthetic_problem(n_matched=7, n_street_only=1, n_overview_only=2, k=3, seed=seed, decoy_rate=0.2,
                          length_tol_m=25)
    m = _mrf(p)
    ref = mplp(m, tighten_triplets=True)
    assert ref.energy - ref.lower_bound < 1e-3, "precondition: pgmpy certifies the optimum"
    t, b = trws(m), loopy_bp(m, damping=0.5)
    assert t.energy == pytest.approx(ref.energy)
    bound = max(t.lower_bound, ref.lower_bound)
    assert bound <= min(t.energy, b.energy, ref.energy) + 1e-3


def test_harder_problem_bounds_and_monotonicity():
    """Many decoys, dense labels: the TRW-S bound sits below every solver's energy and never
    decreases; ICM never raises the energy and ends at or below winner-takes-all."""
    p = synthetic_problem(n_matched=30, n_street_only=3, n_overview_only=8, seed=11, decoy_rate=0.3,
                          length_tol_m=30)
    m = _mrf(p)
    t, b, i, g = trws(m), loopy_bp(m, damping=0.5), icm(m), greedy(m)
    assert t.lower_bound <= min(t.energy, b.energy, i.energy, g.energy) + 1e-9
    assert t.energy - t.lower_bound < 0.05 * t.energy  # close to optimal on this problem
    assert np.all(np.diff(t.bound_trace) >= -1e-6)
    assert np.all(np.diff(i.energy_trace) <= 1e-12)
    assert i.energy <= g.energy


def test_loopy_bp_damps_harder_where_the_flooding_schedule_cycles():
    """The plain update (damping 0) cycles on this problem and gives up after stall_iters; halving
    (1 − damping) instead reaches a labelling that holds for patience counted in the same message
    travel (patience·(1 − 0)/(1 − d) iterations at damping d), at no higher energy."""
    p = synthetic_problem(n_matched=60, n_street_only=3, n_overview_only=8, seed=0, decoy_rate=0.3,
                          length_tol_m=30)
    m = _mrf(p)
    kw = dict(damping=0.0, patience=2, stall_iters=30, max_iters=300, polish=True)
    plain, damped = loopy_bp(m, **kw), loopy_bp(m, max_damping=0.9375, **kw)
    assert not plain.converged and plain.damping == 0.0 and plain.iterations < 100
    assert damped.converged and 0.0 < damped.damping <= 0.9375
    held = math.ceil(2 / (1.0 - damped.damping))
    assert held > 2 and len(set(damped.energy_trace[-(held + 1):])) == 1
    assert damped.energy <= plain.energy + 1e-9


def test_pgmpy_answer_complete_when_every_potential_would_be_negative():
    """pgmpy #1702: with all costs high the raw log-potentials are all negative; the shift fixes it."""
    p = synthetic_problem(n_matched=5, k=3, seed=2)
    p.costs.cost[:, :-1] = np.clip(p.costs.cost[:, :-1], 0.9, 1.0)
    m = _mrf(p)
    r = mplp(m)
    assert len(r.labels) == m.n_nodes
    assert r.energy == pytest.approx(trws(m).energy)


def test_greedy_is_winner_takes_all():
    p = synthetic_problem(n_matched=8, seed=3, decoy_rate=0.3)
    m = _mrf(p)
    g = greedy(m)
    np.testing.assert_array_equal(m.to_global(g.labels), np.argmin(p.costs.cost, axis=1))


def test_trws_polish_never_raises_the_energy_and_ends_at_a_local_minimum():
    """match.trws finishes with ICM from its best labelling: the energy can only go down, the bound
    is untouched, and no single node can then lower the energy by changing its label."""
    from toolkit.matching.mrf import conditional_scores

    p = synthetic_problem(n_matched=30, n_street_only=3, n_overview_only=8, seed=11, decoy_rate=0.3,
                          length_tol_m=30)
    m = _mrf(p)
    raw, polished = trws(m, polish=False), trws(m)
    assert polished.energy <= raw.energy + 1e-12
    assert polished.lower_bound == pytest.approx(raw.lower_bound)
    assert polished.energy == pytest.approx(m.energy(m.to_global(polished.labels)))
    x = polished.labels
    for i in range(m.n_nodes):
        score = conditional_scores(m, i, x)
        assert score.min() >= score[x[i]] - 1e-9


def test_loopy_bp_polish_never_raises_the_energy_and_ends_at_a_local_minimum():
    """match.loopy_bp (polish=True, the stage default) lets ICM improve single nodes of its best
    labelling: never a higher energy, and no single node can then lower it."""
    from toolkit.matching.mrf import conditional_scores

    p = synthetic_problem(n_matched=30, n_street_only=3, n_overview_only=8, seed=11, decoy_rate=0.3,
                          length_tol_m=30)
    m = _mrf(p)
    raw, polished = loopy_bp(m, damping=0.5), loopy_bp(m, damping=0.5, polish=True)
    assert polished.energy <= raw.energy + 1e-12
    assert polished.energy == pytest.approx(m.energy(m.to_global(polished.labels)))
    assert polished.energy <= icm(m, init=raw.labels).energy + 1e-12
    x = polished.labels
    for i in range(m.n_nodes):
        score = conditional_scores(m, i, x)
        assert score.min() >= score[x[i]] - 1e-9


@pytest.mark.parametrize("seed", range(3))
def test_sequential_decoding_of_exact_tree_messages_is_optimal(seed):
    """On a chain, min-sum messages iterated past the diameter are exact: decoding them node by node
    (each conditioned on its earlier neighbours' labels) gives a global minimum, ties included."""
    from toolkit.matching.solvers_bp import beliefs, build_plan, send, sequential_decode

    m = _small("path", seed)
    msg = np.zeros(int(m.msg_ptr[-1]))
    plan = build_plan(m, np.arange(len(m.msg_send)))
    for _ in range(m.n_nodes + 1):
        h = beliefs(m, msg)[m.slot_node_flat] - msg
        msg[plan.out_slots] = send(plan, h[plan.src_slots], m.c1, m.c2)
    x = sequential_decode(m, msg)
    assert m.energy(m.to_global(x)) == pytest.approx(brute_force(m))


def test_icm_skipping_settled_nodes_equals_full_sweeps():
    """icm re-scores only nodes whose neighbours changed: the labelling must be exactly what plain
    sweeps over every node in index order give."""
    from toolkit.matching.mrf import conditional_scores

    p = synthetic_problem(n_matched=30, n_street_only=3, n_overview_only=8, seed=11, decoy_rate=0.3,
                          length_tol_m=30)
    m = _mrf(p)
    x = m.greedy_local()
    for _ in range(50):
        changed = 0
        for i in range(m.n_nodes):
            score = conditional_scores(m, i, x)
            best = int(np.argmin(score))
            if score[best] < score[x[i]] - 1e-12:
                x[i], changed = best, changed + 1
        if changed == 0:
            break
    r = icm(m)
    assert r.converged
    np.testing.assert_array_equal(r.labels, x)
    assert r.energy == pytest.approx(m.energy(m.to_global(x)))


def _one_segment_triangle():
    """Street segment 0 with neighbours 1, 2, 3: three street edges sharing it (a conjugate
    triangle). Each edge can send segment 0 to over-view segment A (cost 0.45) or B (cost 0.05);
    over-view segments 2, 3, 4 take the other ends. Labels agree when they send 0 to the same one."""
    import networkx as nx

    from toolkit.types import ConjugateGraphs, DataCosts

    ov_edges = np.array([[0, 2], [0, 3], [0, 4], [1, 2], [1, 3], [1, 4]])
    label_pairs = np.repeat(ov_edges, 2, axis=0)
    label_pairs[1::2] = label_pairs[1::2, ::-1]
    street_edges = np.array([[0, 1], [0, 2], [0, 3]])
    conj = np.array([[0, 1], [0, 2], [1, 2]])
    cost = np.full((3, len(label_pairs) + 1), np.inf)
    cost[:, -1] = 1.0
    for node in range(3):
        cost[node, 2 * node] = 0.45          # 0 → A (over-view 0), node's neighbour → 2 + node
        cost[node, 2 * (node + 3)] = 0.05    # 0 → B (over-view 1)
    graphs = ConjugateGraphs(nx.Graph(), nx.Graph(), street_edges, ov_edges, label_pairs, conj,
                             np.zeros(3, np.int64), nx.Graph())
    costs = DataCosts(cost, np.zeros((3, len(label_pairs))), np.zeros((3, len(label_pairs), 2)))
    return build_mrf(graphs, costs, c1=0.1, c2=0.6, theta_th_deg=10.0, t_th_m=100.0)


def test_segment_moves_re_match_a_segment_that_icm_cannot_move():
    """All three edges send segment 0 to A. Moving one edge to B alone costs 2·(c2 − c1) = 1.0 for
    a 0.4 gain, so ICM is stuck; moving the three together gains 1.2. The segment move finds it,
    never raises the energy, and reports the energy of the labelling it returns."""
    from toolkit.matching.solvers_local import icm_polish, segment_move_sweeps

    m = _one_segment_triangle()
    on_a = np.zeros(3, np.int64)  # local label 0 = the lower global label = the A label of each node
    e_a = m.energy(m.to_global(on_a))
    assert icm(m, init=on_a).energy == pytest.approx(e_a)
    moved, e_moved = segment_move_sweeps(m, on_a, e_a)
    assert e_moved == pytest.approx(e_a - 1.2)
    assert e_moved == pytest.approx(m.energy(m.to_global(moved)))
    assert e_moved == pytest.approx(brute_force(m))
    assert icm_polish(m, on_a, e_a)[1] == pytest.approx(e_a)  # ICM alone keeps it
    assert icm_polish(m, on_a, e_a, segment_moves=True)[1] == pytest.approx(e_moved)


@pytest.mark.parametrize("seed", range(3))
def test_segment_moves_never_raise_the_energy(seed):
    from toolkit.matching.solvers_local import segment_move_sweeps

    p = synthetic_problem(n_matched=30, n_street_only=3, n_overview_only=8, seed=seed, decoy_rate=0.3,
                          length_tol_m=30)
    m = _mrf(p)
    for start in (m.greedy_local(), icm(m).labels):
        e0 = m.energy(m.to_global(start))
        x, e = segment_move_sweeps(m, start, e0)
        assert e <= e0 + 1e-12
        assert e == pytest.approx(m.energy(m.to_global(x)))
