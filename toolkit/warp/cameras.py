"""Camera pose changes as point maps: what a street point moves by when it follows the camera that
captured it (``toolkit.adjust.remake``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.types import SparseModel
from toolkit.warp.blend import PointMaps


@dataclass(frozen=True)
class CameraMaps:
    """Each camera's pose change as an affine map of the input street frame (metres) into the scene
    CRS: A (C,3,3), b (C,3) relative to ``origin`` (3,), the mean camera position (keeps b small)."""

    A: np.ndarray
    b: np.ndarray
    origin: np.ndarray

    @classmethod
    def between(cls, before: SparseModel, R_after: np.ndarray, t_after: np.ndarray) -> CameraMaps:
        """The maps taking what camera c saw in ``before`` to where it sees it with (R_after, t_after)."""
        A = np.einsum("cba,cbd->cad", R_after, before.R)
        centres = -np.einsum("cba,cb->ca", R_after, t_after)
        origin = centres.mean(axis=0) if len(centres) else np.zeros(3)
        b = np.einsum("cba,cb->ca", R_after, np.asarray(before.t, np.float64) - t_after) - origin
        return cls(A, b, origin)

    def at(self, camera: np.ndarray) -> PointMaps:
        return PointMaps(np.asarray(camera, np.int64), self.A, self.b, self.origin)
