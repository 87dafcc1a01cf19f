"""The street cloud's frames: its finite points, a local origin, and the rotations that level it.

A voxel grid tilted against the vertical biases voxel-centroid normals towards its axes (0.3° at
0.4 m on the campus scene), so with voxels the grid is laid out in a frame levelled by a first,
coarser pass (``pre_levelling``); the analysis cloud is then levelled exactly (``levelling``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from toolkit.errors import StageError
from toolkit.street.normals import open3d_normals
from toolkit.street.order import prepare
from toolkit.street.vertical import VerticalConfig, find_vertical

COARSE_POINTS = 1_000_000  # first levelling (voxel mode): from about this many input points
ORIGIN_SAMPLE = 100_000  # the origin (median) and the collinearity test: from this many points


@dataclass(frozen=True)
class Levelling:
    """up: (3,) unit up in the analysis frame; rotation: (3,3) analysis frame → levelled (+z up)."""

    up: np.ndarray
    rotation: np.ndarray


def valid_points(points: np.ndarray, obs: Any, who: str) -> tuple[np.ndarray, np.ndarray | None]:
    """The finite rows of an (N,3) cloud and the (N,) mask of them (None: all finite); one-line errors
    otherwise."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise StageError(f"{who}: street cloud must be (N,3), got shape {pts.shape}")
    if len(pts) == 0:
        raise StageError(f"{who}: the street cloud has no points")
    if np.isfinite(pts.min()) and np.isfinite(pts.max()):  # two quick passes; the row test is 6x slower
        return pts, None
    finite = np.isfinite(pts).all(axis=1)
    n_ok = int(finite.sum())
    if n_ok == 0:
        raise StageError(f"{who}: every street cloud point is NaN or Inf")
    if n_ok < len(pts):
        obs.warn(f"{len(pts) - n_ok} street points with NaN/Inf coordinates ignored (label -2)")
        pts = pts[finite]
    return pts, finite


def local_origin(pts: np.ndarray, k_max: int, seed: int, who: str) -> np.ndarray:
    """(3,) median of a sample of the finite cloud ``pts``; errors when it is too small for ``k_max``
    neighbours or lies on a line."""
    if len(pts) <= k_max:
        raise StageError(f"{who}: only {len(pts)} finite street points, need more than knn={k_max}")
    rng = np.random.default_rng(seed)
    sample = pts[np.sort(rng.choice(len(pts), min(len(pts), ORIGIN_SAMPLE), replace=False))]
    s = np.linalg.svd(sample - sample.mean(axis=0), compute_uv=False)
    if s[0] == 0 or s[1] < 1e-6 * s[0]:
        raise StageError(f"{who}: all street points lie on a line or a point; nothing to segment")
    return np.median(sample, axis=0)


def pre_levelling(pts: np.ndarray, origin: np.ndarray, voxel_m: float, knn: int, vertical: VerticalConfig,
                  seed: int, who: str) -> np.ndarray:
    """(3,3) rotation levelling a coarse (``2 voxel_m``) copy of the cloud; identity without voxels."""
    if voxel_m <= 0:
        return np.eye(3)
    coarse = prepare(pts[::max(1, len(pts) // COARSE_POINTS)], origin, 2 * voxel_m, who)
    return rotation_to_z(find_vertical(coarse.points, open3d_normals(coarse.points, knn), vertical, seed, who).up)


def levelling(points: np.ndarray, normals: np.ndarray, pre: np.ndarray, vertical: VerticalConfig, seed: int,
              obs: Any, who: str) -> Levelling:
    """The vertical of the analysis cloud and the rotation to it; up/down from the input +z (``pre``
    the analysis frame's rotation from it) when no cell tells them apart."""
    found = find_vertical(points, normals, vertical, seed, who)
    up = found.up
    if found.cells == 0:  # nothing tells up from down: prefer the input +z
        up = up if (pre.T @ up)[2] >= 0 else -up
        obs.warn("no cell holds both ground and façade points: up/down sign taken from the input +z")
    return Levelling(up, rotation_to_z(up))


def rotation_to_z(up: np.ndarray) -> np.ndarray:
    """The smallest rotation R with R @ up = +z (Rodrigues)."""
    up = up / np.linalg.norm(up)
    v = np.cross(up, [0.0, 0.0, 1.0])
    c = float(up[2])
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)
