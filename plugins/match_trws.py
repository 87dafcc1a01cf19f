"""match.trws — sequential tree-reweighted message passing (Kolmogorov 2006) with a lower bound."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from toolkit.matching.mrf import SmoothnessParams
from toolkit.matching.solvers_common import solve_stage
from toolkit.matching.solvers_trws import trws
from toolkit.stage import Stage
from toolkit.types import ConjugateGraphs, DataCosts, Matches


class TRWS(Stage):
    """TRW-S on the conjugate graph with the same O(L + |compatible|) messages as loopy BP.

    Usually reaches a lower energy than loopy BP; ``Matches.lower_bound`` is the monotonic-chain
    dual bound, so ``energy - lower_bound`` shows how far from optimal the answer can be.
    """

    kind = "match"
    name = "trws"

    class Params(SmoothnessParams):
        max_iters: int = Field(100, ge=1, description="maximum number of forward+backward passes")
        patience: int = Field(3, ge=1, description="passes with unchanged energy (and stalled bound) to stop")
        energy_tol: float = Field(1e-9, ge=0.0, description="relative energy change regarded as no change; "
                                                            "also the relative gap regarded as closed")
        bound_tol: float = Field(1e-5, ge=0.0, description="relative bound gain per pass regarded as stalled")
        polish: bool = Field(True, description="finish with ICM from the best labelling (never raises the energy)")
        segment_moves: bool = Field(True, description="with polish, also re-match one street "
                                                      "segment (all its edges) at a time")

    def __call__(self, graphs: ConjugateGraphs, costs: DataCosts, obs: Any) -> Matches:
        p = self.params
        return solve_stage(graphs, costs, p, obs, self.key(), lambda mrf, log: trws(
            mrf, max_iters=p.max_iters, patience=p.patience, energy_tol=p.energy_tol, bound_tol=p.bound_tol,
            polish=p.polish, segment_moves=p.segment_moves, on_iter=log))
