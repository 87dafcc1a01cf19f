"""Independent neighbouring steps run side by side; results, warnings and errors as in recipe order."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from tests import fake_stages
from tests.fake_stages import FAKE_RECIPE, fake_registry
from toolkit.errors import StageError
from toolkit.observe import NullObserver
from toolkit.overlap import BufferedObserver, independent
from toolkit.recipe import StepSpec, load_recipe
from toolkit.runner import build, execute
from toolkit.stage import Stage
from toolkit.threads import query_workers, thread_budget, thread_cap


def _spec(kind: str) -> StepSpec:
    return StepSpec(name=kind, use=f"{kind}.x", params={})


def test_independent_follows_the_stage_inputs():
    full = {"overview", "street", "graph", "unary", "match", "refine", "warp", "adjust", "evaluate"}
    assert independent(_spec("overview"), _spec("street"), full)
    assert not independent(_spec("street"), _spec("graph"), full)
    assert not independent(_spec("warp"), _spec("adjust"), full)
    # evaluate's optional inputs count when the recipe makes them: the adjusted cameras
    assert not independent(_spec("adjust"), _spec("evaluate"), full)
    assert not independent(_spec("warp"), _spec("evaluate"), full - {"adjust"})


def test_buffered_observer_replays_in_order():
    real = NullObserver()
    buf = BufferedObserver(wants_debug=False)
    buf.stage_start("overview", "overview.x")
    buf.debug("dropped", 1.0)
    buf.warn("first")
    assert list(buf.progress([1, 2])) == [1, 2]
    buf.stage_end("overview", 0.5, None)
    assert real.warnings == [] and real.timings == {}
    buf.replay(real)
    assert real.warnings == ["overview: first"] and real.timings == {"overview": 0.5}
    assert buf.calls == []


@pytest.fixture
def plan(tmp_path: Path, mini_scene: Path):
    p = tmp_path / "fake.yaml"
    p.write_text(FAKE_RECIPE)
    return lambda reg=None: build(load_recipe(p), scene=mini_scene, registry=reg or fake_registry())


def test_overlap_gives_the_same_results_and_warnings(plan, monkeypatch):
    real = fake_stages.FakeOverview.__call__

    def warning_overview(self, scene, obs):
        obs.warn("from overview")
        return real(self, scene, obs)

    monkeypatch.setattr(fake_stages.FakeOverview, "__call__", warning_overview)
    runs = {}
    for overlap in (False, True):
        obs = NullObserver()
        results, timings = execute(plan(), obs, overlap=overlap)
        runs[overlap] = (results, list(timings), obs.warnings)
    (r0, t0, w0), (r1, t1, w1) = runs[False], runs[True]
    assert r0.made() == r1.made() and t0 == t1 == ["overview", "street", "graph", "unary", "match", "refine", "warp"]
    assert w0 == w1 == ["overview: from overview"]
    np.testing.assert_array_equal(r0.overview.label_image, r1.overview.label_image)
    np.testing.assert_array_equal(r0.registration.points, r1.registration.points)


def test_independent_steps_really_run_side_by_side(plan, monkeypatch):
    # each of the two steps waits for the other at a barrier: run one after the other, both time out
    barrier = threading.Barrier(2, timeout=20)
    for cls in (fake_stages.FakeOverview, fake_stages.FakeStreet):
        real = cls.__call__

        def meet(self, *args, _real=real, **kwargs):
            barrier.wait()
            return _real(self, *args, **kwargs)

        monkeypatch.setattr(cls, "__call__", meet)
    results, _ = execute(plan(), NullObserver(), overlap=True)
    assert results.street.point_labels.size > 0


def test_the_earlier_steps_error_wins(plan, monkeypatch):
    def broken_overview(self, scene, obs):
        raise StageError("DSM is all nodata")

    monkeypatch.setattr(fake_stages.FakeOverview, "__call__", broken_overview)
    for overlap in (False, True):
        with pytest.raises(StageError, match=r"^steps.overview \(overview.fake\): DSM is all nodata$"):
            execute(plan(), NullObserver(), overlap=overlap)


def test_thread_budget_honours_omp_num_threads(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert thread_budget() == 1 and query_workers(10_000_000) == 1
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert thread_budget() >= 1
    assert query_workers(10) == 1


def test_thread_cap_lowers_the_budget_inside_the_block(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "8")
    outside = thread_budget()
    with thread_cap(1):
        assert thread_budget() == 1
    assert thread_budget() == outside


# --- prefetch: evaluate's point metrics beside the adjust step -------------------------------
FULL_RECIPE = FAKE_RECIPE + """  adjust: {use: adjust.fake}
  evaluate: {use: evaluate.chamfer}
"""


class FakeAdjust(Stage):
    """The scene's COLMAP model as it is."""
    kind, name = "adjust", "fake"

    def __call__(self, registration, scene, capture, obs):
        from toolkit.types import AdjustedCameras

        return AdjustedCameras(capture.sparse, 0.0, 0.0, 0)


@pytest.fixture
def full_plan(tmp_path: Path, mini_scene: Path):
    from plugins.evaluate_chamfer import Chamfer

    p = tmp_path / "full.yaml"
    p.write_text(FULL_RECIPE)
    reg = fake_registry()
    reg.add(FakeAdjust)
    reg.add(Chamfer)
    return build(load_recipe(p), scene=mini_scene, registry=reg)


def _metrics_json(results) -> str:
    import json

    return json.dumps(results.metrics.values, sort_keys=True, default=str)


def test_prefetch_gives_the_same_metrics(full_plan, monkeypatch):
    from plugins.evaluate_chamfer import Chamfer

    calls = []
    real = Chamfer.prefetch

    def recording(self, **inputs):
        calls.append(threading.current_thread().name)
        return real(self, **inputs)

    monkeypatch.setattr(Chamfer, "prefetch", recording)
    alone, _ = execute(full_plan, NullObserver(), overlap=False)
    assert calls == []
    beside, _ = execute(full_plan, NullObserver(), overlap=True)
    assert len(calls) == 1 and calls[0] != threading.main_thread().name
    assert _metrics_json(alone) == _metrics_json(beside)


def test_prefetch_runs_beside_the_step_before(full_plan, monkeypatch):
    from plugins.evaluate_chamfer import Chamfer

    barrier = threading.Barrier(2, timeout=20)  # one after the other, both would time out
    for cls, name in ((FakeAdjust, "__call__"), (Chamfer, "prefetch")):
        real = getattr(cls, name)

        def meet(self, *args, _real=real, **kwargs):
            barrier.wait()
            return _real(self, *args, **kwargs)

        monkeypatch.setattr(cls, name, meet)
    results, _ = execute(full_plan, NullObserver(), overlap=True)
    assert results.metrics.values["street"]["n_points"] > 0


def test_no_prefetch_beside_a_step_that_holds_the_gil(full_plan, monkeypatch):
    from plugins.evaluate_chamfer import Chamfer

    monkeypatch.setattr(FakeAdjust, "holds_gil", lambda self: True)
    monkeypatch.setattr(Chamfer, "prefetch", lambda self, **kw: pytest.fail("prefetch beside a GIL holder"))
    results, _ = execute(full_plan, NullObserver(), overlap=True)
    assert results.metrics is not None


def test_a_prefetch_error_is_the_evaluate_steps_error(full_plan, monkeypatch):
    from plugins.evaluate_chamfer import Chamfer
    from toolkit.errors import SceneError

    def broken(self, **inputs):
        raise SceneError("truth/street_points.npy: shape (3, 3) does not match")

    monkeypatch.setattr(Chamfer, "prefetch", broken)
    with pytest.raises(SceneError, match=r"^steps.evaluate \(evaluate.chamfer\): truth/street_points.npy"):
        execute(full_plan, NullObserver(), overlap=True)


def test_a_prefetch_starts_after_the_background_step_while_the_next_one_runs(plan, monkeypatch):
    # unary's prefetch needs only the over-view: it runs after the background over-view step,
    # while the street step still runs (the barrier: street waits for the prefetch to start)
    barrier = threading.Barrier(2, timeout=20)
    got = {}
    real_street = fake_stages.FakeStreet.__call__

    def street(self, scene, capture, obs):
        barrier.wait()
        return real_street(self, scene, capture, obs)

    def prefetch(self, overview, scene):
        barrier.wait()
        return overview.ids.copy()

    real_unary = fake_stages.FakeUnary.__call__

    def unary(self, *args, prefetched=None, **kwargs):
        got["prefetched"] = prefetched
        return real_unary(self, *args, **kwargs)

    monkeypatch.setattr(fake_stages.FakeStreet, "__call__", street)
    monkeypatch.setattr(fake_stages.FakeUnary, "prefetch_inputs", lambda self: ("overview", "scene"))
    monkeypatch.setattr(fake_stages.FakeUnary, "prefetch", prefetch)
    monkeypatch.setattr(fake_stages.FakeUnary, "__call__", unary)
    results, _ = execute(plan(), NullObserver(), overlap=True)
    np.testing.assert_array_equal(got["prefetched"], results.overview.ids)


def test_map_in_order_keeps_the_item_order_within_the_budget(monkeypatch):
    from toolkit.threads import map_in_order

    names = set()

    def square(x: int) -> int:
        names.add(threading.current_thread().name)
        return x * x

    assert list(map_in_order(square, range(50), workers=8)) == [x * x for x in range(50)]
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    names.clear()
    assert list(map_in_order(square, range(5), workers=8)) == [0, 1, 4, 9, 16]
    assert names == {threading.main_thread().name}  # one thread: nothing else is started
