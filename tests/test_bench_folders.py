"""bench/_common.bound_folders: the benchmarks' output folders stay bounded on disk, and older
variants keep the small files that re-scoring the run status needs."""

import importlib.util
import os
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench" / "_common.py"


def _common():
    spec = importlib.util.spec_from_file_location("bench_common", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _variant(root: Path, name: str, age_s: int) -> Path:
    d = root / f"out-{name}"
    (d / "run-a" / "sparse").mkdir(parents=True)
    (d / "run-a" / "metrics.json").write_text('{"status": "ok", "notes": "%s"}' % ("x" * 100_000))  # a long loop's
    (d / "run-a" / "registered.laz").write_bytes(b"\0" * (100 * 1024))
    (d / "run-a" / "sparse" / "points3D.bin").write_bytes(b"\0" * (100 * 1024))
    (d / "run-a.log").write_text("crossview run ...")
    stamp = 1_000_000 - age_s
    os.utime(d, (stamp, stamp))
    return d


def test_older_variants_keep_their_small_files_then_go(tmp_path):
    common = _common()
    folders = [_variant(tmp_path, f"v{k}", age_s=100 * k) for k in range(5)]  # v0 newest
    common.bound_folders(folders, keep=2, keep_slim=2)
    for d in folders[:2]:  # the newest stay whole
        assert (d / "run-a" / "registered.laz").is_file() and not (d / common.SLIM_MARK).exists()
    for d in folders[2:4]:  # the next two keep metrics.json (however long) and logs, no points, no empty folder
        assert (d / common.SLIM_MARK).is_file()
        assert (d / "run-a" / "metrics.json").is_file() and (d / "run-a.log").is_file()
        assert not (d / "run-a" / "registered.laz").exists() and not (d / "run-a" / "sparse").exists()
    assert not folders[4].exists()

    # a later round: the oldest variants go first, slimmed or not
    newer = _variant(tmp_path, "v5", age_s=-100)
    common.bound_folders(folders + [newer], keep=2, keep_slim=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out-v0", "out-v1", "out-v2", "out-v5"]
    assert (tmp_path / "out-v1" / common.SLIM_MARK).is_file()  # slimmed in this round, newer than v2
    assert (tmp_path / "out-v2" / common.SLIM_MARK).is_file() and not (tmp_path / "out-v0" / common.SLIM_MARK).exists()


def test_without_slim_folders_beyond_keep_are_removed(tmp_path):
    common = _common()
    folders = [_variant(tmp_path, f"v{k}", age_s=100 * k) for k in range(3)]
    common.bound_folders(folders, keep=1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out-v0"]
