"""Synthetic matching problems with a planted solution, for solver tests and benchmarks.

Over-view segments are random centroids; the first ``n_matched`` of them are seen from the street
through one rigid transform (plus centroid noise), and ``n_street_only`` street segments have no
over-view counterpart. Graphs follow the ConjugateGraphs contract (labels 2f = (p, q), 2f+1 =
(q, p)); θ and t come from aligning the two centre lines, as the unary stage does. Costs: the true
label is cheap, other labels are random, and a fraction ``decoy_rate`` of wrong labels is as cheap
as a true one (so winner-takes-all fails and the smoothness has work to do). Candidates whose
centre-line lengths differ by more than ``length_tol_m`` are pruned (+inf) when it is set.
"""

from __future__ import annotations

from dataclasses import dataclass

import networkx as nx
import numpy as np
from scipy.spatial import cKDTree

from toolkit.types import ConjugateGraphs, DataCosts


@dataclass(frozen=True)
class SyntheticProblem:
    graphs: ConjugateGraphs
    costs: DataCosts
    truth_match: np.ndarray  # (S,) over-view index per street segment, -1 = no counterpart
    street_xy: np.ndarray
    overview_xy: np.ndarray


def _knn_edges(xy: np.ndarray, k: int) -> np.ndarray:
    n = len(xy)
    if n < 2:
        return np.zeros((0, 2), np.int64)
    kk = min(k, n - 1)
    _, idx = cKDTree(xy).query(xy, k=kk + 1)
    e = np.sort(np.stack([np.repeat(np.arange(n), kk), idx[:, 1:].ravel()], axis=1), axis=1)
    return np.unique(e[e[:, 0] != e[:, 1]], axis=0)


def _street_edges(xy: np.ndarray, topology: str, k: int) -> np.ndarray:
    n = len(xy)
    if topology == "knn":
        return _knn_edges(xy, k)
    order = np.argsort(xy[:, 0] + 1e-3 * xy[:, 1])
    e = np.stack([order[:-1], order[1:]], axis=1)
    if topology == "cycle" and n > 2:
        e = np.vstack([e, [order[-1], order[0]]])
    elif topology != "path":
        raise ValueError(f"unknown topology {topology!r}")
    return np.unique(np.sort(e, axis=1), axis=0)


def conjugate_of(street_edges: np.ndarray, n_seg: int) -> tuple[np.ndarray, np.ndarray]:
    inc: list[list[int]] = [[] for _ in range(n_seg)]
    for e, (j, k) in enumerate(street_edges):
        inc[j].append(e)
        inc[k].append(e)
    pairs = [(min(a, b), max(a, b), s) for s, es in enumerate(inc) for x, a in enumerate(es) for b in es[x + 1:]]
    if not pairs:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    arr = np.array(sorted(pairs), dtype=np.int64)
    return arr[:, :2], arr[:, 2]


def _graph(n: int, edges: np.ndarray, xy: np.ndarray) -> nx.Graph:
    g = nx.Graph()
    g.add_nodes_from((i, {"pos": (float(xy[i, 0]), float(xy[i, 1]))}) for i in range(n))
    g.add_edges_from(map(tuple, edges.tolist()))
    return g


def synthetic_problem(n_matched: int = 10, n_street_only: int = 0, n_overview_only: int = 4, k: int = 4,
                      topology: str = "knn", decoy_rate: float = 0.1, length_tol_m: float | None = None,
                      noise_m: float = 0.5, extent_m: float = 400.0, street_only_clearance_m: float = 0.0,
                      seed: int = 0) -> SyntheticProblem:
    """A random problem (module doc). Street-only segments keep ``street_only_clearance_m`` from every
    over-view segment (in the scene frame), so that no over-view segment can explain them."""
    rng = np.random.default_rng(seed)
    n_ov = n_matched + n_overview_only
    origin = np.array([500_000.0, 4_400_000.0])  # UTM-like scene coordinates
    ov_xy = rng.uniform(0, extent_m, (n_ov, 2)) + origin
    ang = rng.uniform(-np.pi, np.pi)
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    shift = origin + rng.uniform(-1000, 1000, 2)  # the street frame is local (levelled, origin removed)
    # street frame: x_scene = R @ x_street + shift  →  x_street = R^T (x_scene - shift)
    st_xy = (ov_xy[:n_matched] - shift) @ R + rng.normal(0, noise_m, (n_matched, 2))
    extra = np.zeros((0, 2))
    tree = cKDTree(ov_xy)
    while len(extra) < n_street_only:
        cand = rng.uniform(0, extent_m, (4 * n_street_only, 2)) + origin
        far = tree.query(cand)[0] >= street_only_clearance_m
        extra = np.vstack([extra, cand[far]])[:n_street_only]
    extra = (extra - shift) @ R
    st_xy = np.vstack([st_xy, extra])
    truth = np.r_[np.arange(n_matched), -np.ones(n_street_only, np.int64)]
    perm = rng.permutation(len(st_xy))
    st_xy, truth = st_xy[perm], truth[perm]

    street_edges = _street_edges(st_xy, topology, k)
    ov_edges = _knn_edges(ov_xy, k)
    both = (truth[street_edges[:, 0]] >= 0) & (truth[street_edges[:, 1]] >= 0)
    images = np.sort(truth[street_edges[both]], axis=1)  # plant: true images are over-view edges
    ov_edges = np.unique(np.vstack([ov_edges, images]), axis=0) if len(images) else ov_edges
    label_pairs = np.empty((2 * len(ov_edges), 2), np.int64)
    label_pairs[0::2], label_pairs[1::2] = ov_edges, ov_edges[:, ::-1]
    conj, shared = conjugate_of(street_edges, len(st_xy))

    n_e, n_l = len(street_edges), len(label_pairs) + 1
    vs = st_xy[street_edges[:, 1]] - st_xy[street_edges[:, 0]]
    vo = ov_xy[label_pairs[:, 1]] - ov_xy[label_pairs[:, 0]]
    theta = np.arctan2(vo[None, :, 1], vo[None, :, 0]) - np.arctan2(vs[:, None, 1], vs[:, None, 0])
    theta = (theta + np.pi) % (2 * np.pi) - np.pi
    c, s = np.cos(theta), np.sin(theta)
    ms = 0.5 * (st_xy[street_edges[:, 0]] + st_xy[street_edges[:, 1]])
    mo = 0.5 * (ov_xy[label_pairs[:, 0]] + ov_xy[label_pairs[:, 1]])
    t = np.stack([mo[None, :, 0] - (c * ms[:, None, 0] - s * ms[:, None, 1]),
                  mo[None, :, 1] - (s * ms[:, None, 0] + c * ms[:, None, 1])], axis=-1)

    is_true = (truth[street_edges[:, 0]][:, None] == label_pairs[None, :, 0]) & \
              (truth[street_edges[:, 1]][:, None] == label_pairs[None, :, 1]) & both[:, None]
    cost = np.ones((n_e, n_l))
    wrong = rng.uniform(0.3, 1.0, (n_e, n_l - 1))
    decoy = rng.random((n_e, n_l - 1)) < decoy_rate
    wrong[decoy] = rng.uniform(0.02, 0.25, int(decoy.sum()))
    cost[:, :-1] = np.where(is_true, rng.uniform(0.05, 0.2, (n_e, n_l - 1)), wrong)
    if length_tol_m is not None:
        dl = np.abs(np.linalg.norm(vs, axis=1)[:, None] - np.linalg.norm(vo, axis=1)[None, :])
        cost[:, :-1][dl > length_tol_m] = np.inf

    graphs = ConjugateGraphs(
        street_graph=_graph(len(st_xy), street_edges, st_xy), overview_graph=_graph(n_ov, ov_edges, ov_xy),
        street_edges=street_edges, overview_edges=ov_edges, label_pairs=label_pairs, conj_edges=conj,
        conj_shared=shared, conjugate_graph=nx.Graph(conj.tolist()) if len(conj) else nx.Graph())
    graphs.conjugate_graph.add_nodes_from(range(n_e))
    return SyntheticProblem(graphs=graphs, costs=DataCosts(cost=cost, theta_rad=theta, t=t),
                            truth_match=truth, street_xy=st_xy, overview_xy=ov_xy)
