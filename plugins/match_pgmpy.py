"""match.pgmpy — the same MRF solved by pgmpy's Mplp: a small-problem correctness reference."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from toolkit.errors import StageError
from toolkit.matching.mrf import SmoothnessParams
from toolkit.matching.solvers_common import solve_stage
from toolkit.matching.solvers_pgmpy import mplp, table_entries
from toolkit.stage import Stage
from toolkit.types import ConjugateGraphs, DataCosts, Matches


class PgmpyMplp(Stage):
    """pgmpy ``Mplp`` (max-product LP, Globerson & Jaakkola 2008) on explicit factor tables.

    pgmpy's other MAP paths build junction trees that explode on loopy graphs, and even Mplp holds
    dense (n_a × n_b) tables, so problems above ``max_nodes`` / ``max_table_entries`` are refused.
    ``Matches.lower_bound`` is Mplp's final dual value; ``iterations`` is 1 (Mplp does not report it).
    """

    kind = "match"
    name = "pgmpy"

    class Params(SmoothnessParams):
        max_nodes: int = Field(200, ge=1, description="refuse conjugate graphs with more nodes than this (count)")
        max_table_entries: int = Field(2_000_000, ge=1,
                                       description="refuse when the pairwise tables hold "
                                                   "more entries than this (count)")
        max_iters: int = Field(1000, ge=1, description="Mplp message-passing iterations (init_iter)")
        tighten_triplets: bool = Field(False, description="tighten the LP with triangle clusters (L^3 tables)")

    def __call__(self, graphs: ConjugateGraphs, costs: DataCosts, obs: Any) -> Matches:
        p = self.params

        def run(mrf, log):
            entries = table_entries(mrf)
            if mrf.n_nodes > p.max_nodes or entries > p.max_table_entries:
                raise StageError(
                    f"{self.key()}: problem too large for pgmpy Mplp ({mrf.n_nodes} nodes, {entries:,} pairwise "
                    f"table entries; limits max_nodes={p.max_nodes}, max_table_entries={p.max_table_entries:,}): "
                    f"use match.trws or match.loopy_bp")
            try:
                result = mplp(mrf, max_iters=p.max_iters, tighten_triplets=p.tighten_triplets)
            except RuntimeError as exc:
                raise StageError(f"{self.key()}: {exc}") from exc
            if log is not None:
                log(1, mrf.to_global(result.labels), result.energy, result.lower_bound)
            return result

        return solve_stage(graphs, costs, p, obs, self.key(), run)
