"""CLI polish: ``run -q`` prints nothing but errors, batch fails fast on a bad scheduler and prints a
line per finished scene, the street step shows progress, the adjusted points3D ERROR column is
filled, and report.html links only the files the run folder holds."""

from __future__ import annotations

import http.server
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import toolkit.registry as registry_mod
from tests.fake_stages import FAKE_RECIPE, fake_registry
from toolkit.capture import StreetCapture
from toolkit.cli import main
from toolkit.observe import NullObserver

REPO = Path(__file__).resolve().parents[1]
SCHEDULER_DEADLINE_S = 30


@pytest.fixture
def fake_default_registry(monkeypatch):
    monkeypatch.setattr(registry_mod, "_default", fake_registry())


@pytest.fixture
def recipe(tmp_path: Path) -> Path:
    p = tmp_path / "fake.yaml"
    p.write_text(FAKE_RECIPE + 'log: {rerun: "{out}/recording.rrd"}\n')
    return p


# --- run -q ----------------------------------------------------------------------------------------
def test_run_quiet_prints_nothing_but_errors(fake_default_registry, recipe, mini_scene, tmp_path, capsys):
    assert main(["run", str(recipe), "--scene", str(mini_scene), "--out", str(tmp_path / "loud"), "--no-rerun"]) == 0
    assert "crossview —" in capsys.readouterr().out  # the summary table, without -q
    assert main(["run", str(recipe), "--scene", str(mini_scene), "--out", str(tmp_path / "q"), "--no-rerun", "-q"]) == 0
    assert capsys.readouterr() == ("", "")
    assert (tmp_path / "q/metrics.json").is_file()


def test_run_quiet_keeps_the_unreliable_verdict(fake_default_registry, recipe, mini_scene, tmp_path, capsys,
                                                monkeypatch):
    import toolkit.status

    monkeypatch.setattr(toolkit.status, "verdict_line", lambda assessment: "registration unreliable: façades off")
    code = main(["run", str(recipe), "--scene", str(mini_scene), "--out", str(tmp_path / "q"), "--no-rerun", "-q"])
    assert code == toolkit.status.EXIT_UNRELIABLE
    assert capsys.readouterr() == ("", "registration unreliable: façades off\n")


def test_demo_quiet_prints_nothing_but_errors(fake_default_registry, mini_scene, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "recipes").mkdir()
    (tmp_path / "recipes/demo.yaml").write_text(FAKE_RECIPE)
    shutil.copytree(mini_scene, tmp_path / "data/demo")
    assert main(["demo", "-q"]) == 0
    assert capsys.readouterr() == ("", "")
    assert (tmp_path / "out/demo/metrics.json").is_file()
    assert main(["demo"]) == 0
    assert "demo finished" in capsys.readouterr().err


# --- report links ----------------------------------------------------------------------------------
def _hrefs(page: str) -> set[str]:
    return {h for h in re.findall(r'href="([^"]+)"', page) if not h.startswith("figures/")}


@pytest.mark.parametrize("rerun", [True, False])
def test_report_links_match_the_files_present(rerun, fake_default_registry, recipe, mini_scene, tmp_path):
    out = tmp_path / "out"
    assert main(["run", str(recipe), "--scene", str(mini_scene), "--out", str(out), "-q"]
                + ([] if rerun else ["--no-rerun"])) == 0
    page = re.sub(r"<pre>.*?</pre>", "", (out / "report.html").read_text(), flags=re.S)  # not the recipe's text
    links = _hrefs(page)
    assert links and all((out / h).exists() for h in links), links
    assert {"metrics.json", "transforms.json", "run.log"} <= links
    assert ("recording.rrd" in page) == rerun and ("recording.rrd" in links) == rerun
    assert "sparse/" not in links  # the fake recipe has no adjust step


def test_links_name_only_existing_files(tmp_path):
    from toolkit.report_links import links_html

    assert links_html(tmp_path) == ""
    (tmp_path / "sparse").mkdir()
    (tmp_path / "metrics.json").write_text("{}")
    html = links_html(tmp_path)
    assert 'href="metrics.json"' in html and 'href="sparse/"' in html and "rrd" not in html


# --- street progress -------------------------------------------------------------------------------
class RecordingObserver(NullObserver):
    """Counts what each progress bar was advanced by, and whether it was closed."""

    def __init__(self) -> None:
        super().__init__()
        self.bars: list[dict] = []

    def progress(self, iterable, total=None, desc=""):
        bar = {"desc": desc, "total": total, "done": 0, "closed": False}
        self.bars.append(bar)

        def advance():
            try:
                for item in iterable:
                    yield item
                    bar["done"] += 1
            finally:
                bar["closed"] = True

        return advance()


def test_street_step_reports_progress_to_the_end():
    from plugins.street_region_growing import RegionGrowing
    from toolkit.testing.street_toy import toy_street

    obs = RecordingObserver()
    RegionGrowing().segment(toy_street().points, obs)
    assert obs.bars == [{"desc": "street", "total": 100, "done": 100, "closed": True}]


def test_street_progress_bar_closes_on_an_error():
    from plugins.street_region_growing import RegionGrowing
    from toolkit.errors import StageError

    obs = RecordingObserver()
    line = np.linspace(0, 50, 2000)
    with pytest.raises(StageError):
        RegionGrowing().segment(np.column_stack([line, line, line]), obs)
    assert len(obs.bars) == 1 and obs.bars[0]["closed"] and obs.bars[0]["done"] < 100


def test_progress_observer_draws_the_street_bar(mini_scene):
    import io

    from rich.console import Console

    from plugins.street_region_growing import RegionGrowing
    from toolkit.observe import ProgressObserver
    from toolkit.testing.street_toy import toy_street

    obs = ProgressObserver()
    obs.console = Console(file=io.StringIO(), force_terminal=True, width=100)
    RegionGrowing().segment(toy_street().points, obs)
    assert "street" in obs.console.file.getvalue()


# --- points3D ERROR column -------------------------------------------------------------------------
@pytest.mark.parametrize("stage", ["constrained_ba", "none"])
def test_adjusted_points3d_error_column_is_the_mean_reprojection_error(stage, tmp_path):
    from plugins.adjust_constrained_ba import ConstrainedBA
    from plugins.adjust_none import NoAdjust
    from tests.refine_warp_world import ba_problem
    from toolkit.adjust.model import residuals
    from toolkit.io.colmap import read_model, write_model
    from toolkit.scene import load_scene, write_manifest

    model, reg, _ = ba_problem(seed=1, n_cam=14, n_pts=700, noise_px=0.5)
    root = tmp_path / "scene"
    write_model(model, root / "street/sparse", binary=True)
    write_manifest(root, "ba", "EPSG:32617", {"street": {"sparse": "street/sparse"}})
    scene = load_scene(root)
    out = (ConstrainedBA if stage == "constrained_ba" else NoAdjust)()(reg, scene, StreetCapture(scene), NullObserver()).model
    res = np.linalg.norm(residuals(out, out.R, out.t, out.points3d), axis=1)
    pt = out.observations[:, 1].astype(int)
    count = np.bincount(pt, minlength=len(out.points3d))
    expected = np.where(count > 0, np.bincount(pt, weights=res, minlength=len(count)) / np.maximum(count, 1), -1.0)
    write_model(out, tmp_path / "txt", binary=False)
    write_model(out, tmp_path / "bin", binary=True)
    column = np.array([float(line.split()[7]) for line in (tmp_path / "txt/points3D.txt").read_text().splitlines()
                       if not line.startswith("#")])
    np.testing.assert_allclose(column, expected, rtol=1e-12)
    assert (column[count > 0] > 0).all()
    if stage == "constrained_ba":  # 0.5 px pixel noise per axis: a mean error norm of about 0.6 px
        assert 0.3 < np.median(column[count > 0]) < 1.5
    for folder in ("txt", "bin"):
        np.testing.assert_array_equal(read_model(tmp_path / folder).points3d_error_px, column)
    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction(str(tmp_path / "bin"))
    ids = np.asarray(out.points3d_ids)
    np.testing.assert_allclose([rec.points3D[int(i)].error for i in ids], column, rtol=1e-12)


def test_unadjusted_models_keep_writing_zero_errors(tmp_path):
    from tests.refine_warp_world import ba_problem
    from toolkit.io.colmap import replace_poses, write_model

    model, _, _ = ba_problem(seed=1, n_cam=6, n_pts=50)
    moved = replace_poses(model, model.R, model.t + 1.0)  # errors unknown once the poses change
    write_model(moved, tmp_path / "m", binary=False)
    rows = [ln.split() for ln in (tmp_path / "m/points3D.txt").read_text().splitlines() if not ln.startswith("#")]
    assert {r[7] for r in rows} == {"0.0"}


# --- batch --scheduler -----------------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def http_port():
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _QuietHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield server.server_address[1]
    server.shutdown()
    server.server_close()


class _QuietHandler(http.server.BaseHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


SCHEDULER_SCRIPT = """
import asyncio
from distributed import Scheduler

async def main():
    async with Scheduler(host="127.0.0.1", port=0, dashboard=False) as s:
        print(s.address, flush=True)
        await asyncio.sleep(300)

asyncio.run(main())
"""


@pytest.fixture
def lonely_scheduler():
    """A distributed.Scheduler on 127.0.0.1 with no worker, in a child process."""
    proc = subprocess.Popen([sys.executable, "-c", SCHEDULER_SCRIPT], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    try:
        yield proc.stdout.readline().strip()
    finally:
        proc.kill()
        proc.wait()


@pytest.mark.parametrize("kind", ["unreachable", "http", "no-workers"])
def test_batch_fails_fast_on_a_bad_scheduler(kind, request, mini_scene, tmp_path, capsys):
    address = {"unreachable": lambda: f"tcp://127.0.0.1:{_free_port()}",
               "http": lambda: f"tcp://127.0.0.1:{request.getfixturevalue('http_port')}",
               "no-workers": lambda: request.getfixturevalue("lonely_scheduler")}[kind]()
    out = tmp_path / "batch"
    t0 = time.perf_counter()
    code = main(["batch", str(REPO / "recipes/dsm.yaml"), "--scenes", str(mini_scene), "--scheduler", address,
                 "--out", str(out)])
    seconds = time.perf_counter() - t0
    err = capsys.readouterr().err
    assert code == 2 and seconds < SCHEDULER_DEADLINE_S
    assert len(err.strip().splitlines()) == 1 and f"--scheduler {address}" in err and "Traceback" not in err, err
    fragment = {"unreachable": "connection refused", "http": "not a Dask scheduler",
                "no-workers": "the scheduler has no workers"}[kind]
    assert fragment in err
    assert not out.exists()


def test_batch_prints_a_line_per_finished_scene(fake_default_registry, mini_scene, tmp_path, capsys):
    from distributed import LocalCluster

    from toolkit.batch import run_batch

    scenes = [shutil.copytree(mini_scene, tmp_path / "scenes" / name) for name in ("east", "west")]
    recipe = tmp_path / "fake.yaml"
    recipe.write_text(FAKE_RECIPE)
    # worker threads in this process, so they see the fake stages
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp", host="127.0.0.1",
                      dashboard_address=None) as cluster:
        rows = run_batch(recipe, [Path(s) for s in scenes], tmp_path / "batch", scheduler=cluster.scheduler_address)
    assert [r["status"] for r in rows] == ["ok", "ok"]
    out = capsys.readouterr().out
    for name in ("east", "west"):
        found = [ln for ln in out.splitlines() if ln.startswith(f"{name}: ")]
        assert len(found) == 1 and re.fullmatch(rf"{name}: ok, confidence \d\.\d\d, \d+\.\d s", found[0]), out


def test_finished_line_names_the_error():
    from toolkit.batch_client import finished_line

    assert finished_line({"scene": "a", "status": "failed", "confidence": None, "seconds": 1.25,
                          "error": "x.tif: not found"}) == "a: failed, 1.2 s: x.tif: not found"
