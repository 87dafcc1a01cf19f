"""The street cloud re-made from the adjusted cameras (paper §3.4: "the dense cloud can be re-made").

A dense street point was triangulated from the images around one place of the route, so the
trajectory's drift moved it with the poses of those cameras. After the bundle adjustment, every
point therefore moves with the pose change of the camera that captured it instead of with the
blend of segment transforms: p ↦ R'ᵀ (R p + t − t') for the capture camera's input pose (R, t)
and adjusted pose (R', t') (docs/remake.md). The capture camera is the median observing image of
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


def capture_cameras(points: np.ndarray, model: SparseModel, max_gap_m: float = 10.0) -> np.ndarray:
    """(N,) index of the camera each point was captured from (the rule of the module doc)."""
    obs = np.asarray(model.observations)
    n_points3d = len(model.points3d)
    out = np.empty(len(points), np.int64)
    _, out[:] = cKDTree(model.centres).query(points, workers=query_workers(len(points)))
    if len(obs) == 0 or n_points3d == 0:
        return out
    point, image = obs[:, 1].astype(np.int64), obs[:, 0].astype(np.int64)
    order = np.lexsort((image, point))
    point, image = point[order], image[order]
    count = np.bincount(point, minlength=n_points3d)
    seen = np.flatnonzero(count > 0)
    median_image = image[np.searchsorted(point, seen) + (count[seen] - 1) // 2]
    dist, nn = cKDTree(np.asarray(model.points3d, np.float64)[seen]).query(
        points, distance_upper_bound=max_gap_m, workers=query_workers(len(points)))
    hit = np.isfinite(dist)
    out[hit] = median_image[nn[hit]]
    return out


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
    maps = CameraMaps.between(model, R_after, t_after)
    camera = capture_cameras(points, model, max_gap_m)
    warp = registration.warp
    if warp is not None:
        warp = warp.following(maps, camera)
    return replace(registration, points=maps.at(camera).apply(points), warp=warp)
