"""End to end on synthetic `tiny` scenes: the paper pipeline runs, is deterministic, and `batch`
on a 2-worker LocalCluster gives the same metrics as separate runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO, synthetic_scene
from toolkit.runner import run_recipe

RECIPE = REPO / "recipes" / "dsm.yaml"


def _tiny(seed: int) -> Path:
    if seed == 0:
        return synthetic_scene("tiny")
    import fcntl

    root = REPO / "data" / f"test-tiny-{seed}"
    with open(REPO / "data" / f".test-tiny-{seed}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / "scene.yaml").is_file():
            from toolkit.synth.generate import generate

            generate("tiny", seed, root)
    return root


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("pipeline")
    out = {}
    for label, seed in (("a", 0), ("b", 0), ("seed1", 1)):
        res = run_recipe(RECIPE, scene=_tiny(seed), out=base / label, rerun=(label == "a"))
        out[label] = res.out_dir
    return out


def test_full_pipeline_outputs(runs):
    from toolkit.io.cloud import read_points
    from toolkit.io.colmap import read_model

    out = runs["a"]
    for name in ("registered.ply", "transforms.json", "metrics.json", "timings.json", "report.html",
                 "recording.rrd", "recipe.yaml", "run.log", "sparse/images.txt", "sparse/images.bin"):
        assert (out / name).exists(), name
    src = read_points(_tiny(0) / "street/cloud.ply")
    reg = read_points(out / "registered.ply")
    assert reg.shape == src.shape and np.isfinite(reg).all()
    truth = np.load(_tiny(0) / "truth/street_points.npy")
    err_h = np.linalg.norm((reg - truth)[:, :2], axis=1)
    # the street frame is arbitrary (hundreds of metres off): registration must land it on the city
    assert np.median(err_h) < 2.0, np.median(err_h)
    assert read_model(out / "sparse").image_names == read_model(_tiny(0) / "street/sparse").image_names
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["matching"]["precision"] >= 0.8


def test_same_recipe_and_seed_give_identical_outputs(runs):
    for name in ("registered.ply", "metrics.json", "transforms.json", "sparse/images.bin", "sparse/points3D.bin"):
        assert (runs["a"] / name).read_bytes() == (runs["b"] / name).read_bytes(), name


def test_batch_on_local_cluster_matches_separate_runs(runs, tmp_path):
    import os

    from toolkit.batch import run_batch

    environ = dict(os.environ)
    rows = run_batch(RECIPE, [_tiny(0), _tiny(1)], tmp_path / "batch", workers=2, progress=False)
    assert dict(os.environ) == environ  # the nanny's OMP_NUM_THREADS=1 stays with the workers
    assert [r["status"] for r in rows] == ["ok", "ok"], rows
    for row, label in zip(sorted(rows, key=lambda r: r["scene"]), ("a", "seed1")):
        scene_out = tmp_path / "batch" / row["scene"]
        assert (scene_out / "metrics.json").read_bytes() == (runs[label] / "metrics.json").read_bytes()
        assert (scene_out / "registered.ply").read_bytes() == (runs[label] / "registered.ply").read_bytes()
    assert (tmp_path / "batch" / "summary.csv").exists() and (tmp_path / "batch" / "summary.md").exists()


def test_batch_reports_a_corrupt_scene_and_finishes_the_others(tmp_path):
    import os
    import shutil

    from toolkit.batch import run_batch

    bad = tmp_path / "scenes" / "corrupt"
    shutil.copytree(_tiny(1), bad, copy_function=os.link)
    (bad / "street/cloud.ply").unlink()
    (bad / "street/cloud.ply").write_bytes(b"ply\ngarbage")
    rows = run_batch(RECIPE, [bad, _tiny(1)], tmp_path / "batch", workers=2, progress=False)
    by = {r["scene"]: r for r in rows}
    assert by["corrupt"]["status"] == "failed" and "cloud.ply" in by["corrupt"]["error"]
    assert by["test-tiny-1"]["status"] == "ok"
    assert "corrupt" in (tmp_path / "batch/summary.md").read_text()


def _malloc_environ() -> dict:
    import os

    return {k: os.environ.get(k) for k in ("MALLOC_TRIM_THRESHOLD_", "MALLOC_ARENA_MAX", "OMP_NUM_THREADS")}


def test_local_cluster_workers_keep_glibc_adaptive_mmap_threshold():
    """Dask's default MALLOC_TRIM_THRESHOLD_ made every stage 1.4-1.8x slower in a worker."""
    import os

    import dask
    from dask.distributed import Client, LocalCluster

    from toolkit.batch import _restore_environ, worker_config

    environ = dict(os.environ)
    with dask.config.set(worker_config()):
        cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                               silence_logs=40)
    _restore_environ(environ)  # the nanny wrote the workers' variables here too
    with cluster, Client(cluster) as client:
        env = client.submit(_malloc_environ, pure=False).result()
    assert env == {"MALLOC_TRIM_THRESHOLD_": None, "MALLOC_ARENA_MAX": "1", "OMP_NUM_THREADS": "1"}
