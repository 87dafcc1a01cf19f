"""The street stage's output: analysis results carried back to every input point, debug views."""

from __future__ import annotations

from typing import Any

import numpy as np

from toolkit.observe import DebugLines, DebugPoints
from toolkit.street.associate import Association
from toolkit.street.outline import BoundaryConfig, boundary_points, diameters
from toolkit.street.segments import FacadeSegments
from toolkit.types import StreetSegments

DEBUG_POINTS = 200_000


def to_input(values: np.ndarray, inverse: np.ndarray, finite: np.ndarray | None, fill: float) -> np.ndarray:
    """Analysis values → one row per input point (``fill`` on non-finite rows; ``finite`` None: none)."""
    if finite is None or finite.all():
        return values[inverse]
    out = np.full((len(finite),) + values.shape[1:], fill, dtype=values.dtype)
    out[finite] = values[inverse]
    return out


def centroids(xy: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """(n,2) mean of each label's points (labels 0..n-1)."""
    counts = np.maximum(np.bincount(labels, minlength=n), 1)
    return np.stack([np.bincount(labels, weights=xy[:, i], minlength=n) for i in range(2)],
                    axis=1).reshape(n, 2) / counts[:, None]


def street_segments(origin: np.ndarray, up_rotation: np.ndarray, inverse: np.ndarray, finite: np.ndarray | None,
                    segments: FacadeSegments, association: Association, normals: np.ndarray | None,
                    boundary: BoundaryConfig) -> StreetSegments:
    """``StreetSegments`` in input order (``inverse``: analysis index of each finite input point;
    ``normals``: (M,3) in the input frame, or None)."""
    xy, lab, n = segments.xy, segments.labels, segments.count
    return StreetSegments(
        origin=origin, up_rotation=up_rotation, point_labels=to_input(association.labels, inverse, finite, -2),
        carrier=to_input(association.carrier, inverse, finite, -1), ids=np.arange(n, dtype=np.int64),
        boundary_xy=boundary_points(xy, lab, n, **boundary.model_dump()), centroids=centroids(xy, lab, n),
        extent_m=diameters(xy, lab, n), ground_z=association.ground_z, ground_normal=association.ground_normal,
        normals=None if normals is None else to_input(normals, inverse, finite, np.nan))


def debug_views(obs: Any, points: np.ndarray, rotation: np.ndarray, labels: np.ndarray, seed: int) -> None:
    """Levelled points, the vertical, façade points and segments (a sample) to ``obs.debug``."""
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(len(points), min(len(points), DEBUG_POINTS), replace=False))
    levelled = (points[pick] @ rotation.T).astype(np.float32)
    lab = labels[pick]
    obs.debug("raw", DebugPoints(levelled, radius_m=0.05))
    centre = levelled.mean(axis=0)
    obs.debug("vertical", DebugLines([np.stack([centre, centre + np.float32([0.0, 0.0, 20.0])])], radius_m=0.3))
    obs.debug("facade", DebugPoints(levelled[lab >= 0], radius_m=0.05))
    obs.debug("segments", DebugPoints(levelled[lab >= 0], class_ids=lab[lab >= 0], radius_m=0.05))
    # the 2D boundaries are logged from the StreetSegments output itself (street/boundaries)
