"""Two neighbouring recipe steps that do not need each other's output run side by side.

In the paper's pipeline the over-view and street steps are independent: the over-view step
(mostly numpy and scipy.ndimage, which release the GIL) then runs in a second thread while the
street step runs in the caller's. Stages share no state and take no randomness from globals, so
the outputs are the same bytes as when the steps run one after the other.

A step that needs the one before only as an optional input starts early with its stage's
``prefetch``, the part that needs only its required inputs: the evaluation's Chamfer metrics and
per-point errors run beside the bundle adjustment (whose Ceres solve runs in a child process,
``toolkit.adjust.isolate``), and only the camera errors wait for the adjusted poses.

The background step talks to a ``BufferedObserver``: its events (start, debug values, warnings,
end) are replayed to the run's observer once both steps are done, so no observer is ever called
from two threads and the order of warnings does not depend on which step finished first. Its
progress bars are not shown (the step in the caller's thread keeps its own).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterable, Iterator, TypeVar

from toolkit.recipe import StepSpec
from toolkit.stage import KIND_INPUTS, KIND_OPTIONAL, KIND_OUTPUT, Stage

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


def prefetches(first: tuple[StepSpec, Stage], second: tuple[StepSpec, Stage]) -> bool:
    """True when ``second``'s stage has a ``prefetch``, needs what ``first`` makes, if at all,
    only as an optional input, and ``first`` does not hold the GIL: the prefetch may then run
    beside ``first``."""
    (first_spec, first_stage), (spec, stage) = first, second
    return (type(stage).prefetch is not Stage.prefetch and not first_stage.holds_gil()
            and KIND_OUTPUT[first_spec.name] not in KIND_INPUTS[spec.name])


def independent(first: StepSpec, second: StepSpec, recipe_kinds: set[str]) -> bool:
    """True when ``second`` needs nothing ``first`` makes (neither as input nor as optional input
    that this recipe produces), so the two may run side by side."""
    made = KIND_OUTPUT[first.name]
    needs = set(KIND_INPUTS[second.name])
    needs |= {n for n in KIND_OPTIONAL.get(second.name, ()) if any(KIND_OUTPUT[k] == n for k in recipe_kinds)}
    return made not in needs
