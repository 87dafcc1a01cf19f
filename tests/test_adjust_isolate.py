"""run_isolated: the same result from a forked child; errors come back; one thread: in-process."""

from __future__ import annotations

import os

import numpy as np
import pytest

from toolkit.adjust.isolate import isolates, run_isolated


def _pid_and_sum(a: np.ndarray) -> tuple[int, np.ndarray]:
    return os.getpid(), np.cumsum(a) * 1.1


def _fails(message: str) -> None:
    raise ValueError(message)


def test_child_returns_the_same_bytes():
    a = np.random.default_rng(0).normal(size=10_000)
    pid, out = run_isolated(_pid_and_sum, a)
    assert out.tobytes() == _pid_and_sum(a)[1].tobytes()
    assert (pid != os.getpid()) == isolates()


def test_errors_come_back():
    with pytest.raises(ValueError, match="no observations"):
        run_isolated(_fails, "no observations")


def test_one_thread_runs_here(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert not isolates()
    assert run_isolated(_pid_and_sum, np.ones(3))[0] == os.getpid()
