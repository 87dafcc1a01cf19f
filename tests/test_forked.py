"""toolkit.forked: one call in a forked child, and independent jobs split between this process and children."""

from __future__ import annotations

import os

import numpy as np
import pytest

import toolkit.forked as forked
from toolkit.forked import can_fork, forks, map_chunks_forked, run_forked
from toolkit.threads import thread_budget, thread_cap

needs_two = pytest.mark.skipif(thread_budget() < 2 or not can_fork(), reason="needs two threads and fork")
SEEN: list[int] = []


def _square_with_pid(jobs: list[int]) -> list[tuple[int, int]]:
    SEEN.extend(jobs)  # a child's changes stay in the child
    return [(j * j, os.getpid()) for j in jobs]


def _fail_on_three(jobs: list[int]) -> list[int]:
    if 3 in jobs:
        raise ValueError("job 3")
    return jobs


@needs_two
def test_children_run_a_share_and_results_keep_job_order():
    SEEN.clear()
    out = map_chunks_forked(_square_with_pid, range(40))
    assert [r for r, _ in out] == [j * j for j in range(40)]
    pids = [p for _, p in out]
    assert len(set(pids)) == 2 and pids[-1] == os.getpid()  # this process takes the last chunk
    here = [j for j, (_, p) in enumerate(out) if p == os.getpid()]
    assert SEEN == here  # what the child appended to SEEN stayed in the child
    assert not forked._BUSY.locked() and forked._JOB is None


def test_one_thread_or_few_jobs_run_here():
    with thread_cap(1):
        assert {p for _, p in map_chunks_forked(_square_with_pid, range(40))} == {os.getpid()}
    assert {p for _, p in map_chunks_forked(_square_with_pid, range(10))} == {os.getpid()}


@needs_two
def test_a_second_map_while_one_runs_stays_here():
    assert forked._BUSY.acquire(blocking=False)
    try:
        assert {p for _, p in map_chunks_forked(_square_with_pid, range(40))} == {os.getpid()}
    finally:
        forked._BUSY.release()


@needs_two
def test_an_error_in_a_child_is_raised_here_with_its_type():
    with pytest.raises(ValueError, match="job 3"):
        map_chunks_forked(_fail_on_three, range(40))  # job 3 is in the child's chunk
    assert not forked._BUSY.locked() and forked._JOB is None


def _map_in_daemon(queue) -> None:
    queue.put({p for _, p in map_chunks_forked(_square_with_pid, range(40))} == {os.getpid()})


def test_a_daemonic_process_like_a_dask_worker_maps_here():
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    proc = ctx.Process(target=_map_in_daemon, args=(queue,), daemon=True)
    proc.start()
    ran_here = queue.get(timeout=60)
    proc.join(timeout=60)
    assert ran_here and proc.exitcode == 0  # no "daemonic processes are not allowed to have children"


def _pid_and_sum(a: np.ndarray) -> tuple[int, np.ndarray]:
    return os.getpid(), np.cumsum(a) * 1.1


def _fails(message: str) -> None:
    raise ValueError(message)


def test_run_forked_returns_the_same_bytes():
    a = np.random.default_rng(0).normal(size=10_000)
    pid, out = run_forked(_pid_and_sum, a)
    assert out.tobytes() == _pid_and_sum(a)[1].tobytes()
    assert (pid != os.getpid()) == forks()


def test_run_forked_errors_come_back():
    with pytest.raises(ValueError, match="no observations"):
        run_forked(_fails, "no observations")


def test_run_forked_with_one_thread_runs_here(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert not forks()
    assert run_forked(_pid_and_sum, np.ones(3))[0] == os.getpid()
