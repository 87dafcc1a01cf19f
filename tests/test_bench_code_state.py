"""bench/cities.py's code state: results are keyed by the commit and a hash of what differs from it,
new modules included (a run that imports a file not yet added is not the commit's run)."""

import importlib.util
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench"


def _cities():
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location("bench_cities", BENCH / "cities.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module         # its dataclasses look their module up there
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(BENCH))


def _git(repo: Path, *args: str) -> None:
    subprocess.run(["git", "-c", "user.email=t@example.org", "-c", "user.name=t", *args], cwd=repo, check=True,
                   capture_output=True)


def test_a_new_module_is_part_of_the_code_state(tmp_path, monkeypatch):
    cities = _cities()
    _git(tmp_path, "init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    _git(tmp_path, "add", "a.py")
    _git(tmp_path, "commit", "-qm", "a")
    monkeypatch.setattr(cities, "REPO", tmp_path)
    clean, clean_hash = cities.code_state()
    assert not clean.endswith("-dirty")

    (tmp_path / "notes.txt").write_text("not code")
    assert cities.code_state() == (clean, clean_hash)

    (tmp_path / "b.py").write_text("y = 1\n")
    dirty, first = cities.code_state()
    assert dirty == clean + "-dirty" and first != clean_hash
    (tmp_path / "b.py").write_text("y = 2\n")
    assert cities.code_state()[1] not in (clean_hash, first)
