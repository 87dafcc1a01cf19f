"""The street side of a scene as one typed input: the street cloud, the COLMAP model, the GPS fixes.

The runner makes one ``StreetCapture`` per run, once the street scale is resolved (``build``), and
passes it to the stages that declare it (``KIND_INPUTS``: ``capture``); helpers take it or arrays
from it, never a scene file of the street side.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from toolkit.types import Scene, SparseModel, StreetScale

if TYPE_CHECKING:
    from toolkit.io.attributes import CloudSource
    from toolkit.io.gps import GpsFixes

WHO = "the street capture"


@dataclass(frozen=True)
class StreetCapture:
    """The street capture of ``scene`` (its street scale resolved), in metres.

    points: (N,3) float64 street cloud divided by the street scale, read-only, row i = input point i;
        with ``step`` > 1 the analysis cloud instead, row i = input point ``rows[i]``.
    sparse: the COLMAP model, camera centres and points divided by the street scale; None without
        street/sparse. gps: the fixes of street/gps.csv, None without one.
    attributes(): the cloud as written (street frame units) with every attribute, in input order.

    Loading is lazy and nothing is kept here: each property reads through the scene's cached readers
    (``toolkit.scene``), so a stage that never asks reads nothing, the stages of a run share one copy,
    and a reader that streams the cloud can later replace them without changing this interface. The
    ``*_path`` properties tell what the scene has without reading it.
    """

    scene: Scene
    step: int = 1               # the run analyses rows 0, step, 2·step, … (toolkit.stream; 1: every row)
    chunk_points: int = 2_000_000  # rows per chunk of a streamed read

    @property
    def cloud_points(self) -> int:
        """Points of the street cloud (its header)."""
        from toolkit.io.attributes import open_cloud

        return open_cloud(self.cloud_path).count

    @property
    def rows(self) -> np.ndarray | None:
        """The input rows of ``points`` (None: every row, in order)."""
        if self.step == 1:
            return None
        return np.arange(0, self.cloud_points, self.step, dtype=np.int64)

    @property
    def scale(self) -> StreetScale:
        return self.scene.street_scale

    @property
    def cloud_path(self) -> Path | None:
        return self.scene.files.street_cloud

    @property
    def sparse_path(self) -> Path | None:
        return self.scene.files.sparse

    @property
    def gps_path(self) -> Path | None:
        return self.scene.files.gps

    @property
    def points(self) -> np.ndarray:
        from toolkit.scene import load_points

        if self.step == 1:
            return load_points(self.scene, "street_cloud", WHO)
        from toolkit.stream import analysis_points

        # a test scene's truth rows are read in the same pass: its evaluation then does not read the cloud again
        truth_rows = self.scene.files.truth_street_rows if self.scene.has("truth_street_rows") else None
        return analysis_points(self.cloud_path, self.step, self.chunk_points, self.scale.value, truth_rows)

    @property
    def sparse(self) -> SparseModel | None:
        from toolkit.scene import load_sparse

        return load_sparse(self.scene, WHO) if self.sparse_path is not None else None

    def require_sparse(self, who: str) -> SparseModel:
        """``sparse``, or a SceneError saying that ``who`` needs street/sparse."""
        from toolkit.scene import load_sparse

        return load_sparse(self.scene, who)

    @property
    def gps(self) -> GpsFixes | None:
        from toolkit.io.gps import read_gps_csv

        return read_gps_csv(self.gps_path) if self.gps_path is not None else None

    def attributes(self) -> CloudSource:
        """The street cloud's header and chunked reader (``toolkit.io.attributes``): nothing of the
        points is read until its chunks are."""
        from toolkit.io.attributes import open_cloud
        from toolkit.scene import need

        return open_cloud(need(self.scene, "street_cloud", WHO))
