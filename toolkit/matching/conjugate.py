"""K-nearest-segment graphs and the conjugate graph (Ling & Qin 2022, §3.3.1), as arrays and networkx graphs.

A conjugate node is a street edge (j, k); its non-null labels are the over-view edges in both
orders (label 2f = edge f as (p, q), label 2f+1 = (q, p)); two conjugate nodes are neighbours when
their street edges share a street segment.
"""

from __future__ import annotations

import networkx as nx
import numpy as np
from scipy.spatial import cKDTree


def knn_edges(centroids: np.ndarray, k: int, max_length: float | None = None) -> np.ndarray:
    """(E,2) int64 undirected edges (i < j, sorted) linking each point to its k nearest points.

    The union of the directed K-NN relations, so a node may have more than k neighbours.
    Edges longer than ``max_length`` are dropped (None: keep all).
    """
    pts = np.asarray(centroids, dtype=np.float64).reshape(-1, 2)
    n = len(pts)
    if n < 2 or k < 1:
        return np.zeros((0, 2), dtype=np.int64)
    pts = pts - pts.mean(axis=0)  # large eastings: keep the KD-tree well conditioned
    kk = min(k, n - 1)
    dist, idx = cKDTree(pts).query(pts, k=kk + 1)
    src = np.repeat(np.arange(n), kk)
    # Column 0 is normally the point itself; with duplicate centroids it may not be, so filter.
    dst = idx[:, 1:].ravel()
    d = dist[:, 1:].ravel()
    keep = dst != src
    if max_length is not None:
        keep &= d <= max_length
    pairs = np.sort(np.stack([src[keep], dst[keep]], axis=1), axis=1)
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    return np.unique(pairs, axis=0).astype(np.int64)


def label_pairs(overview_edges: np.ndarray) -> np.ndarray:
    """(2F,2): row 2f = (p, q), row 2f+1 = (q, p) for over-view edge f = (p, q)."""
    e = np.asarray(overview_edges, dtype=np.int64).reshape(-1, 2)
    out = np.empty((2 * len(e), 2), dtype=np.int64)
    out[0::2] = e
    out[1::2] = e[:, ::-1]
    return out


def conjugate_edges(street_edges: np.ndarray, n_segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of street edges sharing a segment: (C,2) node pairs (a < b) and (C,) shared segment.

    Two distinct undirected edges share at most one segment, so each pair appears once.
    """
    e = np.asarray(street_edges, dtype=np.int64).reshape(-1, 2)
    if len(e) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    # incidence list sorted by segment: (segment, edge index)
    seg = e.ravel()
    node = np.repeat(np.arange(len(e)), 2)
    order = np.lexsort((node, seg))
    seg, node = seg[order], node[order]
    starts = np.searchsorted(seg, np.arange(n_segments + 1))
    pairs, shared = [], []
    for s in range(n_segments):  # one iteration per segment (small), pairs built vectorised
        inc = node[starts[s]:starts[s + 1]]
        if len(inc) < 2:
            continue
        a, b = np.triu_indices(len(inc), k=1)
        pairs.append(np.stack([inc[a], inc[b]], axis=1))
        shared.append(np.full(len(a), s))
    if not pairs:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    p = np.sort(np.concatenate(pairs), axis=1)
    sh = np.concatenate(shared)
    order = np.lexsort((p[:, 1], p[:, 0]))
    return p[order].astype(np.int64), sh[order].astype(np.int64)


def segment_graph(n: int, edges: np.ndarray, centroids: np.ndarray) -> nx.Graph:
    """networkx graph on segment indices 0..n-1; nodes carry ``pos``, edges ``length``."""
    g = nx.Graph()
    c = np.asarray(centroids, dtype=np.float64)
    g.add_nodes_from((i, {"pos": (float(c[i, 0]), float(c[i, 1]))}) for i in range(n))
    lengths = np.linalg.norm(c[edges[:, 1]] - c[edges[:, 0]], axis=1) if len(edges) else []
    g.add_edges_from((int(a), int(b), {"length": float(d)}) for (a, b), d in zip(edges, lengths))
    return g


def conjugate_graph(street_edges: np.ndarray, conj: np.ndarray, shared: np.ndarray) -> nx.Graph:
    """networkx graph on conjugate node indices; nodes carry ``street_edge``, edges ``shared``."""
    g = nx.Graph()
    g.add_nodes_from((i, {"street_edge": (int(a), int(b))}) for i, (a, b) in enumerate(street_edges))
    g.add_edges_from((int(a), int(b), {"shared": int(s)}) for (a, b), s in zip(conj, shared))
    return g
