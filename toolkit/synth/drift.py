"""Monocular-SfM-like trajectory drift and the arbitrary street frame.

Each camera k gets a similarity (rotation D_k, scale s_k, drifted centre c'_k). Rotation errors
accumulate as a random walk of small world-frame increments (heading about up, pitch about the
vehicle's lateral axis, roll about its forward axis), the scale as a trend (random sign unless
``scale_drift_signed``) plus a random walk, and the drifted trajectory integrates the drifted
steps: c'_{k+1} = c'_k + s_k D_k (c_{k+1} - c_k).
A point captured by camera k moves as x' = c'_k + s_k D_k (x - c_k); then the whole street frame
is rotated (any yaw, tilt ≤ max_tilt_deg), translated and scaled by ``street_scale`` (a monocular
model's unknown scale): x_street = k (G_R x' + G_t).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from toolkit.synth.config import SynthConfig


@dataclass
class Drift:
    true_centres: np.ndarray  # (C,3) scene CRS
    drift_centres: np.ndarray  # (C,3) c'_k, scene CRS before the global transform
    drift_rotation: np.ndarray  # (C,3,3) D_k
    drift_scale: np.ndarray  # (C,) s_k
    global_rotation: np.ndarray  # (3,3) G_R
    global_translation: np.ndarray  # (3,) G_t
    global_scale: float = 1.0  # k: the street frame's unknown scale (street_scale)

    def apply(self, points: np.ndarray, camera: np.ndarray) -> np.ndarray:
        """True scene-CRS points → street frame, each with the drift of its capturing camera."""
        d = points - self.true_centres[camera]
        moved = self.drift_centres[camera] + self.drift_scale[camera, None] * np.einsum(
            "nij,nj->ni", self.drift_rotation[camera], d
        )
        return self.global_scale * (moved @ self.global_rotation.T + self.global_translation)

    def undo(self, street: np.ndarray, camera: np.ndarray) -> np.ndarray:
        """Street-frame points → true scene-CRS points (the inverse of ``apply``)."""
        moved = (street / self.global_scale - self.global_translation) @ self.global_rotation
        d = np.einsum("nji,nj->ni", self.drift_rotation[camera], moved - self.drift_centres[camera])
        return self.true_centres[camera] + d / self.drift_scale[camera, None]

    def street_poses(self, R_c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """COLMAP world-to-camera poses (R (C,3,3), t (C,3)) of the drifted cameras in the street frame."""
        R_wc = np.transpose(R_c2w, (0, 2, 1))
        R = R_wc @ np.transpose(self.drift_rotation, (0, 2, 1)) @ self.global_rotation.T
        centres = self.global_scale * (self.drift_centres @ self.global_rotation.T + self.global_translation)
        return R, -np.einsum("cij,cj->ci", R, centres)

    def arrays(self) -> dict[str, np.ndarray]:
        return {
            k: getattr(self, k)
            for k in (
                "true_centres",
                "drift_centres",
                "drift_rotation",
                "drift_scale",
                "global_rotation",
                "global_translation",
                "global_scale",
            )
        }


def make_drift(
    centres: np.ndarray, R_c2w: np.ndarray, arclength: np.ndarray, cfg: SynthConfig, rng: np.random.Generator
) -> Drift:
    n = len(centres)
    ds = np.diff(arclength, prepend=arclength[0])
    walk = (
        np.sqrt(ds / 100.0)[:, None]
        * rng.normal(0, 1, (n, 3))
        * np.deg2rad([cfg.heading_walk_deg, cfg.pitch_walk_deg, cfg.roll_walk_deg])
    )
    fwd = R_c2w[:, :, 2].copy()
    fwd[:, 2] = 0
    fwd /= np.maximum(np.linalg.norm(fwd, axis=1, keepdims=True), 1e-12)
    lateral = np.column_stack([-fwd[:, 1], fwd[:, 0], np.zeros(n)])
    up = np.array([0.0, 0.0, 1.0])
    rotvec = walk[:, :1] * up + walk[:, 1:2] * lateral + walk[:, 2:3] * fwd
    steps = Rotation.from_rotvec(rotvec).as_matrix()
    D = np.empty((n, 3, 3))
    acc = np.eye(3)
    for k in range(n):
        acc = steps[k] @ acc
        D[k] = acc
    total = max(arclength[-1], 1e-9)
    sign = rng.choice([-1.0, 1.0])  # drawn either way: the other draws stay the same
    trend = cfg.scale_drift * (1.0 if cfg.scale_drift_signed else sign) * arclength / total
    scale = np.exp(trend + np.cumsum(rng.normal(0, 1, n) * cfg.scale_walk * np.sqrt(ds / 100.0)))
    scale /= scale[0]
    steps_xyz = np.diff(centres, axis=0)
    moved = scale[:-1, None] * np.einsum("nij,nj->ni", D[:-1], steps_xyz)
    drifted = centres[0] + np.concatenate([np.zeros((1, 3)), np.cumsum(moved, axis=0)])
    G_R, G_t = _global_transform(centres[0], cfg, rng)
    return Drift(centres, drifted, D, scale, G_R, G_t, float(cfg.street_scale))


def _global_transform(anchor: np.ndarray, cfg: SynthConfig, rng) -> tuple[np.ndarray, np.ndarray]:
    yaw = rng.uniform(0, 2 * np.pi)
    tilt = np.deg2rad(rng.uniform(0, cfg.max_tilt_deg))
    axis_angle = rng.uniform(0, 2 * np.pi)
    axis = np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0])
    G_R = Rotation.from_rotvec(axis * tilt).as_matrix() @ Rotation.from_euler("z", yaw).as_matrix()
    G_t = -G_R @ anchor + rng.normal(0, 1, 3) * cfg.global_offset_m
    return G_R, G_t
