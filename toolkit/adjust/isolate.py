"""Run a solve in a forked child process, so that it does not hold this process's GIL.

pycolmap keeps the GIL for the whole Ceres solve (measured: a Python thread beside it got 351
loop iterations in 2.2 s instead of ~150 000), so no other thread of the run can work meanwhile,
not even numpy or KD-tree code that would release the GIL. In a child process the solve leaves
this process free: the runner computes the evaluation's point metrics beside it
(``toolkit.overlap``). The child runs the same code on the same inputs, single-threaded, so the
result is the same bytes. With a thread budget of one (batch workers) or where this process may not fork
(``toolkit.forked.can_fork``), the solve runs here.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, TypeVar

from toolkit.forked import can_fork
from toolkit.threads import thread_budget

R = TypeVar("R")


def isolates() -> bool:
    """Whether ``run_isolated`` runs in a child process here (a second thread, and ``can_fork``)."""
    return thread_budget() >= 2 and can_fork()


def run_isolated(fn: Callable[..., R], *args: Any) -> R:
    """``fn(*args)``, in a forked child process when the thread budget has a second thread.

    ``fn`` must be a module-level function; its arguments and result are pickled. An exception
    raised by ``fn`` is raised here; a child that dies (e.g. out of memory) gets ``RuntimeError``.
    """
    if not isolates():
        return fn(*args)
    # fork, not spawn: the child starts in ~50 ms with every module already imported (spawn
    # would re-import numpy and pycolmap, ~0.6 s). It only runs ``fn`` and exits without running
    # this process's atexit handlers.
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork")) as pool:
        try:
            return pool.submit(fn, *args).result()
        except BrokenProcessPool as exc:
            raise RuntimeError(f"{getattr(fn, '__name__', fn)}: the child process died ({exc})") from exc
