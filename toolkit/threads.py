"""How many threads a run may use: the CPUs this process may run on, capped by ``OMP_NUM_THREADS``.

``crossview batch`` runs one scene per dask worker process and dask starts its workers with
``OMP_NUM_THREADS=1`` (Open3D and BLAS honour it): a stage that spread its work over every core
there would fight the other workers' scenes for the same cores. So every threaded step of ours
(KD-tree query workers, thread pools, the runner's overlap of independent stages) asks here
instead of using ``workers=-1`` / ``os.cpu_count()``. Results never depend on the answer.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Callable, Iterable, Iterator, TypeVar

from threadpoolctl import threadpool_limits

T = TypeVar("T")
R = TypeVar("R")

_cap: ContextVar[int | None] = ContextVar("crossview_thread_cap", default=None)


@contextmanager
def thread_cap(n: int) -> Iterator[None]:
    """Within this block (this thread and code it calls, not threads it starts without copying
    the context), ``thread_budget()`` is at most ``n``: e.g. work run beside a step that keeps
    one core busy gets the rest."""
    token = _cap.set(max(1, n))
    try:
        yield
    finally:
        _cap.reset(token)


def thread_budget() -> int:
    """Threads this process should use (≥ 1)."""
    cap = _cap.get()
    if cap is not None:
        return min(cap, _process_budget())
    return _process_budget()


def _process_budget() -> int:
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        n = os.cpu_count() or 1
    cap = os.environ.get("OMP_NUM_THREADS", "").strip()
    if cap.isdigit() and int(cap) >= 1:
        n = min(n, int(cap))
    return max(n, 1)


def query_workers(n_queries: int, min_queries: int = 200_000) -> int:
    """cKDTree ``workers`` for ``n_queries`` points: threads only pay off for large queries."""
    return thread_budget() if n_queries >= min_queries else 1


def map_in_order(fn: Callable[[T], R], items: Iterable[T], workers: int | None = None) -> Iterator[R]:
    """``map(fn, items)`` in up to ``workers`` threads (default and cap: the thread budget), results
    in item order. With one thread it stays lazy; numpy, scipy and Open3D release the GIL in most
    heavy work, so threads overlap there."""
    items = list(items)
    n = min(thread_budget() if workers is None else workers, thread_budget(), len(items))
    if n <= 1:
        return map(fn, items)
    with ThreadPoolExecutor(n) as pool:
        return iter(list(pool.map(fn, items)))


def single_threaded_blas():
    """numpy's BLAS on one thread within this block (process-wide): the one limiter the runner and
    every stage that may run outside it use. Our BLAS calls are tall-skinny products ((N,3) @ (3,3))
    and vector-sized LSMR steps, where BLAS threads gain nothing and, on a loaded machine, lose much
    to synchronisation (measured: (3.5 M,3) @ (3,3) 6–7.5 s multi-threaded, 0.3 s on one thread)."""
    return threadpool_limits(1, user_api="blas")


@contextmanager
def openmp_threads(n: int) -> Iterator[None]:
    """At most ``n`` OpenMP threads within this block (a library that takes no ``workers``)."""
    with threadpool_limits(limits=n, user_api="openmp"):
        yield
