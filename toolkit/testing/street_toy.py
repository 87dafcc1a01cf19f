"""A small street cloud with truth, built from planes and boxes, for tests and benchmarks.

Not the scene generator (``crossview synth``): a cross of two streets lined with box buildings
(street-facing façades plus the first metres of side walls), road ground on a gentle slope, parked
cars, poles, tree crowns, Gaussian noise and uniform outliers, then an arbitrary rigid motion
(any yaw, a tilt, a large translation) like an SfM frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ToyStreet:
    """points: (N,3) in the moved frame; labels: (N,) building id, -1 ground, -2 clutter;
    up: (3,) true up in the moved frame; rotation, translation: moved = R @ true + t."""

    points: np.ndarray
    labels: np.ndarray
    up: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray


def _rect(rng, density, origin, u, v, lu, lv):
    n = rng.poisson(density * lu * lv)
    a, b = rng.uniform(0, lu, n), rng.uniform(0, lv, n)
    return origin + a[:, None] * u + b[:, None] * v


def random_rotation(rng: np.random.Generator, max_tilt_deg: float) -> np.ndarray:
    """Any yaw, then a tilt of up to ``max_tilt_deg`` about a random horizontal axis."""
    yaw = rng.uniform(0, 2 * np.pi)
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    tilt = np.radians(rng.uniform(0, max_tilt_deg))
    axis = np.array([*_unit2(rng.uniform(0, 2 * np.pi)), 0.0])
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rt = np.eye(3) + np.sin(tilt) * k + (1 - np.cos(tilt)) * k @ k
    return rt @ rz


def _unit2(a: float) -> np.ndarray:
    return np.array([np.cos(a), np.sin(a)])


def toy_street(seed: int = 0, density: float = 60.0, half_length_m: float = 60.0, noise_m: float = 0.02,
               outlier_share: float = 0.003, max_tilt_deg: float = 45.0, slope: float = 0.02,
               rotation: np.ndarray | None = None) -> ToyStreet:
    rng = np.random.default_rng(seed)
    parts, labels = [], []
    ex, ey, ez = np.eye(3)
    road = 9.0
    # ground: two crossing strips
    for u, v in ((ex, ey), (ey, ex)):
        g = _rect(rng, density, -half_length_m * u - road * v, u, v, 2 * half_length_m, 2 * road)
        parts.append(g)
        labels.append(np.full(len(g), -1))
    bid = 0
    for u, v in ((ex, ey), (ey, ex)):
        for side in (-1.0, 1.0):
            for start in (-half_length_m, road + 2.0):
                pos = start
                stop = start + half_length_m - road - 2.0
                while pos < stop - 6.0:
                    width = min(rng.uniform(8.0, 22.0), stop - pos)
                    height = rng.uniform(6.0, 18.0)
                    base = pos * u + side * road * v
                    f = _rect(rng, density, base, u, ez, width, height)
                    s1 = _rect(rng, density, base, side * v, ez, 3.0, height)
                    s2 = _rect(rng, density, base + width * u, side * v, ez, 3.0, height)
                    b = np.concatenate([f, s1, s2])
                    parts.append(b)
                    labels.append(np.full(len(b), bid))
                    bid += 1
                    pos += width + rng.uniform(1.0, 4.0)
    # clutter: cars along kerbs, poles, tree crowns
    clutter = []
    for _ in range(int(half_length_m / 4)):
        c = np.array([rng.uniform(-half_length_m, half_length_m), rng.choice([-6.5, 6.5]), 0.0])
        if rng.random() < 0.5:
            c = c[[1, 0, 2]]
        size = np.array([4.5, 1.8, 1.5]) if abs(c[1]) > 1 else np.array([1.8, 4.5, 1.5])
        lo = c - size * [0.5, 0.5, 0.0]
        for axis in range(3):
            for top in (0.0, 1.0):
                if axis == 2 and top == 0.0:
                    continue
                a, b = [i for i in range(3) if i != axis]
                o = lo.copy()
                o[axis] += top * size[axis]
                clutter.append(_rect(rng, density, o, np.eye(3)[a], np.eye(3)[b], size[a], size[b]))
    for _ in range(int(half_length_m / 6)):
        c = np.array([rng.uniform(-half_length_m, half_length_m), rng.choice([-8.0, 8.0]), 0.0])
        if rng.random() < 0.5:
            c = c[[1, 0, 2]]
        n = rng.poisson(density * 2 * np.pi * 0.1 * 5)
        ang, z = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 5, n)
        clutter.append(c + np.stack([0.1 * np.cos(ang), 0.1 * np.sin(ang), z], axis=1))
        if rng.random() < 0.5:
            n = rng.poisson(density * 4 * np.pi * 2.0**2)
            d = rng.normal(size=(n, 3))
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            clutter.append(c + [0, 0, 6.0] + d * rng.uniform(1.5, 2.0, (n, 1)))
    cl = np.concatenate(clutter)
    parts.append(cl)
    labels.append(np.full(len(cl), -2))
    pts = np.concatenate(parts)
    lab = np.concatenate(labels).astype(np.int32)
    pts[:, 2] += slope * pts[:, 0]  # terrain slope carries everything
    pts += rng.normal(0, noise_m, pts.shape)
    n_out = int(outlier_share * len(pts))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pts = np.concatenate([pts, rng.uniform(lo, hi, (n_out, 3))])
    lab = np.concatenate([lab, np.full(n_out, -2, dtype=np.int32)])
    perm = rng.permutation(len(pts))
    pts, lab = pts[perm], lab[perm]
    rot = random_rotation(rng, max_tilt_deg) if rotation is None else np.asarray(rotation, dtype=np.float64)
    trans = np.array([4.5e5, 5.4e6, 120.0]) + rng.uniform(-1e3, 1e3, 3)
    return ToyStreet(pts @ rot.T + trans, lab, rot @ ez, rot, trans)
