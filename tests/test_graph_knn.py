"""graph.knn: K-NN segment graphs, label orders and the conjugate graph (METHOD.md §3)."""

from __future__ import annotations

from dataclasses import dataclass, field

import networkx as nx
import numpy as np
import pytest
from pydantic import ValidationError

from plugins.graph_knn import KnnGraph
from toolkit.matching import conjugate as C
from toolkit.testing.matching_toy import make_toy, street_from_boundaries
from toolkit.observe import DebugGraph, DebugLines, NullObserver


@dataclass
class RecordingObserver(NullObserver):
    records: dict = field(default_factory=dict)

    @property
    def wants_debug(self) -> bool:
        return True

    def debug(self, name, value, it=None, timeline=None):
        self.records[name] = value


@pytest.fixture(scope="module")
def toy():
    return make_toy((3, 3), seed=3)


def test_knn_edges_link_each_point_to_its_k_nearest():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 100, (40, 2))
    edges = C.knn_edges(pts, 4)
    assert edges.dtype == np.int64 and (edges[:, 0] < edges[:, 1]).all()
    assert len(np.unique(edges, axis=0)) == len(edges)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    np.fill_diagonal(d, np.inf)
    expected = {tuple(sorted((i, j))) for i in range(40) for j in np.argsort(d[i])[:4]}
    assert {tuple(e) for e in edges} == expected


def test_knn_edges_on_a_line_with_k1_is_a_path_and_max_length_drops_long_edges():
    pts = np.array([[0.0, 0], [1, 0], [3, 0], [6, 0], [20, 0]])
    assert C.knn_edges(pts, 1).tolist() == [[0, 1], [1, 2], [2, 3], [3, 4]]
    assert C.knn_edges(pts, 1, max_length=5.0).tolist() == [[0, 1], [1, 2], [2, 3]]
    assert C.knn_edges(pts[:1], 4).shape == (0, 2)


def test_knn_edges_do_not_depend_on_a_large_utm_origin():
    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 300, (60, 2))
    assert np.array_equal(C.knn_edges(pts, 4), C.knn_edges(pts + [500_000.0, 4_400_000.0], 4))


def test_label_orders_are_symmetric():
    edges = np.array([[0, 3], [1, 2], [2, 5]])
    pairs = C.label_pairs(edges)
    assert pairs.shape == (6, 2)
    assert np.array_equal(pairs[0::2], edges)
    assert np.array_equal(pairs[1::2], edges[:, ::-1])


def test_conjugate_edges_are_exactly_the_street_edge_pairs_sharing_a_segment():
    rng = np.random.default_rng(2)
    street = C.knn_edges(rng.uniform(0, 100, (25, 2)), 3)
    conj, shared = C.conjugate_edges(street, 25)
    expected = {}
    for a in range(len(street)):
        for b in range(a + 1, len(street)):
            common = set(street[a]) & set(street[b])
            if common:
                expected[(a, b)] = common.pop()
    assert {tuple(c): s for c, s in zip(conj.tolist(), shared.tolist())} == expected
    assert (conj[:, 0] < conj[:, 1]).all()


def test_stage_output_is_consistent(toy):
    g = KnnGraph()(toy.street, toy.overview, NullObserver())
    S, O = len(toy.street), len(toy.overview)
    assert g.n_labels == 2 * len(g.overview_edges) + 1 and g.null_label == g.n_labels - 1
    assert g.label_pairs.max() < O and g.street_edges.max() < S
    assert set(g.street_graph.nodes) == set(range(S)) and set(g.overview_graph.nodes) == set(range(O))
    assert {tuple(sorted(e)) for e in g.street_graph.edges} == {tuple(e) for e in g.street_edges}
    assert {tuple(sorted(e)) for e in g.overview_graph.edges} == {tuple(e) for e in g.overview_edges}
    assert g.conjugate_graph.number_of_nodes() == g.n_nodes
    assert {tuple(sorted(e)) for e in g.conjugate_graph.edges} == {tuple(e) for e in g.conj_edges}
    for (a, b), s in zip(g.conj_edges, g.conj_shared):
        assert s in g.street_edges[a] and s in g.street_edges[b]
        assert g.conjugate_graph.edges[a, b]["shared"] == s
    assert min(d for _, d in g.street_graph.degree) >= 4  # each links to its 4 nearest (union)
    assert nx.is_connected(g.overview_graph)
    # street nodes carry each segment's horizontal diameter for the match stages' vote
    ext = [g.street_graph.nodes[i]["extent_m"] for i in range(S)]
    np.testing.assert_allclose(ext, np.asarray(toy.street.extent_m, dtype=np.float64))


def test_k_and_overview_k(toy):
    small = KnnGraph(KnnGraph.Params(k=2, overview_k=None))(toy.street, toy.overview, NullObserver())
    mixed = KnnGraph(KnnGraph.Params(k=2, overview_k=6))(toy.street, toy.overview, NullObserver())
    assert len(small.overview_edges) < len(mixed.overview_edges)
    assert np.array_equal(small.street_edges, mixed.street_edges)
    with pytest.raises(ValidationError):
        KnnGraph.Params(k=0)
    with pytest.raises(ValidationError):
        KnnGraph.Params(kk=3)


def test_degenerate_views_give_empty_graphs_with_a_warning(toy):
    one = street_from_boundaries([toy.street.boundary_xy[0]])
    obs = NullObserver()
    g = KnnGraph()(one, toy.overview, obs)
    assert g.n_nodes == 0 and g.conj_edges.shape == (0, 2) and g.n_labels > 1
    assert any("no street edge" in w for w in obs.warnings)


def test_debug_payloads_when_wanted(toy):
    obs = RecordingObserver()
    g = KnnGraph()(toy.street, toy.overview, obs)
    for name in ("street_knn", "overview_knn", "conjugate"):
        assert isinstance(obs.records[name], DebugGraph)
    assert len(obs.records["conjugate"].edges) == len(g.conj_edges)
    assert isinstance(obs.records["overview_knn_lines"], DebugLines)
    loops = g.overview_edges[:, 0] == g.overview_edges[:, 1]   # same-segment labels are not drawn
    assert loops.sum() == len(toy.overview)
    assert len(obs.records["overview_knn_lines"].strips) == (~loops).sum()
    # over-view positions are pixel (col, row), not UTM: they fit on the grid
    pos = obs.records["overview_knn"].positions
    assert pos.min() >= 0 and pos[:, 0].max() < toy.overview.grid.width
