"""Import Open3D without its plotly/dash web viewer.

``import open3d`` runs ``open3d.visualization.draw_plotly``, which imports dash, plotly and
IPython: 0.45 s of the 0.85 s the import takes here (measured with ``python -X importtime``), on
the critical path of every run, for a notebook viewer no stage uses. ``open3d()`` puts a stand-in
for that one module in place before the import; its three functions import the real module when
first called, so ``open3d.visualization.draw_plotly(...)`` still works.
"""

from __future__ import annotations

import importlib
import sys
from types import ModuleType
from typing import Any

PLOTLY_MODULE = "open3d.visualization.draw_plotly"
PLOTLY_FUNCTIONS = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def _real_plotly() -> ModuleType:
    """Replace the stand-in with the real module (and the package's names bound to the stand-in's)."""
    if isinstance(sys.modules.get(PLOTLY_MODULE), _PlotlyStandIn):
        del sys.modules[PLOTLY_MODULE]
    real = importlib.import_module(PLOTLY_MODULE)
    package = sys.modules.get("open3d.visualization")
    if package is not None:
        for name in PLOTLY_FUNCTIONS:
            setattr(package, name, getattr(real, name))
    return real


class _PlotlyStandIn(ModuleType):
    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):  # the import system probes e.g. __path__: not a use of the module
            raise AttributeError(name)
        return getattr(_real_plotly(), name)


def _deferred(name: str):
    def call(*args: Any, **kwargs: Any) -> Any:
        return getattr(_real_plotly(), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    return call


def open3d() -> ModuleType:
    """The ``open3d`` module, imported without dash/plotly if it is not imported yet."""
    if "open3d" in sys.modules:
        return sys.modules["open3d"]
    if PLOTLY_MODULE not in sys.modules:
        stand_in = _PlotlyStandIn(PLOTLY_MODULE)
        for name in PLOTLY_FUNCTIONS:
            setattr(stand_in, name, _deferred(name))
        sys.modules[PLOTLY_MODULE] = stand_in
    try:
        return importlib.import_module("open3d")
    except BaseException:
        if isinstance(sys.modules.get(PLOTLY_MODULE), _PlotlyStandIn):
            del sys.modules[PLOTLY_MODULE]
        raise
