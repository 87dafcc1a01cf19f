"""Stage base class, parameter base and the per-kind contracts.

A stage is a class with ``kind``, ``name``, a nested ``Params`` (a ``StageParams``) and
``__call__`` taking its typed inputs (named as in ``KIND_INPUTS``) plus ``obs``. The constructor
takes only its Params: no I/O. ``from_config`` builds it from a plain mapping (detectron2 style).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar, Generic, Mapping, Protocol, TypeVar, runtime_checkable

from pydantic import BaseModel, ConfigDict

from toolkit.types import (
    AdjustedCameras,
    ConjugateGraphs,
    DataCosts,
    Matches,
    Metrics,
    OverviewSegments,
    Registration,
    Scene,
    SegmentTransforms,
    StreetSegments,
)

if TYPE_CHECKING:
    from toolkit.capture import StreetCapture

# Kinds in pipeline order, the name of what each produces, and what each consumes.
KINDS: tuple[str, ...] = (
    "overview", "street", "graph", "unary", "match", "refine", "warp", "adjust", "evaluate",
)
KIND_OUTPUT: dict[str, str] = {
    "overview": "overview", "street": "street", "graph": "graphs", "unary": "costs",
    "match": "matches", "refine": "transforms", "warp": "registration", "adjust": "cameras",
    "evaluate": "metrics",
}
KIND_OUTPUT_TYPE: dict[str, type] = {
    "overview": OverviewSegments, "street": StreetSegments, "graph": ConjugateGraphs,
    "unary": DataCosts, "match": Matches, "refine": SegmentTransforms, "warp": Registration,
    "adjust": AdjustedCameras, "evaluate": Metrics,
}
# Required inputs (by output name, plus "scene" and "capture", the run's StreetCapture: the street
# cloud and COLMAP model in metres, GPS); OPTIONAL ones are passed as None when absent. Names are
# fields of ``toolkit.types.RunOutputs``.
KIND_INPUTS: dict[str, tuple[str, ...]] = {
    "overview": ("scene",),
    "street": ("scene", "capture"),
    "graph": ("street", "overview"),
    "unary": ("graphs", "street", "overview", "scene", "capture"),
    "match": ("graphs", "costs"),
    "refine": ("matches", "street", "overview", "scene", "capture"),
    "warp": ("transforms", "street", "scene", "capture"),
    "adjust": ("registration", "scene", "capture"),
    "evaluate": ("registration", "scene"),
}
RUN_INPUTS: tuple[str, ...] = ("scene", "capture")  # given by the runner, made by no step
KIND_OPTIONAL: dict[str, tuple[str, ...]] = {
    "refine": ("graphs",),
    "evaluate": ("cameras", "matches", "street", "overview", "transforms"),
}


class StageParams(BaseModel):
    """Base of every stage's Params: unknown fields rejected, immutable, documented fields."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class Stage:
    """Base class of all stages. Subclasses set kind, name, Params and implement __call__."""

    kind: ClassVar[str] = ""
    name: ClassVar[str] = ""
    Params: ClassVar[type[StageParams]] = StageParams

    def __init__(self, params: StageParams | None = None) -> None:
        self.params = params if params is not None else self.Params()

    @classmethod
    def key(cls) -> str:
        return f"{cls.kind}.{cls.name}"

    @classmethod
    def from_config(cls, config: Mapping[str, Any] | None = None) -> "Stage":
        return cls(cls.Params(**dict(config or {})))

    @classmethod
    def scene_needs(cls, params: StageParams) -> tuple[str, ...]:
        """Scene file keys (``SceneFiles`` fields) this stage reads. ``"a|b"`` means either one."""
        return ()

    def check_scene(self, scene: Scene) -> None:
        """What ``__call__`` would reject in the scene files, with this stage's parameters, found from
        headers before anything is computed (``build()`` runs it after the generic file checks)."""

    def holds_gil(self) -> bool:
        """True when the step keeps Python's GIL for most of its run (a C++ solver that does not
        release it): the runner then starts no ``prefetch`` beside it, as that would only wait."""
        return False

    def remakes(self) -> tuple[str, ...]:
        """Earlier outputs this step's output replaces for the steps after it (the adjust step's
        re-made registration, ``AdjustedCameras.registration``); no prefetch reading them runs before it."""
        return ()

    def prefetch_inputs(self) -> tuple[str, ...]:
        """The inputs ``prefetch`` takes (default: the required ones, ``KIND_INPUTS``)."""
        return KIND_INPUTS[self.kind]

    def prefetch(self, **inputs: Any) -> Any:
        """Work that needs only ``prefetch_inputs``; None: nothing to do. The runner calls it in a
        second thread as soon as those inputs are made (``toolkit.overlap.Prefetcher``) and passes
        the result to ``__call__`` as ``prefetched=`` (a stage that overrides it takes that
        keyword; it is not passed when no prefetch ran). It gets no observer. A result the stage
        wants to free before it returns goes in a ``Handoff``: the runner holds its prefetch result
        until the step ends.
        """
        return None

    def __repr__(self) -> str:
        return f"{self.key()}({self.params!r})"


T = TypeVar("T")


class Handoff(Generic[T]):
    """A prefetch result its stage takes out (``take``), so that it is freed when the stage drops it."""

    def __init__(self, value: T) -> None:
        self._value: T | None = value

    def take(self) -> T:
        value, self._value = self._value, None
        if value is None:
            raise RuntimeError("Handoff.take: already taken")
        return value


@runtime_checkable
class OverviewStage(Protocol):
    def __call__(self, scene: Scene, obs: Any) -> OverviewSegments: ...


@runtime_checkable
class StreetStage(Protocol):
    def __call__(self, scene: Scene, capture: StreetCapture, obs: Any) -> StreetSegments: ...


@runtime_checkable
class GraphStage(Protocol):
    def __call__(self, street: StreetSegments, overview: OverviewSegments, obs: Any) -> ConjugateGraphs: ...


@runtime_checkable
class UnaryStage(Protocol):
    def __call__(self, graphs: ConjugateGraphs, street: StreetSegments, overview: OverviewSegments,
                 scene: Scene, capture: StreetCapture, obs: Any) -> DataCosts: ...


@runtime_checkable
class MatchStage(Protocol):
    def __call__(self, graphs: ConjugateGraphs, costs: DataCosts, obs: Any) -> Matches: ...


@runtime_checkable
class RefineStage(Protocol):
    def __call__(self, matches: Matches, street: StreetSegments, overview: OverviewSegments, scene: Scene,
                 capture: StreetCapture, obs: Any, graphs: ConjugateGraphs | None = None) -> SegmentTransforms: ...


@runtime_checkable
class WarpStage(Protocol):
    def __call__(self, transforms: SegmentTransforms, street: StreetSegments, scene: Scene,
                 capture: StreetCapture, obs: Any) -> Registration: ...


@runtime_checkable
class AdjustStage(Protocol):
    def __call__(self, registration: Registration, scene: Scene, capture: StreetCapture,
                 obs: Any) -> AdjustedCameras: ...


@runtime_checkable
class EvaluateStage(Protocol):
    def __call__(self, registration: Registration, scene: Scene, obs: Any, **optional: Any) -> Metrics: ...


KIND_PROTOCOL: dict[str, type] = {
    "overview": OverviewStage, "street": StreetStage, "graph": GraphStage, "unary": UnaryStage,
    "match": MatchStage, "refine": RefineStage, "warp": WarpStage, "adjust": AdjustStage,
    "evaluate": EvaluateStage,
}
