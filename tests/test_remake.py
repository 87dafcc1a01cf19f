"""The street points re-made from the adjusted cameras (toolkit.adjust.remake)."""

from __future__ import annotations

import numpy as np

from toolkit.adjust.remake import capture_cameras
from toolkit.types import Camera, SparseModel
from toolkit.warp.cameras import CameraMaps


def _model(centres: np.ndarray, points3d: np.ndarray, observations: np.ndarray) -> SparseModel:
    C = len(centres)
    R = np.repeat(np.eye(3)[None], C, axis=0)
    return SparseModel(cameras={1: Camera(1, "PINHOLE", 100, 100, (50.0, 50.0, 50.0, 50.0))},
                       image_names=tuple(f"{i:03d}.jpg" for i in range(C)), image_ids=np.arange(1, C + 1),
                       camera_ids=np.ones(C, np.int64), R=R, t=-centres.astype(np.float64),
                       points3d_ids=np.arange(1, len(points3d) + 1), points3d=points3d.astype(np.float64),
                       points3d_rgb=np.zeros((len(points3d), 3), np.uint8), observations=observations)


def test_the_capture_camera_is_the_median_observer_of_the_nearest_sparse_point_else_the_nearest_camera():
    centres = np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0], [30, 0, 0], [40, 0, 0]])
    # sparse point 0 (at x = 100 m, beside camera 4's end of the route) seen by cameras 0, 1, 3: median 1
    obs = np.array([[0, 0, 0, 0], [1, 0, 0, 0], [3, 0, 0, 0]], np.float64)
    model = _model(centres, np.array([[100.0, 5, 0]]), obs)
    points = np.array([[101.0, 5, 0], [2.0, 30, 0], [38.0, 0, 1]])
    # the first is 1 m from the sparse point; the others are farther than 10 m from it: nearest centre
    assert capture_cameras(points, model, max_gap_m=10.0).tolist() == [1, 0, 4]


def test_a_camera_map_keeps_each_point_in_the_direction_its_camera_saw_it_at_the_scaled_depth():
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(4, 3)) * 20
    before = _model(centres, np.zeros((0, 3)), np.zeros((0, 4)))
    angle = rng.normal(size=(4, 3)) * 0.1
    R_after = np.stack([_rotation(a) for a in angle])
    t_after = rng.normal(size=(4, 3)) * 50
    cam = rng.integers(0, 4, 200)
    p = rng.normal(size=(200, 3)) * 30
    seen_before = np.einsum("nab,nb->na", before.R[cam], p) + before.t[cam]
    for scale in (None, np.array([1.0, 1.02, 0.97, 1.5])):
        moved = CameraMaps.between(before, R_after, t_after, scale).at(cam).apply(p)
        seen_after = np.einsum("nab,nb->na", R_after[cam], moved) + t_after[cam]
        s = np.ones(4) if scale is None else scale
        np.testing.assert_allclose(seen_after, s[cam, None] * seen_before, atol=1e-9)


def _rotation(w: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(w)
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / th
    return np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * k @ k
