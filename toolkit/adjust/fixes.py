"""GPS fixes in the bundle adjustment's camera-position prior (``adjust.constrained_ba`` ``gps_prior``).

Each camera's prior is its warped centre with variance v (1/λ plus the warp's uncertainty there,
per axis). A camera with a fix of σ (scene x, y) gets the product of the two normal densities in
x and y: centre (x/v + g/σ²) / (1/v + 1/σ²), variance 1 / (1/v + 1/σ²); its height keeps the
warp's. A camera the registration placed well (v ≈ 1/λ = 0.05 m²) barely moves towards a 5 m
fix (weight 0.2 %), while one the blend or the bridge placed loosely (v of metres²) is held by the
fixes around it, which the reprojections tie together. A fix without σ counts as 10 m
(``toolkit.io.gps.DEFAULT_SIGMA_M``). See docs/remake.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.capture import StreetCapture
from toolkit.errors import CrossviewError
from toolkit.types import SparseModel

@dataclass(frozen=True)
class CameraFixes:
    """camera: (F,) index of the fixed camera in the model; xy: (F,2) scene x, y; sigma_m: (F,)."""

    camera: np.ndarray
    xy: np.ndarray
    sigma_m: np.ndarray


def camera_fixes(capture: StreetCapture, model: SparseModel) -> CameraFixes | None:
    """The fixes of street/gps.csv that name cameras of ``model``, in the scene CRS (None: none)."""
    from toolkit.io.gps import match_images

    if capture.gps_path is None:
        return None
    try:
        gps = capture.gps
    except CrossviewError:
        return None
    image = match_images(list(gps.names), model.image_names)
    hit = image >= 0
    if not hit.any():
        return None
    return CameraFixes(image[hit].astype(np.int64), gps.scene_xy(capture.scene.crs)[hit],
                       gps.sigma_or_default()[hit].astype(np.float64))


def fuse_fixes(C_prior: np.ndarray, var_m2: np.ndarray, fixes: CameraFixes) -> tuple[np.ndarray, np.ndarray]:
    """(C,3) prior centres and (C,3) per-axis variances with each fix fused into its camera's x, y."""
    C = np.array(C_prior, dtype=np.float64)
    var = np.array(np.broadcast_to(np.asarray(var_m2, np.float64).reshape(len(C), -1), C.shape))
    k, w_fix = fixes.camera, 1.0 / fixes.sigma_m[:, None] ** 2
    w_cam = 1.0 / var[k, :2]
    C[k, :2] = (w_cam * C[k, :2] + w_fix * fixes.xy) / (w_cam + w_fix)
    var[k, :2] = 1.0 / (w_cam + w_fix)
    return C, var
