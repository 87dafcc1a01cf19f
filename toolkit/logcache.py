"""``replaying_cache``: an lru_cache whose hits log again what the first call logged.

A reader notes what it did to a file (a raster resampled onto the scene grid, a float32 cloud) on
the ``crossview.*`` loggers when it reads it. Cached, the second run in a process would read nothing
and note nothing; replaying the first call's records on every hit gives every run that loads a
file the same notes, so run.log and metrics.json do not depend on what ran before in the process.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import threading

LOGGER = "crossview"
_fresh = threading.local()


@contextlib.contextmanager
def listening(handler: logging.Handler):
    """``handler`` on the ``crossview`` logger, which passes INFO (the readers' notes) meanwhile."""
    logger = logging.getLogger(LOGGER)
    level = logger.level
    logger.addHandler(handler)
    if logger.getEffectiveLevel() > logging.INFO:
        logger.setLevel(logging.INFO)
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


class _Recorder(logging.Handler):
    """The records one thread logs on ``crossview.*``."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.thread = threading.get_ident()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread == self.thread:
            self.records.append(record)


def replaying_cache(maxsize: int):
    def wrap(fn):
        @functools.lru_cache(maxsize=maxsize)
        def first(*args):
            with listening(_Recorder()) as recorder:  # records notes even when nobody shows them
                value = fn(*args)
            _fresh.called = True
            return value, tuple(recorder.records)

        @functools.wraps(fn)
        def call(*args):
            _fresh.called = False
            value, records = first(*args)
            if not _fresh.called:  # a cache hit: the first call's records again
                for record in records:
                    again = logging.makeLogRecord({**record.__dict__, "thread": threading.get_ident()})
                    logging.getLogger(record.name).handle(again)
            return value

        call.cache_clear = first.cache_clear
        call.cache_info = first.cache_info
        return call

    return wrap
