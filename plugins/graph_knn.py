"""graph.knn — K-nearest-segment graphs of both views and their conjugate graph (paper §3.3.1).

Each segment is linked to its K nearest segments by centroid distance (the union of the directed
relations, so degrees may exceed K). Conjugate nodes are street edges; their labels are the
over-view edges in both orders plus null; conjugate neighbours share a street segment. With K-NN
edges the label count is about 2·K·n instead of n(n−1). Street graph nodes carry ``pos`` and
``extent_m`` (the segment's horizontal diameter, which the match stages' vote reads).
"""

from __future__ import annotations

import networkx as nx
import numpy as np
from pydantic import Field

from toolkit.errors import StageError
from toolkit.matching import conjugate as C
from toolkit.observe import DebugGraph, DebugLines
from toolkit.stage import Stage, StageParams
from toolkit.types import ConjugateGraphs, OverviewSegments, StreetSegments


class KnnGraph(Stage):
    """K-nearest-segment graphs of both views and their conjugate graph (paper §3.3.1)."""

    kind = "graph"
    name = "knn"

    class Params(StageParams):
        k: int = Field(4, ge=1, le=64, description="Neighbours per segment (paper: K = 4), both views.")
        overview_k: int | None = Field(
            10, ge=1, le=64, description="K-nearest neighbours per segment in the over-view graph (count; None: k)")
        same_segment_labels: bool = Field(
            True, description="Also allow labelling a street edge with one over-view "
                              "segment for both ends (not in the paper)")
        max_edge_m: float | None = Field(
            None, gt=0, description="Drop K-NN edges longer than this (metres; None keeps all).")

    def __call__(self, street: StreetSegments, overview: OverviewSegments, obs) -> ConjugateGraphs:
        p = self.params
        if len(street) == 0:
            raise StageError("the street step found no building segment (see its warnings): there is "
                             "nothing to match; check the street cloud")
        if len(overview) == 0:
            raise StageError("the over-view step found no building segment: there is nothing to match")
        s_cent = np.asarray(street.centroids, dtype=np.float64).reshape(-1, 2)
        o_cent = np.asarray(overview.centroids, dtype=np.float64).reshape(-1, 2)
        street_edges = C.knn_edges(s_cent, p.k, p.max_edge_m)
        overview_edges = C.knn_edges(o_cent, p.overview_k or p.k, p.max_edge_m)
        if p.same_segment_labels and len(o_cent) and len(street_edges):
            loops = np.repeat(np.arange(len(o_cent), dtype=np.int64)[:, None], 2, axis=1)
            overview_edges = np.concatenate([overview_edges, loops])
        if len(street_edges) == 0:
            obs.warn(f"street has {len(s_cent)} segment(s): no street edge, nothing to match")
        if len(overview_edges) == 0:
            obs.warn(f"over-view has {len(o_cent)} segment(s) and no over-view edge: only the null label")
        pairs = C.label_pairs(overview_edges)
        conj, shared = C.conjugate_edges(street_edges, len(s_cent))
        street_graph = C.segment_graph(len(s_cent), street_edges, s_cent)
        ext = np.asarray(street.extent_m, dtype=np.float64).reshape(-1)
        if len(ext) == len(s_cent):  # read by the match stages' vote (SmoothnessParams.tie_min_extent_m)
            nx.set_node_attributes(street_graph, dict(enumerate(ext.tolist())), "extent_m")
        graphs = ConjugateGraphs(
            street_graph=street_graph,
            overview_graph=C.segment_graph(len(o_cent), overview_edges, o_cent),
            street_edges=street_edges,
            overview_edges=overview_edges,
            label_pairs=pairs,
            conj_edges=conj,
            conj_shared=shared,
            conjugate_graph=C.conjugate_graph(street_edges, conj, shared),
        )
        if obs.wants_debug:
            _debug(graphs, street, overview, obs)
        return graphs


def _strips(pos: np.ndarray, edges: np.ndarray) -> list[np.ndarray]:
    return [pos[e] for e in edges]


def _debug(g: ConjugateGraphs, street: StreetSegments, overview: OverviewSegments, obs) -> None:
    """Graphs as GraphNodes/GraphEdges and as line strips: street frame, over-view pixels (x=col)."""
    s_pos = np.asarray(street.centroids, dtype=np.float64).reshape(-1, 2)
    o_pos = overview.grid.world_to_pixel(np.asarray(overview.centroids).reshape(-1, 2))[:, ::-1]
    c_pos = s_pos[g.street_edges].mean(axis=1) if len(g.street_edges) else np.zeros((0, 2))
    obs.debug("street_knn", DebugGraph(s_pos, g.street_edges, [str(i) for i in street.ids]))
    obs.debug("street_knn_lines", DebugLines(_strips(s_pos, g.street_edges), radius_m=0.3))
    o_edges = g.overview_edges[g.overview_edges[:, 0] != g.overview_edges[:, 1]]  # no self-loops
    obs.debug("overview_knn", DebugGraph(o_pos, o_edges, [str(i) for i in overview.ids]))
    obs.debug("overview_knn_lines", DebugLines(_strips(o_pos, o_edges), radius_m=1.0))
    obs.debug("conjugate", DebugGraph(c_pos, g.conj_edges,
                                      [f"{a}-{b}" for a, b in g.street_edges]))
    obs.debug("conjugate_lines", DebugLines(_strips(c_pos, g.conj_edges), radius_m=0.2))
