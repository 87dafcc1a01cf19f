"""adjust.none — keep the warped camera poses (a baseline for adjust.constrained_ba).

The model's 3D points are moved with the warp (each by the pose change of the cameras observing
it) and the reprojection RMS of the warped model is reported (before = after).
"""

from __future__ import annotations

from toolkit.adjust.model import point_errors_px, registered_poses, residuals, rms_px, warp_points3d
from toolkit.capture import StreetCapture
from toolkit.io.colmap import replace_poses
from toolkit.stage import Stage, StageParams
from toolkit.threads import single_threaded_blas
from toolkit.types import AdjustedCameras, Registration, Scene, SparseModel


class NoAdjust(Stage):
    """No bundle adjustment: the warped poses unchanged, with their reprojection RMS."""

    kind = "adjust"
    name = "none"

    class Params(StageParams):
        pass

    @classmethod
    def scene_needs(cls, params) -> tuple[str, ...]:
        return ("sparse",)

    def __call__(self, registration: Registration, scene: Scene, capture: StreetCapture, obs) -> AdjustedCameras:
        with single_threaded_blas():
            return self._run(registration, capture.require_sparse("adjust"), obs)

    def _run(self, registration: Registration, model: SparseModel, obs) -> AdjustedCameras:
        R, t = registered_poses(model, registration)
        X = warp_points3d(model, R, t)
        residual_px = residuals(model, R, t, X)
        rms = rms_px(residual_px)
        return AdjustedCameras(replace_poses(model, R, t, X, point_errors_px(model, residual_px)), rms, rms, 0)
