"""``timed``: the generator's step timer (wall and CPU seconds to the ``toolkit.synth`` log)."""

from __future__ import annotations

import contextlib
import logging
import time

log = logging.getLogger("toolkit.synth")


@contextlib.contextmanager
def timed(what: str):
    t0, c0 = time.perf_counter(), time.process_time()
    yield
    log.info("%-28s %6.2f s (cpu %.2f s)", what, time.perf_counter() - t0, time.process_time() - c0)
