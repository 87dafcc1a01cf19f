"""Small rigid-transform helpers shared by the refine and warp stages (float64 throughout).

Eq. 5 of the paper composes a segment transform from the 2D registration (R2d, t2d) and the 3D
ground step (R_Z, t_z): ``T = [[R2d, 0], [0, 1]] · R_Z`` with ``t = [t2d | t_z]``. Here R_Z turns
about a chosen centre ``c`` (the segment's ground centre) instead of the levelled origin, so that a
small tilt correction does not slide a segment that lies far from the origin; with ``c = 0`` the
result is exactly Eq. 5.
"""

from __future__ import annotations

import numpy as np


def rot2(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def rigid2d(theta: float, t: np.ndarray) -> np.ndarray:
    """(3,3) homogeneous 2D rigid transform."""
    m = np.eye(3)
    m[:2, :2] = rot2(theta)
    m[:2, 2] = t
    return m


def theta_of(T2d: np.ndarray) -> float:
    """Rotation angle of a (3,3) 2D transform (its rotation part projected to SO(2))."""
    return float(np.arctan2(T2d[1, 0] - T2d[0, 1], T2d[0, 0] + T2d[1, 1]))


def apply2d(T2d: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return xy @ T2d[:2, :2].T + T2d[:2, 2]


def apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(4,4) transform applied to (N,3) points."""
    return p @ T[:3, :3].T + T[:3, 3]


def apply_each(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N,4,4) transforms, each applied to its own point of (N,3)."""
    return np.einsum("nab,nb->na", T[:, :3, :3], p) + T[:, :3, 3]


def scale_of(M: np.ndarray) -> np.ndarray:
    """(...) scale of (...,3,3) similarity linear parts s·R: the cube root of the determinant."""
    return np.cbrt(np.linalg.det(M))


def rotation_part(M: np.ndarray) -> np.ndarray:
    """(...,3,3) similarity linear parts s·R → R."""
    s = scale_of(M)
    return M / np.where(s != 0, s, 1.0)[..., None, None]


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector a onto unit vector b (Rodrigues)."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    # np.cross's products and differences, without its overhead (~40 µs a call)
    v = np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])
    s, c = np.linalg.norm(v), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
    ang = np.arctan2(s, c)
    return np.eye(3) + np.sin(ang) * k + (1 - np.cos(ang)) * (k @ k)


def compose_eq5(T2d: np.ndarray, R_z: np.ndarray, t_z: float, centre: np.ndarray | None = None) -> np.ndarray:
    """Eq. 5: levelled street frame → scene, ``p ↦ A·(R_Z (p − c) + c) + [t2d, t_z]``, A = R2d ⊕ 1."""
    c = np.zeros(3) if centre is None else np.asarray(centre, float)
    A = np.eye(4)
    A[:2, :2] = T2d[:2, :2]
    A[:2, 3] = T2d[:2, 2]
    A[2, 3] = t_z
    B = np.eye(4)
    B[:3, :3] = R_z
    B[:3, 3] = c - R_z @ c
    return A @ B


def tilt_deg(R: np.ndarray) -> float:
    """Angle between R·z and z, degrees."""
    return float(np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0))))

