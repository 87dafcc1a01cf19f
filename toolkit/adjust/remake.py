"""The street cloud re-made from the adjusted cameras (paper §3.4: "the dense cloud can be re-made").

A dense street point was triangulated from the images around one place of the route, so the
trajectory's drift moved it with the poses of those cameras. After the bundle adjustment, every
point therefore moves with the pose change of the camera that captured it instead of with the
blend of segment transforms: p ↦ R'ᵀ (s (R p + t) − t') for the capture camera's input pose
(R, t), adjusted pose (R', t') and the warp's scale s there (docs/remake.md). The capture camera is the median observing image of
the nearest sparse point (it knows which pass of the route saw the place), else the camera whose
centre is nearest.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from toolkit.errors import StageError
from toolkit.threads import query_workers
from toolkit.types import Registration, SparseModel
from toolkit.warp.cameras import CameraMaps
from toolkit.warp.passes import median_observers


def capture_cameras(points: np.ndarray, model: SparseModel, max_gap_m: float = 10.0) -> np.ndarray:
    """(N,) index of the camera each point was captured from (the rule of the module doc)."""
    out = np.full(len(points), -1, np.int64)
    observer = median_observers(model)
    seen = np.flatnonzero(observer >= 0)
    if len(seen):
        dist, nn = cKDTree(np.asarray(model.points3d, np.float64)[seen]).query(
            points, distance_upper_bound=max_gap_m, workers=query_workers(len(points)))
        hit = np.isfinite(dist)
        out[hit] = observer[seen][nn[hit]]
    miss = np.flatnonzero(out < 0)
    if len(miss):
        _, out[miss] = cKDTree(model.centres).query(points[miss], workers=query_workers(len(miss)))
    return out


def camera_scales(registration: Registration, points: np.ndarray, camera: np.ndarray, n_cameras: int) -> np.ndarray:
    """(C,) the warp's scale (cube root of its maps' determinant) over each camera's points: the bundle
    adjustment keeps the frame's scale error, which the segment transforms have fitted; a camera
    without points takes that of the nearest camera (by index) with points; 1 without a warp."""
    if registration.warp is None or len(points) == 0:
        return np.ones(n_cameras)
    maps = replace(registration.warp, street_scale=1.0).maps(points, registration.point_segment)
    row_scale = np.cbrt(np.linalg.det(maps.A))[maps.rows]
    count = np.bincount(camera, minlength=n_cameras)
    mean = np.bincount(camera, weights=row_scale, minlength=n_cameras) / np.maximum(count, 1)
    has = np.flatnonzero(count > 0)
    return np.interp(np.arange(n_cameras), has, mean[has]) if len(has) else np.ones(n_cameras)


def remake_registration(registration: Registration, points: np.ndarray, model: SparseModel,
                        R_after: np.ndarray, t_after: np.ndarray, max_gap_m: float = 10.0) -> Registration:
    """``registration`` with every street point moved by its capture camera's pose change; its stored
    warp follows the cameras too (``crossview apply`` gives the same points). The poses stay the
    warp's (the adjusted ones are ``AdjustedCameras.model``).

    ``points``: the input street cloud in metres; ``model``: the input COLMAP model in metres, in
    the image order of ``R_after``/``t_after`` and of the registration."""
    if len(points) != len(registration.points):
        raise StageError(f"adjust: the street cloud has {len(points)} points, the registration "
                         f"{len(registration.points)}: cannot re-make the points from the cameras")
    camera = capture_cameras(points, model, max_gap_m)
    maps = CameraMaps.between(model, R_after, t_after, camera_scales(registration, points, camera, len(model.R)))
    warp = registration.warp
    if warp is not None:
        warp = warp.following(maps, camera)
    return replace(registration, points=maps.at(camera).apply(points), warp=warp)
