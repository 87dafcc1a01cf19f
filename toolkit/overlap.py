"""Two neighbouring recipe steps that do not need each other's output run side by side.

In the paper's pipeline the over-view and street steps are independent: the over-view step
(mostly numpy and scipy.ndimage, which release the GIL) then runs in a second thread while the
street step runs in the caller's. Stages share no state and take no randomness from globals, so
the outputs are the same bytes as when the steps run one after the other.

A stage can also start early with its ``prefetch``, the part of its work that needs only some
of its inputs (``prefetch_inputs``), as soon as those are made (``Prefetcher``): the unary
step's distance atlas (over-view only) is built while the street step runs, and the evaluation's
Chamfer metrics and per-point errors run beside the bundle adjustment (whose Ceres solve runs in
a child process, ``toolkit.forked``), so only the camera errors wait for its poses.

The background step talks to a ``BufferedObserver``: its events (start, debug values, warnings,
end) are replayed to the run's observer once both steps are done, so no observer is ever called
from two threads and the order of warnings does not depend on which step finished first. Its
progress bars are not shown (the step in the caller's thread keeps its own).
"""

from __future__ import annotations

from concurrent.futures import Executor, Future
from dataclasses import dataclass, field
from typing import Any, Iterable, Iterator, TypeVar

from toolkit.recipe import StepSpec
from toolkit.stage import KIND_INPUTS, KIND_OPTIONAL, KIND_OUTPUT, Stage
from toolkit.threads import thread_budget, thread_cap
from toolkit.types import RunOutputs

T = TypeVar("T")


@dataclass
class BufferedObserver:
    """Records observer calls for a later ``replay`` (debug values only if the real one wants them)."""

    wants_debug: bool = False
    calls: list[tuple[str, tuple[Any, ...], dict[str, Any]]] = field(default_factory=list)

    def stage_start(self, step: str, stage_key: str) -> None:
        self.calls.append(("stage_start", (step, stage_key), {}))

    def stage_end(self, step: str, seconds: float, output: Any) -> None:
        self.calls.append(("stage_end", (step, seconds, output), {}))

    def debug(self, name: str, value: Any, it: int | None = None, timeline: str | None = None) -> None:
        if self.wants_debug:
            self.calls.append(("debug", (name, value), {"it": it, "timeline": timeline}))

    def progress(self, iterable: Iterable[T], total: int | None = None, desc: str = "") -> Iterator[T]:
        return iter(iterable)

    def warn(self, message: str) -> None:
        self.calls.append(("warn", (message,), {}))

    def replay(self, obs: Any) -> None:
        for name, args, kwargs in self.calls:
            getattr(obs, name)(*args, **kwargs)
        self.calls.clear()


class Prefetcher:
    """Starts each later step's ``prefetch`` as soon as the inputs it names (``prefetch_inputs``)
    are made: in the background thread right after a background step (the unary step's distance
    atlas needs only the over-view, so it is built while the street step still runs), else in the
    pool beside the step that runs next, unless that step holds the GIL or is the step itself."""

    def __init__(self, steps: list[tuple[StepSpec, Stage]], pool: Executor) -> None:
        self.steps, self.pool = steps, pool
        self.started: dict[str, Future] = {}

    def _due(self, outputs: RunOutputs, after: int) -> list[tuple[StepSpec, Stage]]:
        due = []
        for i, (spec, stage) in enumerate(self.steps[after + 1:], after + 1):
            remade = {n for _, earlier in self.steps[after + 1:i] for n in earlier.remakes()}
            if spec.name not in self.started and type(stage).prefetch is not Stage.prefetch \
                    and all(outputs.has(n) and n not in remade for n in stage.prefetch_inputs()):
                due.append((spec, stage))
        return due

    def start_beside(self, outputs: RunOutputs, after: int) -> None:
        """Prefetches the outputs up to step ``after`` allow, in the pool, beside step ``after + 1``."""
        if after + 1 >= len(self.steps) or self.steps[after + 1][1].holds_gil():
            return
        for spec, stage in self._due(outputs, after):
            if spec.name != self.steps[after + 1][0].name:  # the step itself simply runs
                self.started[spec.name] = self.pool.submit(run_prefetch, stage, outputs)

    def run_here(self, outputs: RunOutputs, after: int) -> None:
        """Prefetches the outputs up to step ``after`` allow, in this (background) thread."""
        for spec, stage in self._due(outputs, after):
            job: Future = Future()
            try:
                job.set_result(run_prefetch(stage, outputs))
            except BaseException as exc:  # raised when the step runs: it is that step's error
                job.set_exception(exc)
            self.started[spec.name] = job

    def take(self, name: str) -> Future | None:
        return self.started.pop(name, None)


def run_prefetch(stage: Stage, outputs: RunOutputs) -> Any:
    """``stage.prefetch`` on its inputs, beside a step that keeps a core busy: with the threads left."""
    with thread_cap(thread_budget() - 1):
        return stage.prefetch(**{n: getattr(outputs, n) for n in stage.prefetch_inputs()})


def independent(first: StepSpec, second: StepSpec, recipe_kinds: set[str]) -> bool:
    """True when ``second`` needs nothing ``first`` makes (neither as input nor as optional input
    that this recipe produces), so the two may run side by side."""
    made = KIND_OUTPUT[first.name]
    needs = set(KIND_INPUTS[second.name])
    needs |= {n for n in KIND_OPTIONAL.get(second.name, ()) if any(KIND_OUTPUT[k] == n for k in recipe_kinds)}
    return made not in needs
