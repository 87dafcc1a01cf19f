"""Build (validate everything) and run a recipe; outputs appear atomically or not at all."""

from __future__ import annotations

import logging
import os
import shutil
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from pydantic import ValidationError

from toolkit.capture import StreetCapture
from toolkit.errors import CrossviewError, RecipeError, SceneError
from toolkit.observe import NullObserver, Observer
from toolkit.overlap import BufferedObserver, Prefetcher, independent
from toolkit.recipe import Recipe, StepSpec, load_recipe
from toolkit.registry import Registry, default_registry
from toolkit.scene import FIELD_TO_MANIFEST, load_scene
from toolkit.street_scale import first_guess_alternative, resolve_street_scale, scale_from_matching
from toolkit.stage import KIND_INPUTS, KIND_OPTIONAL, KIND_OUTPUT, KIND_OUTPUT_TYPE, RUN_INPUTS, Stage
from toolkit.status import Assessment, assess
from toolkit.threads import single_threaded_blas, thread_budget
from toolkit.types import RunOutputs, Scene, StreetScale

log = logging.getLogger("crossview.runner")


@dataclass(frozen=True)
class Plan:
    """A validated recipe: its scene, the scene's street capture and instantiated stages, ready to execute."""

    recipe: Recipe
    scene: Scene
    stages: tuple[tuple[StepSpec, Stage], ...]
    capture: StreetCapture


@dataclass
class RunResult:
    out_dir: Path | None
    results: RunOutputs
    timings: dict[str, float]
    warnings: list[str] = field(default_factory=list)
    assessment: Assessment | None = None  # the truth-free self-assessment (toolkit.status)
    scene: Scene | None = None            # the scene as run (its street scale resolved)


def _step_label(spec: StepSpec) -> str:
    return f"steps.{spec.name} ({spec.use})"


def format_validation_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    loc = ".".join(str(p) for p in err.get("loc", ())) or "params"
    more = f" (+{len(exc.errors()) - 1} more)" if len(exc.errors()) > 1 else ""
    return f"{loc}: {err.get('msg', 'invalid')}{more}"


def resolve_scene_path(recipe: Recipe, scene: str | Path | None) -> Path:
    ref = scene if scene is not None else recipe.scene
    if ref is None:
        raise RecipeError(f"{recipe.path}: no scene: set 'scene:' in the recipe or pass --scene DIR")
    p = Path(ref)
    if p.is_absolute() or p.exists() or scene is not None:
        return p
    beside = recipe.path.parent / p
    return beside if beside.exists() else p


def build(recipe: Recipe, scene: str | Path | None = None, registry: Registry | None = None) -> Plan:
    """Validate stage names, params, step dependencies and scene files before any computation."""
    registry = registry or default_registry()
    stages: list[tuple[StepSpec, Stage]] = []
    available = set(RUN_INPUTS)
    for spec in recipe.steps:
        label = _step_label(spec)
        try:
            cls = registry.get(spec.use)
        except CrossviewError as exc:
            raise RecipeError(f"{recipe.path}: steps.{spec.name}.use: {exc}") from exc
        try:
            stage = cls.from_config(spec.params)
        except ValidationError as exc:
            raise RecipeError(f"{recipe.path}: {label}: {format_validation_error(exc)}") from exc
        missing = [n for n in KIND_INPUTS[spec.name] if n not in available]
        if missing:
            kind = next(k for k, v in KIND_OUTPUT.items() if v == missing[0])
            raise RecipeError(f"{recipe.path}: {label} needs a steps.{kind} step before it")
        available.add(KIND_OUTPUT[spec.name])
        stages.append((spec, stage))
    scene_obj = resolve_street_scale(load_scene(resolve_scene_path(recipe, scene)), recipe.street_scale, recipe.path)
    capture = StreetCapture(scene_obj)  # the run's one capture, in metres now that the scale is known
    needed: list[str] = []
    for spec, stage in stages:
        for need in type(stage).scene_needs(stage.params):
            options = need.split("|")
            if not any(scene_obj.has(o) for o in options):
                names = " or ".join(FIELD_TO_MANIFEST.get(o, o) for o in options)
                raise SceneError(f"{_step_label(spec)} needs {names}, which "
                                 f"{scene_obj.root / 'scene.yaml'} does not name")
            needed += options
    from toolkit.validate import check_scene_files

    check_scene_files(scene_obj, needed, [stage for _, stage in stages], capture)
    # a cloud too large to hold is analysed on every k-th point (read only once its header is checked)
    return Plan(recipe=recipe, scene=scene_obj, stages=tuple(stages), capture=street_capture(scene_obj, recipe))


def street_capture(scene: Scene, recipe: Recipe) -> StreetCapture:
    """The scene's street capture; a cloud of more than ``stream.max_points`` points is analysed on
    every k-th point (``toolkit.stream``)."""
    from toolkit.stream import StreamSettings, thinning_step

    settings = recipe.stream or StreamSettings()
    if not scene.has("street_cloud"):
        return StreetCapture(scene)
    from toolkit.io.attributes import open_cloud

    step = thinning_step(open_cloud(scene.files.street_cloud).count, settings.max_points)
    if step > 1:
        log.info("%s: more than stream.max_points (%s) points: the analysis takes one point in %d, the registered "
                 "clouds are written a chunk at a time", scene.files.street_cloud, f"{settings.max_points:,}", step)
    return StreetCapture(scene, step, settings.chunk_points)


def _run_step(spec: StepSpec, stage: Stage, outputs: RunOutputs, obs: Any,
              prefetched: Future | None = None) -> tuple[Any, float]:
    """One step on its inputs from ``outputs``: (output, seconds); errors name the step.
    ``prefetched``: the stage's ``prefetch``, started beside the step before (an error in it is
    this step's error)."""
    kwargs = {n: getattr(outputs, n) for n in KIND_INPUTS[spec.name] + KIND_OPTIONAL.get(spec.name, ())}
    obs.stage_start(spec.name, spec.use)
    t0 = time.perf_counter()
    try:
        if prefetched is not None:
            kwargs["prefetched"] = prefetched.result()
        out = stage(**kwargs, obs=obs)
    except CrossviewError as exc:
        msg = str(exc)
        raise type(exc)(msg if msg.startswith("steps.") else f"{_step_label(spec)}: {msg}") from exc
    seconds = time.perf_counter() - t0
    expected = KIND_OUTPUT_TYPE[spec.name]
    if not isinstance(out, expected):
        raise TypeError(f"{spec.use} returned {type(out).__name__}, expected {expected.__name__}")
    obs.stage_end(spec.name, seconds, out)
    return out, seconds


class _Rescale(Exception):
    """The matching found another street scale: the street step runs again at it."""

    def __init__(self, scale: StreetScale, made: RunOutputs, seconds: float) -> None:
        super().__init__(f"street scale {scale.value:g}")
        self.scale, self.made, self.seconds = scale, made, seconds


def execute(plan: Plan, obs: Observer | None = None, overlap: bool | None = None,
            keep: RunOutputs | None = None) -> tuple[RunOutputs, dict[str, float]]:
    """Run the stages in recipe order; returns what they made (with the scene and its capture, whose
    street scale is the one the run settled on) and seconds per step.

    ``overlap`` (default: when the thread budget has two threads, ``toolkit.threads``): a step and
    the next one run side by side when the next needs nothing from it, and a stage's ``prefetch``
    starts in a second thread as soon as its inputs are made (``toolkit.overlap``); step seconds
    then add up to more than the run's wall time.

    Without GPS (street scale ``matching``), the street segments are checked against the over-view
    right after the street step (``toolkit.street_scale.scale_from_matching``); when they fit at
    another scale, the steps run again from the street step at it (the over-view is kept). The
    seconds of that check and of the street passes it discarded are ``scale``.

    ``keep``: outputs made before (the over-view) that the steps do not make again.
    """
    obs = obs or NullObserver()
    overlap = thread_budget() >= 2 if overlap is None else overlap
    spent, made = 0.0, keep
    while True:
        try:
            outputs, timings = _execute(plan, obs, overlap, made)
        except _Rescale as r:
            plan = _with_scale(plan, r.scale)
            spent += r.seconds
            made = r.made
            log.info("street scale %.4g (frame units per metre) from the matching: the street step runs again at it",
                     r.scale.value)
            continue
        if spent or "scale" in timings:
            timings["scale"] = timings.get("scale", 0.0) + spent
        return outputs, timings


@dataclass(frozen=True)
class Try:
    """One registration of a run: the street scale it ran at, where that scale came from, its verdict
    (``toolkit.status``) and seconds."""

    street_scale: float
    scale_from: str  # "run": as the run settled it; "first guess": the cameras' height (toolkit.street_scale)
    status: str
    confidence: float
    reason: str
    seconds: float

    def as_dict(self) -> dict[str, Any]:
        return {"street_scale": round(self.street_scale, 6), "scale_from": self.scale_from, "status": self.status,
                "confidence": self.confidence, "reason": self.reason}


@dataclass(frozen=True)
class Assessed:
    """The registration a run keeps, with its warnings and notes, and every try (one unless retried)."""

    outputs: RunOutputs
    timings: dict[str, float]
    assessment: Assessment
    warnings: tuple[str, ...]
    notes: tuple[str, ...]
    tries: tuple[Try, ...]


def _try(plan: Plan, obs: Observer, overlap: bool | None, scale_from: str, keep: RunOutputs | None = None,
         seen: int = 0) -> Assessed:
    """One registration; its warnings are the observer's from the ``seen``-th on and those logged."""
    t0 = time.perf_counter()
    with collected_log() as logged:
        outputs, timings = execute(plan, obs, overlap, keep)
    assessment = assess(outputs)
    verdict = Try(outputs.scene.street_scale.value, scale_from, assessment.status, assessment.confidence,
                  assessment.main_reason, time.perf_counter() - t0)
    warnings = list(getattr(obs, "warnings", []))[seen:] + logged.warnings
    return Assessed(outputs, timings, assessment, tuple(warnings), tuple(logged.notes), (verdict,))


def execute_assessed(plan: Plan, obs: Observer | None = None, overlap: bool | None = None) -> Assessed:
    """``execute``, assessed without truth. When the registration is unreliable and the façades' scan
    moved the street scale away from the cameras' height first guess (no GPS,
    ``toolkit.street_scale.first_guess_alternative``), the steps run again from the street step at
    the first guess (the over-view is kept), and that registration is kept when it is ``ok``."""
    obs = obs or NullObserver()
    first = _try(plan, obs, overlap, "run")
    scale = first.outputs.scene.street_scale
    other = first_guess_alternative(scale)
    if first.assessment.reliable or other is None:
        return first
    log.info("registration unreliable at the street scale %.4g the façades chose (%s): the steps run again from "
             "the street step at the cameras' height first guess %.4g", scale.value, first.assessment.main_reason,
             other.value)
    again = _try(_with_scale(plan, other), obs, overlap, "first guess",
                 RunOutputs(scene=plan.scene, capture=plan.capture, overview=first.outputs.overview),
                 seen=len(getattr(obs, "warnings", [])))
    tries = first.tries + again.tries
    if again.assessment.reliable:
        note = (f"street scale {scale.value:.4g} (the façades' scan) gave an unreliable registration "
                f"({first.assessment.main_reason}); kept: the one at the cameras' height first guess "
                f"{other.value:.4g} (ok, confidence {again.assessment.confidence:.2f})")
        kept, spent = again, first.tries[0].seconds
    else:
        note = (f"the registration at the cameras' height first guess {other.value:.4g} was unreliable too "
                f"({again.assessment.main_reason}); kept: the one at the façades' scale {scale.value:.4g}")
        kept, spent = first, again.tries[0].seconds
    return replace(kept, timings={**kept.timings, "retries": spent}, warnings=kept.warnings + (note,), tries=tries)


def _with_scale(plan: Plan, scale: StreetScale) -> Plan:
    scene = replace(plan.scene, street_scale=scale)
    return replace(plan, scene=scene, capture=replace(plan.capture, scene=scene))


def _settle_scale(plan: Plan, outputs: RunOutputs, obs) -> tuple[RunOutputs, float]:
    """After the street step: the matching's check of an unsettled street scale. Returns the outputs
    with the settled scale and the check's seconds, or raises _Rescale."""
    t0 = time.perf_counter()
    scale = plan.capture.scale
    unary = next((st for sp, st in plan.stages if sp.name == "unary"), None)
    cfg = getattr(getattr(unary, "params", None), "route_prior", None)
    if outputs.overview is None or outputs.street is None or len(outputs.street) == 0 or cfg is None:
        new = replace(scale, settled=True)
    else:
        new = scale_from_matching(scale, outputs.street, outputs.overview, plan.capture, cfg,
                                  workers=thread_budget())
    seconds = time.perf_counter() - t0
    found = new.matching or {}
    if new.source == "matching" and found.get("reason", "").startswith("no distinct"):
        h = found.get("camera_height_frame")
        obs.warn(f"street scale {new.value:.4g}: the façades show no distinct scale against the over-view, so it rests "
                 f"on the cameras' height alone ({h:.3g} frame units above the points under them, taken as "
                 f"{h / new.value:.2f} m); set street_scale when it is known")
    if not new.settled:
        kept = RunOutputs(scene=plan.scene, capture=plan.capture, overview=outputs.overview)
        raise _Rescale(new, kept, seconds)
    scene = replace(outputs.scene, street_scale=new)
    return replace(outputs, scene=scene, capture=replace(plan.capture, scene=scene)), seconds


def _execute(plan: Plan, obs: Observer, overlap: bool,
             made: RunOutputs | None) -> tuple[RunOutputs, dict[str, float]]:
    """One pass of ``execute``; steps whose output ``made`` holds are not run again."""
    outputs = RunOutputs(scene=plan.scene, capture=plan.capture)
    if made is not None and made.overview is not None:
        outputs = replace(outputs, overview=made.overview)
    timings: dict[str, float] = {}
    kinds = {spec.name for spec, _ in plan.stages}
    steps = list(plan.stages)
    stage_of = {spec.name: stage for spec, stage in steps}
    with single_threaded_blas(), ThreadPoolExecutor(1, "crossview-step") as pool:
        early = Prefetcher(steps, pool)

        def behind(k: int, buffered: BufferedObserver) -> tuple[Any, float]:
            done = _run_step(*steps[k], outputs, buffered)
            early.run_here(replace(outputs, **{KIND_OUTPUT[steps[k][0].name]: done[0]}), k + 1)
            return done

        i = 0
        while i < len(steps):
            spec, stage = steps[i]
            if getattr(outputs, KIND_OUTPUT[spec.name]) is not None:  # kept from an earlier pass
                i += 1
                continue
            if overlap:
                early.start_beside(outputs, i - 1)
            if overlap and i + 1 < len(steps) and independent(spec, steps[i + 1][0], kinds):
                buffered = BufferedObserver(obs.wants_debug)
                background = pool.submit(behind, i, buffered)
                try:
                    ahead = _run_step(*steps[i + 1], outputs, obs, early.take(steps[i + 1][0].name))
                finally:
                    done = background.result()  # waits; the earlier step's error wins, as in recipe order
                buffered.replay(obs)
                pairs = [(spec, done), (steps[i + 1][0], ahead)]
                i += 2
            else:
                pairs = [(spec, _run_step(spec, stage, outputs, obs, early.take(spec.name)))]
                i += 1
            for s, (out, seconds) in pairs:
                outputs = replace(outputs, **{KIND_OUTPUT[s.name]: out})
                timings[s.name] = seconds
                for name in stage_of[s.name].remakes():  # e.g. the adjust step's re-made registration
                    if getattr(out, name, None) is not None:
                        outputs = replace(outputs, **{name: getattr(out, name)})
            if any(s.name == "street" for s, _ in pairs) and not plan.capture.scale.settled:
                outputs, timings["scale"] = _settle_scale(plan, outputs, obs)
                plan = replace(plan, scene=outputs.scene, capture=outputs.capture)
            if outputs.costs is not None and not any("costs" in KIND_INPUTS[s.name] + KIND_OPTIONAL.get(s.name, ())
                                                     for s, _ in steps[i:]):
                outputs = replace(outputs, costs=outputs.costs.released())
            if nothing_registered(outputs, steps[i:]):
                obs.warn("no street segment was registered: the steps after refine are skipped and the run "
                         "is assessed as it stands")
                break
    return outputs, timings


def nothing_registered(outputs: RunOutputs, rest: list) -> bool:
    """True once refine has run and kept no transform while steps remain: they would have nothing to
    move, and the run is then a failed registration (exit 4), not a bad input."""
    t = outputs.transforms
    return bool(rest) and t is not None and not np.asarray(t.valid, bool).any()


class _LogCollector(logging.Handler):
    """The readers' notes (INFO) and warnings logged on ``crossview.*`` during a run, in order."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.notes: list[str] = []
        self.warnings: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        kept = self.warnings if record.levelno >= logging.WARNING else self.notes
        message = " ".join(record.getMessage().split())
        if message not in kept:  # a file read by several steps notes it each time
            kept.append(message)


def collected_log():
    """Collect ``crossview.*`` log messages for run.log and metrics.json (batch workers included)."""
    from toolkit.logcache import listening

    return listening(_LogCollector())


def _prepare_out(out: Path, overwrite: bool) -> Path:
    if out.exists() and not overwrite:
        raise CrossviewError(f"{out}: output folder already exists (pass --overwrite to replace it)")
    parent = out.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = parent / f".{out.name}.partial-{os.getpid()}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
    except OSError as exc:
        raise CrossviewError(f"{parent}: cannot write the output folder ({exc.strerror or exc})") from exc
    return tmp


def run_recipe(recipe_path: str | Path, scene: str | Path | None = None, out: str | Path | None = None,
               overrides: Iterable[str] = (), observer: Observer | None = None, overwrite: bool = False,
               registry: Registry | None = None, rerun: bool | None = None,
               recipe: Recipe | None = None, overlap: bool | None = None, scheduler: str | None = None) -> RunResult:
    """Load, build and run a recipe, writing ``out`` (default ``out/<recipe name>``) atomically.

    The run is assessed without truth (``toolkit.status``): an unreliable run still writes every
    output and returns normally; ``RunResult.assessment`` says so (``crossview run`` exits 4).

    ``rerun=False`` disables the recipe's rerun log (tests, compare/batch use their own observers).
    ``overlap``: see ``execute`` (False: one step at a time, e.g. to profile each step alone).
    ``scheduler``: a Dask scheduler address for the chunked passes over a street cloud of more than
    ``stream.max_points`` points (``toolkit.stream``; default: ``stream.workers`` local processes, or
    this process); unused for a cloud the run holds whole.
    """
    recipe = recipe or load_recipe(recipe_path, overrides)
    plan = build(recipe, scene=scene, registry=registry)
    out_dir = Path(out) if out is not None else Path("out") / recipe.name
    if plan.capture.step > 1:
        from toolkit.stream import use_client

        with use_client(scheduler, recipe.stream.workers):
            return _run_plan(plan, recipe, out_dir, overwrite, observer, rerun, overlap)
    if scheduler:
        log.info("--scheduler %s: not used, the street cloud is within stream.max_points and is held whole",
                 scheduler)
    return _run_plan(plan, recipe, out_dir, overwrite, observer, rerun, overlap)


def _run_plan(plan: Plan, recipe: Recipe, out_dir: Path, overwrite: bool, observer: Observer | None,
              rerun: bool | None, overlap: bool | None) -> RunResult:
    from toolkit.outputs import write_outputs  # matplotlib and friends only when running

    tmp = _prepare_out(out_dir, overwrite)
    obs = observer or NullObserver()
    rerun_obs = None
    try:
        rerun_path = recipe.log.get("rerun") if rerun is not False else None
        if rerun_path:
            from toolkit.observe import MultiObserver
            from toolkit.viz_rerun import RerunObserver

            target = Path(str(rerun_path).replace("{out}", str(tmp)))
            rerun_obs = RerunObserver(target, max_points=int(recipe.log.get("max_points", 200_000)))
            rerun_obs.log_text("recipe", f"```yaml\n{recipe.to_yaml()}\n```")
            obs = MultiObserver(obs, rerun_obs)
        kept = execute_assessed(plan, obs, overlap)
        outputs, assessment = kept.outputs, kept.assessment
        plan = replace(plan, scene=outputs.scene, capture=outputs.capture)  # the street scale settled on
        if rerun_obs is not None:
            rerun_obs.close()
            rerun_obs = None
        warnings, timings = list(kept.warnings), kept.timings
        write_outputs(tmp, plan, outputs, timings, warnings, assessment, notes=list(kept.notes),
                      progress=obs.progress, tries=kept.tries)
        if out_dir.exists():
            shutil.rmtree(out_dir)
        tmp.rename(out_dir)
        return RunResult(out_dir=out_dir, results=outputs, timings=timings, warnings=warnings,
                         assessment=assessment, scene=plan.scene)
    except BaseException:
        if rerun_obs is not None:
            try:
                rerun_obs.close()
            except Exception:
                pass
        shutil.rmtree(tmp, ignore_errors=True)
        raise
