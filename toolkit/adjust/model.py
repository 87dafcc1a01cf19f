"""The COLMAP model in the scene CRS: warped poses, warped 3D points, reprojection residuals.

Reprojection RMS convention: ``sqrt(mean(r²))`` over all image coordinates (u and v residuals
pooled), i.e. comparable to the per-axis standard deviation of the pixel noise.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from toolkit.errors import StageError
from toolkit.types import Camera, Registration, SparseModel

NUMPY_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def registered_poses(model: SparseModel, reg: Registration) -> tuple[np.ndarray, np.ndarray]:
    """(C,3,3), (C,3) warped world-to-camera poses in the model's image order."""
    where = {n: i for i, n in enumerate(reg.image_names)}
    missing = [n for n in model.image_names if n not in where]
    if missing:
        raise StageError(f"adjust: registration has no pose for image {missing[0]!r} "
                         f"({len(missing)} of {len(model.image_names)} images missing)")
    idx = np.array([where[n] for n in model.image_names], dtype=np.int64)
    return np.asarray(reg.R, np.float64)[idx], np.asarray(reg.t, np.float64)[idx]


def registered_spread(model: SparseModel, reg: Registration) -> np.ndarray | None:
    """(C,) the warp's transform spread at each camera (``Registration.camera_spread_m``) in the
    model's image order, or None when the registration has none."""
    if reg.camera_spread_m is None or len(reg.camera_spread_m) != len(reg.image_names):
        return None
    where = {n: i for i, n in enumerate(reg.image_names)}
    return np.asarray(reg.camera_spread_m, np.float64)[[where[n] for n in model.image_names]]


def warp_points3d(model: SparseModel, R_new: np.ndarray, t_new: np.ndarray) -> np.ndarray:
    """Move each 3D point with the pose change of the cameras observing it (mean over its track).

    A camera's pose change is the rigid transform ``X ↦ R_newᵀ (R X + t − t_new)``: it keeps the
    point where that camera saw it. Points nobody observes follow the nearest camera.
    """
    X = np.asarray(model.points3d, np.float64)
    out = np.zeros_like(X)
    if len(X) == 0:
        return out
    ob = model.observations
    img, pt = ob[:, 0].astype(np.int64), ob[:, 1].astype(np.int64)
    xc = np.einsum("kab,kb->ka", model.R[img], X[pt]) + model.t[img]
    moved = np.einsum("kba,kb->ka", R_new[img], xc - t_new[img])
    counts = np.bincount(pt, minlength=len(X)).astype(np.float64)
    for a in range(3):
        out[:, a] = np.bincount(pt, weights=moved[:, a], minlength=len(X))
    seen = counts > 0
    out[seen] /= counts[seen, None]
    if (~seen).any() and len(model.R):
        _, cam = cKDTree(model.centres).query(X[~seen])
        xcu = np.einsum("kab,kb->ka", model.R[cam], X[~seen]) + model.t[cam]
        out[~seen] = np.einsum("kba,kb->ka", R_new[cam], xcu - t_new[cam])
    return out


def project(cam: Camera, xc: np.ndarray) -> np.ndarray:
    """Camera-frame points (n,3) → pixels (n,2) for ``cam``'s model."""
    p = np.asarray(cam.params, np.float64)
    if cam.model not in NUMPY_MODELS:
        import pycolmap

        pc = pycolmap.Camera(model=cam.model, width=cam.width, height=cam.height, params=p)
        return np.asarray(pc.img_from_cam(np.ascontiguousarray(xc), check_cheirality=False))
    x, y = xc[:, 0] / xc[:, 2], xc[:, 1] / xc[:, 2]
    if cam.model == "SIMPLE_PINHOLE":
        return np.column_stack([p[0] * x + p[1], p[0] * y + p[2]])
    if cam.model == "PINHOLE":
        return np.column_stack([p[0] * x + p[2], p[1] * y + p[3]])
    r2 = x * x + y * y
    if cam.model == "SIMPLE_RADIAL":
        d = 1 + p[3] * r2
        return np.column_stack([p[0] * x * d + p[1], p[0] * y * d + p[2]])
    if cam.model == "RADIAL":
        d = 1 + p[3] * r2 + p[4] * r2 * r2
        return np.column_stack([p[0] * x * d + p[1], p[0] * y * d + p[2]])
    k1, k2, p1, p2 = p[4:8]
    d = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * d + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * d + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([p[0] * xd + p[2], p[1] * yd + p[3]])


def residuals(model: SparseModel, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(K,2) observed − projected pixels for every observation of ``model``."""
    ob = model.observations
    img, pt = ob[:, 0].astype(np.int64), ob[:, 1].astype(np.int64)
    xc = np.einsum("kab,kb->ka", R[img], X[pt]) + t[img]
    uv = np.empty((len(ob), 2))
    cam_of_obs = model.camera_ids[img]
    for cid in np.unique(cam_of_obs):
        sel = cam_of_obs == cid
        uv[sel] = project(model.cameras[int(cid)], xc[sel])
    return ob[:, 2:4] - uv


def point_errors_px(model: SparseModel, res: np.ndarray) -> np.ndarray:
    """(P,) mean reprojection error (px) of each 3D point over its observations, as COLMAP's ERROR
    column holds it, from ``res`` = ``residuals(model, ...)``; -1 (COLMAP's "no error") when no image
    observes the point."""
    pt = model.observations[:, 1].astype(np.int64)
    n_points = len(model.points3d)
    count = np.bincount(pt, minlength=n_points)
    total = np.bincount(pt, weights=np.linalg.norm(res, axis=1), minlength=n_points)
    return np.where(count > 0, total / np.maximum(count, 1), -1.0)


def rms_px(res: np.ndarray) -> float:
    return float(np.sqrt(np.mean(res ** 2))) if len(res) else 0.0


def place_unadjusted(model, res) -> np.ndarray:
    """Points seen by fewer than two cameras are not adjusted: put them where their camera sees them."""
    X = res.X.copy()
    single = np.bincount(model.observations[:, 1].astype(np.int64), minlength=len(X)) < 2
    if single.any():
        X[single] = warp_points3d(model, res.R, res.t)[single]
    return X


def bad_observations(model, R, t, X, max_px: float) -> np.ndarray:
    """Observations reprojecting farther than ``max_px`` or behind their camera."""
    ob = model.observations
    img, pt = ob[:, 0].astype(np.int64), ob[:, 1].astype(np.int64)
    depth = np.einsum("kb,kb->k", R[img, 2], X[pt]) + t[img, 2]
    return (np.linalg.norm(residuals(model, R, t, X), axis=1) > max_px) | (depth <= 0)
