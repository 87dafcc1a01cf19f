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


def icm_polish(mrf: MRF, labels: np.ndarray, energy: float,
               starts: tuple[np.ndarray, ...] = ()) -> tuple[np.ndarray, float]:
    """ICM from ``labels`` and from each of ``starts``; the lowest-energy result if it beats
    ``energy`` (a solver's final labelling), else ``labels`` unchanged: never raises the energy."""
    for start in (labels, *starts):
        polished = icm(mrf, init=start)
        if polished.energy < energy:
            labels, energy = polished.labels, polished.energy
    return labels, energy
