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
    def between(cls, before: SparseModel, R_after: np.ndarray, t_after: np.ndarray,
                scale: np.ndarray | None = None) -> CameraMaps:
        """The maps taking what camera c saw in ``before`` to the same direction from (R_after, t_after),
        at ``scale[c]`` (C,) times the depth (None: 1): p ↦ R_afterᵀ (s (R p + t) − t_after)."""
        s = np.ones(len(R_after)) if scale is None else np.asarray(scale, np.float64)
        A = s[:, None, None] * np.einsum("cba,cbd->cad", R_after, before.R)
        centres = -np.einsum("cba,cb->ca", R_after, t_after)
        origin = centres.mean(axis=0) if len(centres) else np.zeros(3)
        b = np.einsum("cba,cb->ca", R_after, s[:, None] * np.asarray(before.t, np.float64) - t_after) - origin
        return cls(A, b, origin)

    def at(self, camera: np.ndarray) -> PointMaps:
        return PointMaps(np.asarray(camera, np.int64), self.A, self.b, self.origin)
