"""Local baselines: winner-takes-all on D (the paper's straw man) and ICM (Besag 1986).

ICM starts from the winner-takes-all labelling and visits the nodes in index order, giving each the
label minimising D_i + Σ_j V(·, l_j) for its neighbours' current labels; a label only changes on a
strict improvement, so the energy never increases. It stops after a sweep without change. Sweeps
skip nodes none of whose neighbours changed since their last visit (they cannot improve).
"""

from __future__ import annotations

import numpy as np

from toolkit.matching.mrf import MRF, conditional_scores
from toolkit.matching.solvers_common import BestTracker, IterCallback, SolveResult


def greedy(mrf: MRF, on_iter: IterCallback | None = None) -> SolveResult:
    x = mrf.greedy_local()
    e = mrf.energy(mrf.to_global(x))
    if on_iter is not None:
        on_iter(1, mrf.to_global(x), e, None)
    return SolveResult(labels=x, energy=e, energy_trace=[e], iterations=1, converged=True)


def icm(mrf: MRF, max_iters: int = 50, init: np.ndarray | None = None,
        on_iter: IterCallback | None = None) -> SolveResult:
    x = mrf.greedy_local() if init is None else np.asarray(init, dtype=np.int64).copy()
    tracker = BestTracker(mrf, 1, 0.0, on_iter)
    tracker.start(x)
    converged, it = False, 0
    # a node whose neighbours kept their labels since its last visit cannot improve: only "dirty"
    # nodes are re-scored (the same sweeps and result as visiting every node, at a fraction of the cost)
    dirty = np.ones(mrf.n_nodes, dtype=bool)
    for it in range(1, max_iters + 1):
        changed = 0
        for i in range(mrf.n_nodes):
            if not dirty[i]:
                continue
            dirty[i] = False
            score = conditional_scores(mrf, i, x)
            best = int(np.argmin(score))
            if score[best] < score[x[i]] - 1e-12:
                x[i] = best
                changed += 1
                dirty[mrf.msg_send[mrf.in_first[i]:mrf.in_first[i] + mrf.deg[i]]] = True
        tracker.step(it, x)
        if changed == 0:
            converged = True
            break
    return SolveResult(labels=tracker.best_labels, energy=tracker.best_energy, energy_trace=tracker.trace,
                       iterations=it, converged=converged)


def icm_polish(mrf: MRF, labels: np.ndarray, energy: float, starts: tuple[np.ndarray, ...] = (),
               segment_moves: bool = False) -> tuple[np.ndarray, float]:
    """ICM from ``labels`` and from each of ``starts``; the lowest-energy result if it beats
    ``energy`` (a solver's final labelling), else ``labels`` unchanged: never raises the energy.
    segment_moves: then alternate ``segment_moves`` and ICM until neither lowers the energy."""
    for start in (labels, *starts):
        polished = icm(mrf, init=start)
        if polished.energy < energy:
            labels, energy = polished.labels, polished.energy
    while segment_moves:  # alternate the two until neither lowers the energy
        moved, e_moved = segment_move_sweeps(mrf, labels, energy)
        if e_moved >= energy:
            break
        polished = icm(mrf, init=moved)
        labels, energy = (polished.labels, polished.energy) if polished.energy < e_moved else (moved, e_moved)
    return labels, energy


def segment_move_sweeps(mrf: MRF, labels: np.ndarray, energy: float, max_sweeps: int = 10,
                        max_block: int = 1024) -> tuple[np.ndarray, float]:
    """Re-label the nodes incident to one street segment together, exactly over their best labels.

    A street segment's match is shared by every conjugate node (street edge) incident to it, and
    those nodes are pairwise neighbours: moving the segment changes several labels at once, and
    ICM, one node at a time, has to pass through a labelling where they disagree (c2 on every
    pair), so it never does. For each segment, every combination of its nodes' candidate labels
    (each node's current label, null, and its best labels given the others, as many as keep the
    block within ``max_block`` combinations) is scored exactly on the terms it changes, and the
    best is kept when it lowers the energy. Sweeps over all segments until one changes nothing.
    Never raises the energy.
    """
    x = np.asarray(labels, dtype=np.int64).copy()
    n_seg = int(mrf.street_edges.max()) + 1 if mrf.n_nodes else 0
    seg_nodes = _groups(mrf.street_edges.T.ravel(), n_seg, mrf.n_nodes)   # nodes incident to each segment
    node_conj = _groups(mrf.conj_edges.T.ravel(), mrf.n_nodes, len(mrf.conj_edges))
    for _ in range(max_sweeps):
        improved = False
        for nodes in seg_nodes:
            if len(nodes) < 2:
                continue
            grid = _block_candidates(mrf, x, nodes, max_block)
            if grid is None:
                continue
            touched = np.unique(np.concatenate([node_conj[i] for i in nodes]))
            block_e = _block_energy(mrf, x, nodes, grid, touched)
            current = np.flatnonzero((grid == x[nodes]).all(axis=1))[0]  # every node's options hold its label
            best = int(np.argmin(block_e))
            delta = float(block_e[best] - block_e[current])
            if delta < -1e-9 * max(1.0, abs(energy)):
                x[nodes] = grid[best]
                energy += delta
                improved = True
        if not improved:
            break
    return x, float(mrf.energy(mrf.to_global(x)))


def _groups(keys: np.ndarray, n_keys: int, modulo: int) -> list[np.ndarray]:
    """For each key 0..n_keys-1, the positions (mod ``modulo``) where it occurs in ``keys``: with
    keys = a (2, M) column pair raveled, the rows 0..M-1 that hold it at either end."""
    order = np.argsort(keys, kind="stable")
    ptr = np.searchsorted(keys[order], np.arange(n_keys + 1))
    return [order[ptr[k]:ptr[k + 1]] % modulo for k in range(n_keys)]


def _block_candidates(mrf: MRF, x: np.ndarray, nodes: np.ndarray, max_block: int) -> np.ndarray | None:
    """(B, len(nodes)) local labels: every combination of the nodes' candidate labels (their
    current label, null, and their best labels given x, about max_block combinations in all)."""
    k = max(1, int(np.floor(max_block ** (1.0 / len(nodes)))) - 2)
    options = []
    for i in nodes:
        best = np.argsort(conditional_scores(mrf, i, x), kind="stable")[:k]
        options.append(np.unique(np.concatenate([best, [x[i], mrf.n_act[i] - 1]])))
    if all(len(o) == 1 for o in options):
        return None
    return np.stack(np.meshgrid(*options, indexing="ij"), axis=-1).reshape(-1, len(nodes))


def _block_energy(mrf: MRF, x: np.ndarray, nodes: np.ndarray, grid: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(B,) Σ D over ``nodes`` + Σ V over conjugate ``edges`` when ``nodes`` take the local labels
    grid (B, len(nodes)) and every other node keeps x."""
    g = mrf.to_global(x)
    block = mrf.act_label[mrf.act_ptr[nodes][None, :] + grid]                # (B, n) global
    unary = mrf.cost[nodes[None, :], block].sum(axis=1)
    if len(edges) == 0:
        return unary
    col = np.full(mrf.n_nodes, -1)
    col[nodes] = np.arange(len(nodes))
    ends = []
    for side in (0, 1):
        node = mrf.conj_edges[edges, side]
        lab = np.broadcast_to(g[node], (len(grid), len(edges))).copy()
        inside = col[node] >= 0
        lab[:, inside] = block[:, col[node[inside]]]
        ends.append(lab)
    return unary + mrf.edge_costs(edges, *ends).sum(axis=1)
