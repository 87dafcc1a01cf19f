"""match.icm — iterated conditional modes from the winner-takes-all labelling (a local baseline)."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from toolkit.matching.mrf import SmoothnessParams
from toolkit.matching.solvers_common import solve_stage
from toolkit.matching.solvers_local import icm
from toolkit.stage import Stage
from toolkit.types import ConjugateGraphs, DataCosts, Matches


class ICM(Stage):
    """Sweeps the conjugate nodes in order, each taking its best label given its neighbours'."""

    kind = "match"
    name = "icm"

    class Params(SmoothnessParams):
        max_iters: int = Field(50, ge=1, description="maximum number of sweeps over the nodes (count)")

    def __call__(self, graphs: ConjugateGraphs, costs: DataCosts, obs: Any) -> Matches:
        p = self.params
        return solve_stage(graphs, costs, p, obs, self.key(),
                           lambda mrf, log: icm(mrf, max_iters=p.max_iters, on_iter=log))
