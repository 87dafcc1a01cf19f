"""Run numpy with single-threaded BLAS inside the refine / warp / adjust stages.

Their BLAS calls are tall-skinny products ((N,3) @ (3,3)) and vector-sized LSMR steps, where
OpenBLAS threads gain nothing and, on a loaded machine, lose a lot to synchronisation: measured
here under load, (3.5 M,3) @ (3,3) took 6–7.5 s multi-threaded and 0.3 s single-threaded, and a
dot of 60 k doubles 7.5 ms vs 40 µs. ``threadpoolctl`` (installed with scipy's stack) is optional.
"""

from __future__ import annotations

from contextlib import nullcontext


def single_threaded_blas():
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # only a speed-up
        return nullcontext()
    return threadpool_limits(1, user_api="blas")

