"""match.loopy_bp — the paper's inference: min-sum loopy BP on the conjugate graph (Eq. 3–4)."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field

from toolkit.matching.mrf import SmoothnessParams
from toolkit.matching.solvers_bp import loopy_bp
from toolkit.matching.solvers_common import solve_stage
from toolkit.stage import Stage
from toolkit.types import ConjugateGraphs, DataCosts, Matches


class LoopyBP(Stage):
    """Synchronous min-sum loopy belief propagation with O(L + |compatible|) messages.

    Stops when the energy of the belief-argmin labelling has not changed for ``patience``
    iterations (the paper's criterion), optionally also when the messages have settled
    (``message_tol``). Damping 0.5 is the default: the paper's plain synchronous update oscillates
    with period 2 on the campus scenes for small c1 (c1 ≤ 0.1–0.3 depending on the data term; see
    bench/table1.py), the damped one settles in 5–10 iterations. Where it still cycles (the best
    energy has not improved for ``stall_iters`` iterations) it halves (1 − damping), up to
    ``max_damping``, and goes on, with ``patience`` counted in the same message travel
    (docs/matching.md). It gives up at ``max_iters`` or at max_damping (then warns). Returns the
    lowest-energy labelling seen, then (``polish``) lets ICM improve single nodes of it and of the
    final messages decoded sequentially (each node conditioned on its earlier neighbours' labels, as
    TRW-S decodes): the belief argmin can leave a node whose label is strictly
    worse than another given its neighbours' final labels (campus seed 3, label map: E 259.563 for
    BP vs 259.462 for ICM from winner-takes-all; held-out seed 7, DSM: 190.903 vs 190.872, polished
    190.872). Polishing is not in the paper (polish=False is its output); it cannot make BP worse
    than its fixed point, but BP can still settle in a worse basin than ICM from winner-takes-all
    (held-out seed 6, OSM: 324.764 vs 324.308).
    """

    kind = "match"
    name = "loopy_bp"

    class Params(SmoothnessParams):
        max_iters: int = Field(300, ge=1, description="maximum number of message-passing iterations")
        damping: float = Field(0.5, ge=0.0, lt=1.0,
                               description="message damping: new = damping·old + (1 − "
                                           "damping)·update (0-1; 0: the paper's plain update)")
        patience: int = Field(2, ge=1, description="consecutive iterations with unchanged energy that count "
                                                   "as converged (count; 1: the paper's criterion)")
        energy_tol: float = Field(1e-9, ge=0.0, description="relative energy change regarded as no change")
        message_tol: float | None = Field(
            None, gt=0.0, description="also require every message entry to move less than this "
                                      "per iteration (cost units; None: energy alone)")
        stall_iters: int | None = Field(
            30, ge=1, description="iterations without a better energy before damping harder, or "
                                  "giving up at max_damping (count; None: run to max_iters)")
        max_damping: float | None = Field(
            0.9375, ge=0.0, lt=1.0, description="after stall_iters without a better energy, halve "
                                                "(1 − damping) up to this instead of giving up (None: give up)")

        polish: bool = Field(
            True, description="finish with ICM from the best BP labelling and the decoded "
                              "messages (never raises the energy; False: the paper)")
        float32_messages: bool = Field(
            True, description="keep messages in float32 (energies are still computed in float64)")

    def __call__(self, graphs: ConjugateGraphs, costs: DataCosts, obs: Any) -> Matches:
        p = self.params
        return solve_stage(graphs, costs, p, obs, self.key(), lambda mrf, log: loopy_bp(
            mrf, max_iters=p.max_iters, damping=p.damping, patience=p.patience, energy_tol=p.energy_tol,
            message_tol=p.message_tol, stall_iters=p.stall_iters, max_damping=p.max_damping,
            dtype=np.float32 if p.float32_messages else np.float64, polish=p.polish, on_iter=log))
