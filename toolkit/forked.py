"""Work that keeps Python's GIL, run in forked children while this process goes on.

Threads gain nothing on such work (many small numpy calls per job, e.g. refine's per-segment
searches; or pycolmap's Ceres solve, which holds the GIL throughout), so it goes to a child forked
from this process: the child starts in ~50 ms with every module imported (spawn would re-import
numpy and pycolmap, ~0.6 s) and exits without this process's atexit handlers. It runs the same
code on the same inputs, so the results are the same bytes.

- ``run_forked(fn, *args)``: one call in a child (arguments and result pickled), leaving this
  process free for other threads (the runner's prefetches, ``toolkit.overlap``).
- ``map_chunks_forked(fn, jobs)``: independent jobs split between this process and children,
  which inherit the jobs (nothing pickled on the way in) and send back results in job order.

With a thread budget of one (batch workers) or where this process may not fork (``can_fork``),
everything runs here.
"""

from __future__ import annotations

import multiprocessing
import sys
import threading
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence, TypeVar

import numpy as np

from toolkit.threads import thread_budget

T = TypeVar("T")
R = TypeVar("R")

# (fn, chunks) of the call in progress: forked children inherit it, so only an index crosses over
_JOB: tuple[Callable, list] | None = None
_BUSY = threading.Lock()


def _run_chunk(k: int) -> list:
    fn, chunks = _JOB  # type: ignore[misc]
    return fn(chunks[k])


def can_fork() -> bool:
    """Whether this process may fork worker children: on Linux (macOS system libraries, e.g. the
    Accelerate BLAS, may abort in a child forked from a threaded process) and not in a daemonic
    process (multiprocessing forbids children there, e.g. in a dask worker)."""
    return sys.platform.startswith("linux") and not multiprocessing.current_process().daemon


@contextmanager
def _forked_pool(n: int) -> Iterator[ProcessPoolExecutor]:
    """``n`` forked worker processes; a worker that dies (e.g. out of memory) raises RuntimeError."""
    try:
        with ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("fork")) as pool:
            yield pool
    except BrokenProcessPool as exc:
        raise RuntimeError(f"a forked child process died ({exc})") from exc


def forks() -> bool:
    """Whether ``run_forked`` runs in a child here (a second thread, and ``can_fork``)."""
    return thread_budget() >= 2 and can_fork()


def run_forked(fn: Callable[..., R], *args: Any) -> R:
    """``fn(*args)``, in a forked child process when ``forks()``. ``fn`` must be a module-level
    function; its arguments and result are pickled. An exception raised by ``fn`` is raised here."""
    if not forks():
        return fn(*args)
    with _forked_pool(1) as pool:
        return pool.submit(fn, *args).result()


def map_chunks_forked(fn: Callable[[list[T]], list[R]], jobs: Sequence[T], min_jobs: int = 32) -> list[R]:
    """``fn(jobs)``, where ``fn`` maps a list of jobs to a list of results (one each, in order),
    with the jobs split in contiguous chunks over the thread budget: the first chunks in forked
    children, the last one here meanwhile. ``fn`` must only read the state it shares with this
    process: what a child changes stays in the child."""
    global _JOB
    jobs = list(jobs)
    n = min(thread_budget(), len(jobs) // max(1, min_jobs // 2))
    # one forked map at a time (its jobs live in a module global); a second one, from another thread
    # or from inside fn, runs here
    if n < 2 or len(jobs) < min_jobs or not can_fork() or not _BUSY.acquire(blocking=False):
        return fn(jobs)
    # A child ran its share ~2x slower than this process (refine's searches on campus, equal halves:
    # 0.61 s vs 0.32 s): it first copies every page it writes to. So this process takes a double share.
    weights = np.array([1.0] * (n - 1) + [2.0])
    bounds = np.concatenate([[0], np.cumsum(weights) / weights.sum() * len(jobs)]).round().astype(int)
    chunks = [jobs[a:b] for a, b in zip(bounds[:-1], bounds[1:])]
    _JOB = (fn, chunks)
    try:
        with _forked_pool(n - 1) as pool:
            futures = [pool.submit(_run_chunk, k) for k in range(n - 1)]
            last = fn(chunks[-1])
            done = [f.result() for f in futures]
    finally:
        _JOB = None
        _BUSY.release()
    return [r for part in [*done, last] for r in part]
