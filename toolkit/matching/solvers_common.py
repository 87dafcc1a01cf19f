"""What every match.* solver shares: its result, per-iteration logging, voting into ``Matches``.

Voting (Ling & Qin 2022, §3.3.1, after Eq. 4): each street segment collects, from every incident conjugate node (street
edge), the over-view segment that edge's label maps it to (null when the label is null). The most
voted over-view segment wins (ties: lower mean unary cost); the segment is null when it has no
incident edge or when the null votes that count strictly outnumber the winner; a tie matches
(optionally only a segment at least ``tie_min_extent_m`` long: a short wall fits many outlines; off
by default, see SmoothnessParams). A null edge (s, k) counts against s only when k has a non-null
vote on some edge: when every edge of k is null, k has
no counterpart in this labelling (a tree, a wall the over-view lacks) and the null edge is explained
by k, not by s. Counting those nulls left a façade with one or two matched neighbours unmatched
beside its unmatchable ones (loopy BP on the 5 campus seeds × 3 sources: mean recall 0.916 → 0.922,
mean precision unchanged at 0.971). confidence = winner votes / all
incident votes (0 when null). T2d is the transform of the lowest-cost agreeing edge: transforms of
different edges have different rotation centres, so averaging t would mix frames. cost = mean unary
cost of the agreeing edges (1 when null).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from toolkit.matching.mrf import MRF
from toolkit.observe import DebugLines, DebugScalar
from toolkit.types import ConjugateGraphs, DataCosts, Matches

IterCallback = Callable[[int, np.ndarray, float, "float | None"], None]


@dataclass
class SolveResult:
    """labels: (E,) local label indices (see MRF); energy of those labels; per-iteration traces."""

    labels: np.ndarray
    energy: float
    energy_trace: list[float] = field(default_factory=list)
    bound_trace: list[float] = field(default_factory=list)
    iterations: int = 0
    converged: bool = False
    lower_bound: float | None = None
    damping: float | None = None  # loopy BP: the damping it ended with


class BestTracker:
    """Keeps the lowest-energy labelling seen and the energy trace; decides 'energy stopped changing'."""

    def __init__(self, mrf: MRF, patience: int, energy_tol: float, on_iter: IterCallback | None) -> None:
        self.mrf, self.patience, self.tol, self.on_iter = mrf, patience, energy_tol, on_iter
        self.trace: list[float] = []
        self.best_labels: np.ndarray | None = None
        self.best_energy = np.inf
        self.still = 0
        self.since_best = 0
        self.prev: float | None = None

    def start(self, local: np.ndarray) -> None:
        """The labelling before the first iteration (not in the trace, but a reference)."""
        self.prev = self._keep(local)

    def _keep(self, local: np.ndarray) -> float:
        e = self.mrf.energy(self.mrf.to_global(local))
        if e < self.best_energy - self.tol * max(1.0, abs(e)) or self.best_labels is None:
            self.best_energy, self.best_labels = e, local.copy()
            self.since_best = -1  # step() counts this iteration
        return e

    def consider(self, local: np.ndarray) -> None:
        """A candidate labelling that is not the iteration's own (kept if it is the best)."""
        self._keep(local)

    def step(self, it: int, local: np.ndarray, bound: float | None = None) -> bool:
        """Record iteration ``it``; True when the energy has not changed for ``patience`` iterations."""
        e = self._keep(local)
        self.since_best += 1
        self.trace.append(e)
        if self.on_iter is not None:
            self.on_iter(it, self.mrf.to_global(local), e, bound)
        same = self.prev is not None and abs(e - self.prev) <= self.tol * max(1.0, abs(e))
        self.still = self.still + 1 if same else 0
        self.prev = e
        return self.still >= self.patience


def iteration_logger(obs: Any) -> IterCallback | None:
    """obs.debug of energy, bound, label changes and labels on the match_iter timeline."""
    if not getattr(obs, "wants_debug", False):
        return None
    prev: dict[str, np.ndarray] = {}

    def log(it: int, labels: np.ndarray, energy: float, bound: float | None) -> None:
        obs.debug("energy", DebugScalar(float(energy)), it=it, timeline="match_iter")
        if bound is not None:
            obs.debug("lower_bound", DebugScalar(float(bound)), it=it, timeline="match_iter")
        if "labels" in prev:
            changed = int(np.count_nonzero(prev["labels"] != labels))
            obs.debug("labels_changed", DebugScalar(float(changed)), it=it, timeline="match_iter")
        prev["labels"] = labels.copy()
        # one-row strip of label ids: a segmentation image whose colours change where labels flip
        obs.debug("labels", labels[None, :].astype(np.int32), it=it, timeline="match_iter")

    return log


def vote(graphs: ConjugateGraphs, costs: DataCosts, edge_label: np.ndarray, tie_min_extent_m: float = 0.0
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(segment_match, confidence, T2d, cost) per street segment from the edge labels (module doc).
    Segment lengths are the street graph's ``extent_m`` node attribute (a missing one counts as long)."""
    n_seg = graphs.street_graph.number_of_nodes()
    se = np.asarray(graphs.street_edges, dtype=np.int64).reshape(-1, 2)
    null = graphs.null_label
    n_edges = len(se)
    seg = np.concatenate([se[:, 0], se[:, 1]])
    edge = np.tile(np.arange(n_edges), 2)
    side = np.repeat([0, 1], n_edges)
    lab = np.asarray(edge_label, dtype=np.int64)[edge]
    is_null = lab == null
    lp = np.asarray(graphs.label_pairs, dtype=np.int64).reshape(-1, 2)
    n_ov = int(lp.max()) + 1 if len(lp) else 1
    ov = np.where(is_null, -1, lp[np.where(is_null, 0, lab), side] if len(lp) else -1)
    ucost = np.asarray(costs.cost)[edge, lab]

    total = np.bincount(seg, minlength=n_seg)
    other = se[edge, 1 - side]
    has_vote = np.bincount(seg[~is_null], minlength=n_seg) > 0
    nulls = np.bincount(seg[is_null & has_vote[other]], minlength=n_seg)  # nulls explained by s (module doc)
    match = np.full(n_seg, -1, dtype=np.int64)
    conf = np.zeros(n_seg)
    mcost = np.ones(n_seg)
    T2d = np.tile(np.eye(3), (n_seg, 1, 1))
    nn = ~is_null
    if not nn.any():
        return match, conf, T2d, mcost
    key = seg[nn] * n_ov + ov[nn]
    uniq, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    mean_cost = np.bincount(inv, weights=ucost[nn]) / cnt
    useg = uniq // n_ov
    order = np.lexsort((mean_cost, -cnt, useg))  # per segment: most votes, then cheapest
    first = order[np.r_[True, useg[order][1:] != useg[order][:-1]]]
    s = useg[first]
    extent = np.array([graphs.street_graph.nodes[int(i)].get("extent_m", np.inf) for i in s], dtype=np.float64)
    ok = (cnt[first] > nulls[s]) | ((cnt[first] == nulls[s]) & (extent >= tie_min_extent_m))
    s, win = s[ok], first[ok]
    if len(s) == 0:
        return match, conf, T2d, mcost
    match[s] = uniq[win] % n_ov
    conf[s] = cnt[win] / total[s]
    mcost[s] = mean_cost[win]
    # lowest-cost agreeing edge of each matched segment gives T2d
    win_of_seg = np.full(n_seg, -1)
    win_of_seg[s] = win
    agree = np.flatnonzero(nn)[win_of_seg[seg[nn]] == inv]
    o = np.lexsort((ucost[agree], seg[agree]))
    agree = agree[o][np.r_[True, seg[agree][o][1:] != seg[agree][o][:-1]]]
    th = np.asarray(costs.theta_rad)[edge[agree], lab[agree]]
    tt = np.asarray(costs.t)[edge[agree], lab[agree]]
    c, sn = np.cos(th), np.sin(th)
    T = np.zeros((len(agree), 3, 3))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -sn, sn, c
    T[:, :2, 2] = tt
    T[:, 2, 2] = 1.0
    T2d[seg[agree]] = T
    return match, conf, T2d, mcost


def to_matches(graphs: ConjugateGraphs, costs: DataCosts, mrf: MRF, result: SolveResult, obs: Any,
               solver: str, tie_min_extent_m: float = 0.0) -> Matches:
    """Vote, warn about degenerate outcomes, log the final matches, build the container."""
    edge_label = mrf.to_global(result.labels) if mrf.n_nodes else np.zeros(0, np.int64)
    match, conf, T2d, mcost = vote(graphs, costs, edge_label, tie_min_extent_m)
    if mrf.n_nodes == 0:
        obs.warn(f"{solver}: the conjugate graph has no nodes (fewer than two street segments?): nothing matched")
    elif np.all(edge_label == mrf.null_label):
        pruned = float(np.mean(mrf.n_act == 1))
        obs.warn(f"{solver}: every street edge took the null label, so no street segment is matched "
                 f"({pruned:.0%} of edges had all candidates pruned; check the unary stage's costs/pruning)")
    elif not np.any(match >= 0):
        obs.warn(f"{solver}: no street segment won a majority of non-null votes: nothing matched")
    if getattr(obs, "wants_debug", False):
        _log_match_lines(graphs, match, T2d, obs)
    return Matches(edge_label=edge_label, segment_match=match, confidence=conf, T2d=T2d, cost=mcost,
                   energy=float(result.energy), energy_trace=np.asarray(result.energy_trace, dtype=np.float64),
                   iterations=int(result.iterations), converged=bool(result.converged),
                   lower_bound=None if result.lower_bound is None else float(result.lower_bound))


def _log_match_lines(graphs: ConjugateGraphs, match: np.ndarray, T2d: np.ndarray, obs: Any) -> None:
    """Lines from each matched street centroid (mapped by its T2d) to its over-view centroid, when the
    graphs carry node positions (``pos``, as graph.knn writes them)."""
    sg, og = graphs.street_graph, graphs.overview_graph
    strips = []
    for s in np.flatnonzero(match >= 0):
        ps, po = sg.nodes[int(s)].get("pos"), og.nodes[int(match[s])].get("pos")
        if ps is None or po is None:
            return
        a = T2d[s] @ np.array([ps[0], ps[1], 1.0])
        strips.append(np.array([a[:2], po], dtype=np.float64))
    if strips:
        obs.debug("matches", DebugLines(strips=strips, radius_m=0.5))


def solve_stage(graphs: ConjugateGraphs, costs: DataCosts, params: Any, obs: Any, solver: str,
                run: Callable[[MRF, IterCallback | None], SolveResult]) -> Matches:
    """Build the MRF from the stage's SmoothnessParams, run the solver, vote, warn, log."""
    from toolkit.matching.mrf import build_mrf

    mrf = build_mrf(graphs, costs, params.c1, params.c2, params.theta_th_deg, params.t_th_m)
    if mrf.n_nodes == 0:
        result = SolveResult(labels=np.zeros(0, np.int64), energy=0.0, converged=True)
    else:
        result = run(mrf, iteration_logger(obs))
        if not result.converged:
            damped = "" if result.damping is None else f", final damping {result.damping:g}"
            obs.warn(f"{solver} did not converge in {result.iterations} iterations (energy still changing or "
                     f"oscillating{damped}); "
                     f"keeping the lowest-energy labelling seen (E = {result.energy:.4f})")
    return to_matches(graphs, costs, mrf, result, obs, solver, params.tie_min_extent_m)
