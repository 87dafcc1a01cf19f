"""Sequential tree-reweighted message passing, TRW-S (Kolmogorov 2006), with the O(L) messages.

Nodes are processed in index order (forward) then in reverse (backward). At node i,
θ̂_i = D_i + Σ_j M_{j→i}; messages to later (forward) or earlier (backward) neighbours are
M_{i→j}(l_j) = min_{l_i} γ_i θ̂_i(l_i) − M_{j→i}(l_i) + V(l_i, l_j), normalised, with
γ_i = 1 / max(#earlier neighbours, #later neighbours) (the monotonic-chain weights).
The labelling is decoded in the forward pass: l_i = argmin D_i + Σ_{j<i} V(·, l_j) + Σ_{j>i} M_{j→i},
and mirrored in the backward pass; the lowest-energy labelling seen is kept.

Lower bound: the graph is split into monotonic chains (each edge in exactly one chain, node i in
max(#earlier, #later) chains). With θ̄ the message reparametrisation (E(x) is unchanged), giving
each chain θ̂_i / n_i at its nodes and θ̄_ij on its edges is an exact decomposition of E, so
Σ_chains min_x E_chain(x) ≤ min E. Each chain minimum is a min-sum DP with the same fast messages,
all chains advanced together, one step per chain position.
"""

from __future__ import annotations

import numpy as np

from toolkit.matching.mrf import MRF, conditional_scores, ranges
from toolkit.matching.solvers_bp import MessagePlan, beliefs, build_plan, send
from toolkit.matching.solvers_common import BestTracker, IterCallback, SolveResult
from toolkit.matching.solvers_local import icm_polish


class ChainBound:
    """The monotonic-chain decomposition of the node order and its lower bound (module doc)."""

    def __init__(self, mrf: MRF, n_earlier: np.ndarray) -> None:
        self.mrf = mrf
        self.n_chain = np.maximum(np.maximum(n_earlier, mrf.deg - n_earlier), 1).astype(np.float64)
        chains: list[list[int]] = []
        arriving: dict[int, list[int]] = {}  # node → chain ids arriving from earlier neighbours
        for i in range(mrf.n_nodes):
            f, d, ne = mrf.in_first[i], mrf.deg[i], n_earlier[i]
            later = mrf.msg_send[f + ne:f + d]
            incoming = arriving.pop(i, [])
            if len(later) == 0 and not incoming:
                chains.append([i])
            for k, j in enumerate(later):
                if k < len(incoming):
                    cid = incoming[k]
                else:
                    cid = len(chains)
                    chains.append([i])
                chains[cid].append(int(j))
                arriving.setdefault(int(j), []).append(cid)
        lengths = np.array([len(c) for c in chains])
        self.singles = np.array([c[0] for c in chains if len(c) == 1], dtype=np.int64)
        multi = [c for c in chains if len(c) > 1]
        msg_key = mrf.msg_recv * mrf.n_nodes + mrf.msg_send  # ascending by construction
        self.first_nodes = np.array([c[0] for c in multi], dtype=np.int64)
        self.steps: list[tuple[MessagePlan, np.ndarray]] = []
        alive = list(range(len(multi)))
        for k in range(int(lengths.max(initial=1)) - 1):
            send_nodes = np.array([multi[c][k] for c in alive], dtype=np.int64)
            recv_nodes = np.array([multi[c][k + 1] for c in alive], dtype=np.int64)
            msgs = np.searchsorted(msg_key, recv_nodes * mrf.n_nodes + send_nodes)
            plan = build_plan(mrf, msgs)
            ends = np.array([len(multi[c]) == k + 2 for c in alive])
            self.steps.append((plan, ends))
            alive = [c for c, e in zip(alive, ends) if not e]

    def __call__(self, msg: np.ndarray) -> float:
        mrf = self.mrf
        theta_hat = beliefs(mrf, msg)
        node_flat = np.repeat(np.arange(mrf.n_nodes), mrf.n_act)
        share = theta_hat / self.n_chain[node_flat]
        bound = 0.0
        if len(self.singles):
            bound += float(np.minimum.reduceat(share, mrf.act_ptr[:-1])[self.singles].sum())
        if not self.steps:
            return bound
        starts = mrf.act_ptr[self.first_nodes]
        f = share[ranges(starts, mrf.n_act[self.first_nodes])]
        for plan, ends in self.steps:
            h = f - msg[plan.src_slots]
            out = send(plan, h, mrf.c1, mrf.c2, normalise=False)
            f_next = share[mrf.slot_node_flat[plan.out_slots]] - msg[plan.out_slots] + out
            seg_min = np.minimum.reduceat(f_next, plan.out_starts)
            bound += float(seg_min[ends].sum())
            keep = ~ends
            f = f_next[ranges(plan.out_starts[keep], plan.out_lens[keep])]
        return bound


def trws(mrf: MRF, max_iters: int = 100, patience: int = 3, energy_tol: float = 1e-9,
         bound_tol: float = 1e-5, polish: bool = True, segment_moves: bool = True,
         on_iter: IterCallback | None = None) -> SolveResult:
    """TRW-S (module doc). Stops when the gap closes, or when the energy has not changed for
    ``patience`` iterations and the bound gained less than bound_tol (relative) in the last one.

    polish: finish with ICM started from the best labelling (never raises its energy): when the LP
    relaxation is not tight the decoded labelling may miss single-node improvements. On the campus
    scenes it changes little (≤ 0.01 of energies ~250).

    segment_moves (with polish): then also re-match whole street segments (solvers_local.
    segment_move_sweeps). Where the relaxation is not tight the decoded labelling can leave a segment
    whose incident edges would all have to change together to lower the energy, which ICM cannot do:
    campus seed 1, label map, E 229.943 → 229.915 (3 edges of one segment; loopy BP had found it)."""
    n = mrf.n_nodes
    msg = np.zeros(int(mrf.msg_ptr[-1]))
    n_earlier = np.array([np.count_nonzero(mrf.msg_send[mrf.in_first[i]:mrf.in_first[i] + mrf.deg[i]] < i)
                          for i in range(n)], dtype=np.int64)
    gamma = 1.0 / np.maximum(np.maximum(n_earlier, mrf.deg - n_earlier), 1)
    out_msgs = mrf.msg_rev[np.arange(len(mrf.msg_send))]  # out_msgs[in_first[i] + r]: i → sender of row r
    fwd = [build_plan(mrf, out_msgs[mrf.in_first[i] + n_earlier[i]:mrf.in_first[i] + mrf.deg[i]])
           for i in range(n)]
    bwd = [build_plan(mrf, out_msgs[mrf.in_first[i]:mrf.in_first[i] + n_earlier[i]]) for i in range(n)]
    bound_of = ChainBound(mrf, n_earlier)
    tracker = BestTracker(mrf, patience, energy_tol, on_iter)
    x = mrf.greedy_local()
    y = x.copy()
    tracker.start(x)
    bounds: list[float] = []
    converged, it = False, 0
    for it in range(1, max_iters + 1):
        for i in range(n):
            theta_hat, block = _node_belief(mrf, msg, i)
            ne = n_earlier[i]
            score = conditional_scores(mrf, i, x, ne) + block[ne:].sum(axis=0)
            x[i] = int(np.argmin(score))
            if len(fwd[i].msgs):
                msg[fwd[i].out_slots] = send(fwd[i], (gamma[i] * theta_hat - block[ne:]).ravel(), mrf.c1, mrf.c2)
        tracker.consider(x)
        for i in range(n - 1, -1, -1):
            theta_hat, block = _node_belief(mrf, msg, i)
            ne = n_earlier[i]
            # the mirror decoding: condition on the later neighbours' (backward) labels
            score = _later_scores(mrf, i, y, ne) + block[:ne].sum(axis=0)
            y[i] = int(np.argmin(score))
            if len(bwd[i].msgs):
                msg[bwd[i].out_slots] = send(bwd[i], (gamma[i] * theta_hat - block[:ne]).ravel(), mrf.c1, mrf.c2)
        bound = bound_of(msg)
        bounds.append(bound)
        stalled = tracker.step(it, y, bound)
        gap = tracker.best_energy - max(bounds)
        gained = bound - bounds[-2] if len(bounds) > 1 else np.inf
        if gap <= energy_tol * max(1.0, abs(tracker.best_energy)) or (
                stalled and gained <= bound_tol * max(1.0, abs(bound))):
            converged = True
            break
    labels, energy = tracker.best_labels, tracker.best_energy
    if polish:
        labels, energy = icm_polish(mrf, labels, energy, segment_moves=segment_moves)
    return SolveResult(labels=labels, energy=energy, energy_trace=tracker.trace,
                       bound_trace=bounds, iterations=it, converged=converged,
                       lower_bound=max(bounds) if bounds else None)


def _later_scores(mrf: MRF, i: int, y: np.ndarray, n_earlier: int) -> np.ndarray:
    """D_i + Σ_{j>i} V(·, y_j): conditional_scores over the later rows of i's incoming block."""
    total = conditional_scores(mrf, i, y)
    if n_earlier == 0:
        return total
    earlier = conditional_scores(mrf, i, y, n_earlier)
    return total - earlier + mrf.act_cost[mrf.act_ptr[i]:mrf.act_ptr[i + 1]]


def _node_belief(mrf: MRF, msg: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray]:
    n = mrf.n_act[i]
    s0 = mrf.msg_ptr[mrf.in_first[i]]
    block = msg[s0:s0 + mrf.deg[i] * n].reshape(mrf.deg[i], n)
    return mrf.act_cost[mrf.act_ptr[i]:mrf.act_ptr[i + 1]] + block.sum(axis=0), block
