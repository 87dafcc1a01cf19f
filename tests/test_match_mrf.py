"""The matching MRF structure: compatible pairs, energy, fast vs dense messages, voting, symmetry."""

from __future__ import annotations

import networkx as nx
import numpy as np
import pytest
from pydantic import ValidationError

from toolkit.errors import StageError
from toolkit.matching.mrf import SmoothnessParams, build_mrf, conditional_scores, segment_argmin
from toolkit.matching.solvers_bp import beliefs, build_plan, loopy_bp, send
from toolkit.matching.solvers_common import vote
from toolkit.matching.solvers_dense import dense_loopy_bp, v_table
from toolkit.testing.solvers_synth import synthetic_problem
from toolkit.types import ConjugateGraphs, DataCosts


def _mrf(p, **kw):
    args = {"c1": 0.1, "c2": 0.6, "theta_th_deg": 10.0, "t_th_m": 100.0} | kw
    return build_mrf(p.graphs, p.costs, **args)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compatible_pairs_match_dense_tables(seed):
    p = synthetic_problem(n_matched=9, n_street_only=2, seed=seed, decoy_rate=0.3, length_tol_m=40)
    m = _mrf(p, t_th_m=30.0)  # a tight t threshold so both tests (θ and t) reject something
    assert len(m.pair_edge) > 0
    for c in range(len(m.conj_edges)):
        a, b = m.conj_edges[c]
        la = m.act_label[m.act_ptr[a]:m.act_ptr[a + 1] - 1]
        lb = m.act_label[m.act_ptr[b]:m.act_ptr[b + 1] - 1]
        dense = v_table(m, c)[np.ix_(la, lb)] == m.c1
        fast = np.zeros_like(dense)
        sel = m.pair_edge == c
        fast[m.pair_a[sel], m.pair_b[sel]] = True
        np.testing.assert_array_equal(fast, dense)


def test_energy_equals_sum_of_dense_tables():
    p = synthetic_problem(n_matched=8, n_street_only=1, seed=4, decoy_rate=0.3)
    m = _mrf(p)
    rng = np.random.default_rng(0)
    for _ in range(5):
        x = m.to_global(rng.integers(0, m.n_act))
        expect = p.costs.cost[np.arange(m.n_nodes), x].sum()
        expect += sum(v_table(m, c)[x[a], x[b]] for c, (a, b) in enumerate(m.conj_edges))
        assert m.energy(x) == pytest.approx(expect)


def test_fast_messages_equal_dense_messages():
    p = synthetic_problem(n_matched=10, n_street_only=2, seed=3, decoy_rate=0.3, length_tol_m=40)
    m = _mrf(p)
    dense_labels, history = dense_loopy_bp(m, 4)
    msg = np.zeros(int(m.msg_ptr[-1]))
    plan = build_plan(m, np.arange(len(m.msg_send)))
    for k in range(4):
        h = beliefs(m, msg)[m.slot_node_flat] - msg
        msg[plan.out_slots] = send(plan, h[plan.src_slots], m.c1, m.c2)
        for d in range(len(m.msg_send)):
            r = m.msg_recv[d]
            active = m.act_label[m.act_ptr[r]:m.act_ptr[r + 1]]
            np.testing.assert_allclose(msg[m.msg_ptr[d]:m.msg_ptr[d + 1]], history[k][d, active], atol=1e-12)
    fast_labels = m.to_global(segment_argmin(beliefs(m, msg), m.act_ptr))
    np.testing.assert_array_equal(fast_labels, dense_labels)
    # and the solver's buffered loop follows the same trajectory
    bp = loopy_bp(m, max_iters=4, patience=100)
    assert bp.energy <= m.energy(dense_labels) + 1e-12


def test_conditional_scores_are_energy_differences():
    p = synthetic_problem(n_matched=9, seed=5, decoy_rate=0.3)
    m = _mrf(p)
    rng = np.random.default_rng(1)
    x = rng.integers(0, m.n_act)
    i = int(np.argmax(m.deg))
    score = conditional_scores(m, i, x)
    for local in range(m.n_act[i]):
        y = x.copy()
        y[i] = local
        assert score[local] - score[x[i]] == pytest.approx(m.energy(m.to_global(y)) - m.energy(m.to_global(x)))


def test_vote_majority_null_and_transform():
    # street segments 0..3, edges (0,1) (0,2) (0,3) (1,2); over-view 0..3 with edges (0,1) (0,2) (0,3) (1,2)
    se = np.array([[0, 1], [0, 2], [0, 3], [1, 2]])
    ov = np.array([[0, 1], [0, 2], [0, 3], [1, 2]])
    lp = np.empty((8, 2), np.int64)
    lp[0::2], lp[1::2] = ov, ov[:, ::-1]
    g = nx.Graph()
    g.add_nodes_from(range(4))
    graphs = ConjugateGraphs(street_graph=g, overview_graph=g.copy(), street_edges=se, overview_edges=ov,
                             label_pairs=lp, conj_edges=np.zeros((0, 2), np.int64),
                             conj_shared=np.zeros(0, np.int64), conjugate_graph=nx.Graph())
    cost = np.full((4, 9), 0.5)
    cost[:, 8] = 1.0
    cost[0, 0], cost[1, 2] = 0.1, 0.3
    theta = np.tile(np.linspace(0.0, 0.7, 8), (4, 1))
    t = np.tile(np.arange(16.0).reshape(8, 2), (4, 1, 1))
    costs = DataCosts(cost=cost, theta_rad=theta, t=t)
    # edge0 (0,1)→(0,1); edge1 (0,2)→(0,2); edge2 (0,3) null; edge3 (1,2)→(1,2)
    match, conf, T2d, mcost = vote(graphs, costs, np.array([0, 2, 8, 6]))
    np.testing.assert_array_equal(match, [0, 1, 2, -1])
    assert conf[0] == pytest.approx(2 / 3) and conf[1] == 1.0 and conf[3] == 0.0
    assert mcost[0] == pytest.approx(0.2) and mcost[3] == 1.0
    # segment 0 takes the transform of its cheapest agreeing edge (edge 0, label 0)
    c, s = np.cos(theta[0, 0]), np.sin(theta[0, 0])
    np.testing.assert_allclose(T2d[0], [[c, -s, 0.0], [s, c, 1.0], [0, 0, 1]])
    np.testing.assert_allclose(T2d[3], np.eye(3))
    # null votes outnumbering the winner make the segment null: edges 0 and 1 are null, their other
    # segments (1, 2) are matched through edge 3, so both nulls count against segment 0's one vote
    match, *_ = vote(graphs, costs, np.array([8, 8, 4, 6]))
    np.testing.assert_array_equal(match, [-1, 1, 2, 3])
    # a null edge to a segment with no non-null vote at all (3 below) is explained by that segment
    # and does not count: segment 0 keeps its match (1 vote against 1 counted null)
    match, conf, *_ = vote(graphs, costs, np.array([0, 8, 8, 6]))
    assert match[0] == 0 and match[1] == 1 and match[3] == -1
    assert conf[0] == pytest.approx(1 / 3)
    # with edge 3 null as well, segments 2 and 3 have no vote: both nulls of segment 0 are explained
    match, *_ = vote(graphs, costs, np.array([0, 8, 8, 8]))
    assert match[0] == 0 and match[2] == -1 and match[3] == -1


def test_vote_tie_needs_a_long_enough_segment():
    """A tie between the winner's votes and the counted nulls matches only a segment at least
    tie_min_extent_m long (graph.knn's ``extent_m`` node attribute; a missing one counts as long);
    a strict majority matches whatever the length."""
    se = np.array([[0, 1], [0, 2], [0, 3], [1, 2]])
    ov = np.array([[0, 1], [0, 2], [0, 3], [1, 2]])
    lp = np.empty((8, 2), np.int64)
    lp[0::2], lp[1::2] = ov, ov[:, ::-1]

    def graphs_with(extent):
        g = nx.Graph()
        g.add_nodes_from(range(4))
        if extent is not None:
            nx.set_node_attributes(g, dict(enumerate(extent)), "extent_m")
        return ConjugateGraphs(street_graph=g, overview_graph=g.copy(), street_edges=se, overview_edges=ov,
                               label_pairs=lp, conj_edges=np.zeros((0, 2), np.int64),
                               conj_shared=np.zeros(0, np.int64), conjugate_graph=nx.Graph())

    cost = np.full((4, 9), 0.5)
    cost[:, 8] = 1.0
    costs = DataCosts(cost=cost, theta_rad=np.zeros((4, 8)), t=np.zeros((4, 8, 2)))
    tie = np.array([0, 8, 8, 6])  # segment 0: one vote for over-view 0, one counted null (edge 1)
    short, long_ = graphs_with([4.0, 4.0, 4.0, 4.0]), graphs_with([7.0, 4.0, 4.0, 4.0])
    assert vote(short, costs, tie, tie_min_extent_m=6.0)[0][0] == -1
    assert vote(long_, costs, tie, tie_min_extent_m=6.0)[0][0] == 0
    assert vote(short, costs, tie, tie_min_extent_m=0.0)[0][0] == 0
    assert vote(graphs_with(None), costs, tie, tie_min_extent_m=6.0)[0][0] == 0
    # edges 0, 1 null; edge 2 → (0, 3), edge 3 → (1, 2): segment 3 has one vote and no null, a strict
    # majority that a short segment keeps; segments 1 and 2 tie 1:1 (their null edge's other end, 0,
    # has a vote) and drop when short, keep when long; segment 0 loses 1:2 either way
    match, *_ = vote(short, costs, np.array([8, 8, 4, 6]), tie_min_extent_m=6.0)
    np.testing.assert_array_equal(match, [-1, -1, -1, 3])
    match, *_ = vote(graphs_with([7.0, 7.0, 7.0, 4.0]), costs, np.array([8, 8, 4, 6]), tie_min_extent_m=6.0)
    np.testing.assert_array_equal(match, [-1, 1, 2, 3])


def _flip_street_edges(p, flip):
    """The same problem with some street edges written (k, j): label 2f ↔ 2f+1 on those rows."""
    g = p.graphs
    se = g.street_edges.copy()
    se[flip] = se[flip][:, ::-1]
    swap = np.arange(g.n_labels - 1) ^ 1
    cost, theta, t = p.costs.cost.copy(), p.costs.theta_rad.copy(), p.costs.t.copy()
    cost[flip, :-1] = cost[flip][:, swap]
    theta[flip] = theta[flip][:, swap]
    t[flip] = t[flip][:, swap]
    graphs = ConjugateGraphs(street_graph=g.street_graph, overview_graph=g.overview_graph, street_edges=se,
                             overview_edges=g.overview_edges, label_pairs=g.label_pairs,
                             conj_edges=g.conj_edges, conj_shared=g.conj_shared, conjugate_graph=g.conjugate_graph)
    return graphs, DataCosts(cost=cost, theta_rad=theta, t=t)


def test_label_order_symmetry():
    p = synthetic_problem(n_matched=14, n_street_only=2, seed=7, decoy_rate=0.15)
    flip = np.arange(p.graphs.n_nodes) % 2 == 1
    graphs2, costs2 = _flip_street_edges(p, flip)
    m1, m2 = _mrf(p), build_mrf(graphs2, costs2, 0.1, 0.6, 10.0, 100.0)
    r1, r2 = loopy_bp(m1, damping=0.5), loopy_bp(m2, damping=0.5)
    assert r1.energy == pytest.approx(r2.energy)
    l1, l2 = m1.to_global(r1.labels), m2.to_global(r2.labels)
    swapped = np.where(flip & (l1 != m1.null_label), l1 ^ 1, l1)
    np.testing.assert_array_equal(l2, swapped)
    np.testing.assert_array_equal(vote(p.graphs, p.costs, l1)[0], vote(graphs2, costs2, l2)[0])


def test_params_and_input_checks():
    with pytest.raises(ValidationError, match="c1"):
        SmoothnessParams(c1=0.7, c2=0.6)
    p = synthetic_problem(n_matched=5, seed=0)
    bad = DataCosts(cost=p.costs.cost[:-1], theta_rad=p.costs.theta_rad[:-1], t=p.costs.t[:-1])
    with pytest.raises(StageError, match="DataCosts.cost has shape"):
        _mrf(type(p)(graphs=p.graphs, costs=bad, truth_match=p.truth_match, street_xy=p.street_xy,
                     overview_xy=p.overview_xy))
