"""Seconds per step of the street stage, reported through the observer, which also draws its bar."""

from __future__ import annotations

import time
from typing import Any

from toolkit.observe import DebugScalar

# percent of the stage's time each step (a lap) takes, measured on campus (3.5 M points, 20 s):
# the progress bar advances by these, so it moves about evenly in time
STEP_SHARES = {"order": 13, "normals": 32, "vertical": 2, "facade": 31, "growing": 10, "associate": 8, "output": 4}


class StepClock:
    """``lap(name)`` ends a step: its seconds go to ``obs.debug("timings/<name>")`` (when debug output
    is wanted) and the stage's progress bar advances by the step's ``STEP_SHARES``."""

    def __init__(self, obs: Any, desc: str) -> None:
        self.laps: dict[str, float] = {}
        self._obs = obs
        self._t = time.perf_counter()
        total = sum(STEP_SHARES.values())
        self._bar = iter(obs.progress(range(total), total=total, desc=desc))
        next(self._bar, None)  # the bar appears at 0 %

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = now - self._t
        self._t = now
        if self._obs.wants_debug:
            self._obs.debug(f"timings/{name}", DebugScalar(self.laps[name]))
        for _ in range(STEP_SHARES.get(name, 0)):
            next(self._bar, None)

    def close(self) -> None:
        """Ends the bar (also when the stage stops early, on an error)."""
        getattr(self._bar, "close", lambda: None)()

    def __str__(self) -> str:
        return ", ".join(f"{k} {v:.2f} s" for k, v in self.laps.items())
