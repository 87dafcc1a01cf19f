"""Large street clouds (toolkit.stream): a run that analyses every k-th point still writes every input
point, in order, moved as ``crossview apply`` moves them; a 2-worker LocalCluster gives the same bytes."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from tests.registered_runs import RECIPE, laz_scene, tiny_run, workdir
from toolkit.errors import RecipeError


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _thin_run(scene: Path, name: str, *extra: str):
    from toolkit.runner import run_recipe

    res = run_recipe(RECIPE, scene=scene, out=workdir() / name, rerun=False,
                     overrides=["stream.max_points=20000", "stream.chunk_points=15000", *extra])
    return res


def test_read_gives_the_rows_of_the_chunk_iterator(tmp_path):
    from toolkit.io.attributes import open_cloud

    for path in (laz_scene() / "street/cloud.laz", tiny_run("ply")[1] / "street/cloud.ply"):
        src = open_cloud(path)
        whole = next(src.chunks(src.count))
        part = src.read(1234, 777)
        assert part.start == 1234 and np.array_equal(part.xyz, whole.xyz[1234:2011])
        for name in src.names:
            assert np.array_equal(part.values[name], whole.values[name][1234:2011]), name


def test_a_thinned_run_writes_every_point_in_order_as_apply_moves_them(tmp_path):
    import laspy

    from toolkit.apply_warp import apply_run
    from toolkit.io.attributes import open_cloud

    full, scene = tiny_run("laz")
    thin = _thin_run(scene, "thin-laz")
    n = open_cloud(scene / "street/cloud.laz").count
    step = -(-n // 20000)
    reg = thin.results.registration
    assert step > 1 and len(reg.points) == len(range(0, n, step))
    assert np.array_equal(reg.rows, np.arange(0, n, step))
    out = laspy.read(thin.out_dir / "registered.laz")
    src = laspy.read(scene / "street/cloud.laz")
    assert len(out.points) == n
    # every input attribute in input order; the analysis rows where the run put them
    assert np.array_equal(out.intensity, src.intensity) and np.array_equal(out.reflectance, src.reflectance)
    xyz = np.column_stack([out.x, out.y, out.z])
    assert np.abs(xyz[reg.rows] - reg.points).max() < 0.001
    again = apply_run(thin.out_dir, scene / "street/cloud.laz", tmp_path / "again.laz")
    got = laspy.read(again.out)
    assert np.array_equal(got.X, out.X) and np.array_equal(got.segment, out.segment)
    # the truth errors cover every point, and stay close to those of the run that held the whole cloud
    mine, whole = json.loads((thin.out_dir / "metrics.json").read_text()), full.results.metrics.values
    assert mine["truth"]["error_3d"]["n"] == n
    assert mine["street_cloud"] == {"points": n, "analysis_step": step, "analysis_points": len(reg.rows)}
    assert mine["truth"]["horizontal"]["median_m"] < max(1.5 * whole["truth"]["horizontal"]["median_m"], 0.2)


def test_a_local_cluster_gives_the_same_bytes():
    _, scene = tiny_run("laz")
    here = _thin_run(scene, "thin-here")
    there = _thin_run(scene, "thin-cluster", "stream.workers=2")
    for name in ("registered.laz", "registered.ply", "warp.npz", "metrics.json", "transforms.json"):
        assert _digest(here.out_dir / name) == _digest(there.out_dir / name), name


def test_stream_settings_are_checked_with_the_recipe():
    from toolkit.recipe import load_recipe

    with pytest.raises(RecipeError, match="stream.max_point"):
        load_recipe(RECIPE, ["stream.max_point=5"])
    with pytest.raises(RecipeError, match="stream.chunk_points"):
        load_recipe(RECIPE, ["stream.chunk_points=0"])


def test_apply_through_a_local_cluster_gives_the_same_bytes(tmp_path):
    from toolkit.cli import main

    res, scene = tiny_run("laz")
    cloud = scene / "street/cloud.laz"
    assert main(["apply", str(res.out_dir), "--cloud", str(cloud), "--out", str(tmp_path / "here.laz"), "-q"]) == 0
    assert main(["apply", str(res.out_dir), "--cloud", str(cloud), "--out", str(tmp_path / "there.laz"), "-q",
                 "--workers", "2"]) == 0
    assert _digest(tmp_path / "here.laz") == _digest(tmp_path / "there.laz")


def test_thinned_points_are_every_kth_row_of_any_format(tmp_path):
    from toolkit.io.cloud import write_ply
    from toolkit.stream import thinned_points

    xyz = np.random.default_rng(3).uniform(-50, 50, (10_007, 3)).round(3)
    ascii_ply = tmp_path / "a.ply"
    body = "\n".join(" ".join(f"{v:.3f}" for v in row) for row in xyz)
    ascii_ply.write_text(f"ply\nformat ascii 1.0\nelement vertex {len(xyz)}\nproperty double x\nproperty double y\n"
                         f"property double z\nend_header\n{body}\n")
    write_ply(tmp_path / "b.ply", xyz)
    keep = np.sort(np.random.default_rng(4).choice(len(xyz), 900, replace=False))
    for path in (ascii_ply, tmp_path / "b.ply"):
        for step, chunk in ((1, 4096), (3, 1000), (7, 50)):
            thin, kept = thinned_points(path, step, chunk, keep=keep)
            np.testing.assert_array_equal(thin, xyz[::step], err_msg=f"{path} {step}")
            np.testing.assert_array_equal(kept.xyz, xyz[keep], err_msg=f"{path} {step}")
            assert thinned_points(path, step, chunk)[1] is None


class _Shift:
    """A stand-in warp: every point moved by (1, 2, 3)."""

    def move(self, xyz):
        return self, None

    def apply(self, xyz):
        return xyz + [1.0, 2.0, 3.0]


def test_truth_rows_kept_by_the_analysis_read_give_the_errors_of_a_second_pass(tmp_path):
    from toolkit.io.cloud import write_ply
    from toolkit.stream import _KEPT, analysis_points, kept_rows, row_errors

    xyz = np.random.default_rng(5).uniform(-50, 50, (20_011, 3)).round(3)
    write_ply(tmp_path / "c.ply", xyz)
    rows = np.arange(3, len(xyz), 7)
    truth = xyz[rows] + np.random.default_rng(6).normal(0, 0.3, (len(rows), 3))
    np.save(tmp_path / "rows.npy", rows)
    analysis_points(tmp_path / "c.ply", 5, 4000, keep_file=tmp_path / "rows.npy")
    np.testing.assert_array_equal(kept_rows(tmp_path / "c.ply", rows), xyz[rows])
    assert kept_rows(tmp_path / "c.ply", rows[1:]) is None  # other rows: read again
    kept = row_errors(tmp_path / "c.ply", rows, truth, _Shift(), 1000)
    _KEPT.clear()  # the same rows read again, a chunk at a time
    again = row_errors(tmp_path / "c.ply", rows, truth, _Shift(), 1000)
    for a, b in zip(kept, again):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(kept[0], np.linalg.norm(xyz[rows] + [1, 2, 3] - truth, axis=1))
    np.save(tmp_path / "bad.npy", rows[::-1])  # not increasing: nothing kept, the analysis read as ever
    np.testing.assert_array_equal(analysis_points(tmp_path / "c.ply", 5, 4000, keep_file=tmp_path / "bad.npy"),
                                  xyz[::5])
    assert kept_rows(tmp_path / "c.ply", rows) is None and not _KEPT


def test_an_unreachable_scheduler_is_a_one_line_error_and_writes_nothing(tmp_path, capsys):
    from toolkit.cli import main

    _, scene = tiny_run("laz")
    out = tmp_path / "run"
    code = main(["run", str(RECIPE), "--scene", str(scene), "--out", str(out), "--no-rerun", "-q",
                 "-s", "stream.max_points=20000", "--scheduler", "tcp://127.0.0.1:1"])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and "--scheduler tcp://127.0.0.1:1: connection refused" in err[0]
    assert not out.exists() and not list(tmp_path.iterdir())


def test_npy_rows_read_the_rows_asked_for_without_a_memory_map(tmp_path):
    from toolkit.stream import NpyRows

    arr = np.random.default_rng(1).normal(size=(1001, 3))
    np.save(tmp_path / "t.npy", arr)
    rows = NpyRows.open(tmp_path / "t.npy")
    assert len(rows) == 1001 and rows.shape == (1001, 3)
    for lo, hi in ((0, 1001), (0, 1), (17, 530), (1000, 1001), (400, 400), (990, 5000)):
        np.testing.assert_array_equal(np.asarray(rows[lo:hi]), arr[lo:hi])
    np.testing.assert_array_equal(np.asarray(rows[100:600][50:70]), arr[150:170])   # a range of a range
    with pytest.raises(IndexError):
        rows[::2]
    np.save(tmp_path / "flat.npy", arr[:, 0])
    with pytest.raises(ValueError, match="2-D"):
        NpyRows.open(tmp_path / "flat.npy")
