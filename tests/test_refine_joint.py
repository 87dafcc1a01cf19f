"""Joint registration along the route (toolkit.refine.joint): per-building outline errors average out."""

from __future__ import annotations

import numpy as np

from toolkit.refine.joint import JointParams, OutlineLabels, cap_per_label, joint_footprint, joint_transforms
from toolkit.refine.transforms import rigid2d
from toolkit.types import Grid

GSD = 0.5
E0, N0 = 500000.0, 4400000.0


def _street(seed: int, shift_sigma_m: float = 0.7):
    """Buildings on both sides of a 200 m street; each over-view outline shifted by its own offset.

    Returns grid, label image, per-segment levelled footprints (front wall + 4 m of the side
    walls), the true levelled → scene transform (one for all: no drift), per-segment route
    positions and street-frame centres, and each building's outline shift.
    """
    rng = np.random.default_rng(seed)
    W, H = 440, 200
    grid = Grid((GSD, 0.0, E0, 0.0, -GSD, N0 + H * GSD), W, H, "EPSG:32617")
    rows, cols = np.mgrid[0:H, 0:W]
    cx, cy = cols * GSD + GSD / 2, (H - rows) * GSD - GSD / 2
    label = -np.ones((H, W), np.int32)
    T_true = rigid2d(np.radians(25.0), np.array([E0 + 7.0, N0 - 3.0]))
    inv = np.linalg.inv(T_true)
    fps, route, centres, shifts = {}, [], [], []
    k = 0
    for y0, y1, front in ((62.0, 82.0, 62.0), (18.0, 38.0, 38.0)):
        x = 5.0 + rng.uniform(0, 4)
        while x < 190:
            x1 = x + rng.uniform(15, 28)
            d = rng.normal(0, shift_sigma_m, 2)
            inside = (cx >= x + d[0]) & (cx < x1 + d[0]) & (cy >= y0 + d[1]) & (cy < y1 + d[1])
            label[inside] = k
            t = np.arange(x, x1, 0.25)
            depth = np.arange(0, 4, 0.25)
            back = 1.0 if front == y0 else -1.0
            wall = np.vstack([np.column_stack([t, np.full(len(t), front)]),
                              np.column_stack([np.full(len(depth), x), front + back * depth]),
                              np.column_stack([np.full(len(depth), x1), front + back * depth])])
            world = wall + [E0, N0]
            fps[k] = world @ inv[:2, :2].T + inv[:2, 2]
            route.append((x + x1) / 2)
            centres.append(fps[k].mean(axis=0))
            shifts.append(d)
            k += 1
            x = x1 + rng.uniform(4, 8)
    return grid, label, fps, T_true, np.array(route), np.array(centres), np.array(shifts)


def _centre_errors(T2d, T_true, fps):
    return np.array([np.linalg.norm((fps[i] @ (T2d[i][:2, :2] - T_true[:2, :2]).T + T2d[i][:2, 2]
                                     - T_true[:2, 2]).mean(axis=0)) for i in fps])


def test_joint_registration_averages_out_per_building_outline_errors():
    before, after = [], []
    for seed in range(2):
        grid, label, fps, T_true, route, centres, shifts = _street(seed)
        # each segment registered on its own lands on its building's shifted outline
        own = np.stack([np.eye(3) for _ in fps])
        for i in fps:
            own[i] = rigid2d(0.0, shifts[i]) @ T_true
        joint = joint_transforms(fps, own, route, centres, grid, label, JointParams(window_m=60.0))
        before.append(_centre_errors(own, T_true, fps))
        after.append(_centre_errors(joint, T_true, fps))
    before, after = np.concatenate(before), np.concatenate(after)
    assert np.median(after) < 0.65 * np.median(before), (np.median(before), np.median(after))


def test_joint_registration_keeps_exact_transforms_and_skips_unknown_route_positions():
    grid, label, fps, T_true, route, centres, shifts = _street(0, shift_sigma_m=0.0)
    own = np.stack([T_true for _ in fps])
    route = route.copy()
    route[0] = np.nan
    seed0 = rigid2d(0.01, np.array([0.5, 0.0])) @ T_true
    own[0] = seed0
    joint = joint_transforms(fps, own, route, centres, grid, label, JointParams(window_m=60.0))
    assert np.array_equal(joint[0], seed0)                 # no route position: left alone
    assert np.median(_centre_errors(joint, T_true, {i: fps[i] for i in list(fps)[1:]})) < 0.1


def _wall(x0: float, length_m: float) -> np.ndarray:
    t = np.arange(0.0, length_m, 0.25)
    return np.column_stack([x0 + t, np.zeros(len(t))])


def test_joint_footprint_box_is_every_footprint_and_caps_and_tricube_thin_by_segment():
    fps = {0: _wall(0.0, 100.0), 1: _wall(200.0, 10.0), 2: _wall(400.0, 10.0)}
    near = np.array([0, 1, 2])
    ds = np.array([0.0, 30.0, 90.0])
    box = joint_footprint(fps, near, ds, JointParams(window_m=100.0, cell_m=0.5))
    assert len(box) == 200 + 20 + 20                       # all of them, one point per 0.5 m cell
    capped = joint_footprint(fps, near, ds, JointParams(window_m=100.0, cell_m=0.5, segment_points=20))
    assert len(capped) == 60                               # the long wall no longer outweighs the others
    assert np.array_equal(capped[20:], box[200:])
    tri = joint_footprint(fps, near, ds, JointParams(window_m=100.0, cell_m=0.5, kernel="tricube"))
    x = tri[:, 0]
    # tricube shares (1 - (ds/100)^3)^3: 1, 0.92, 0.019 -> 200, 19 of 20, 1 (at least one point)
    assert ((x < 150).sum(), ((x > 150) & (x < 300)).sum(), (x > 300).sum()) == (200, 19, 1)
    again = joint_footprint(fps, near, ds, JointParams(window_m=100.0, cell_m=0.5, kernel="tricube"))
    assert np.array_equal(tri, again)                      # deterministic


def test_joint_tricube_window_still_averages_out_outline_errors():
    grid, label, fps, T_true, route, centres, shifts = _street(0)
    own = np.stack([rigid2d(0.0, shifts[i]) @ T_true for i in fps])
    joint = joint_transforms(fps, own, route, centres, grid, label,
                             JointParams(window_m=120.0, kernel="tricube"))
    assert np.median(_centre_errors(joint, T_true, fps)) < 0.65 * np.median(_centre_errors(own, T_true, fps))


def test_outline_labels_name_the_nearest_outline():
    grid = Grid((1.0, 0.0, 0.0, 0.0, -1.0, 20.0), 40, 20, "EPSG:32617")
    label = -np.ones((20, 40), np.int32)
    label[5:15, 2:12] = 3          # x 2..12 m, y 5..15 m
    label[5:15, 25:35] = 7         # x 25..35 m
    xy = np.array([[2.1, 10.0], [12.4, 10.0], [17.0, 10.0], [19.0, 10.0], [30.0, 16.0]])
    assert OutlineLabels(grid, label)(xy).tolist() == [3, 3, 3, 7, 7]
    assert OutlineLabels(grid, -np.ones((20, 40), np.int32))(xy).tolist() == [-1] * 5


def test_cap_per_label_keeps_an_even_stride_of_each_large_group():
    pts = np.arange(20.0)[:, None] * [1.0, 0.0]
    labels = np.array([0] * 12 + [1] * 3 + [2] * 5)
    out = cap_per_label(pts, labels, 4)
    assert out[:, 0].tolist() == [0.0, 3.0, 7.0, 11.0, 12.0, 13.0, 14.0, 15.0, 16.0, 17.0, 19.0]


def test_joint_footprint_outline_cap_counts_each_outline_once_across_segments():
    # two segments on one long building (outline 0) and a short one on another (outline 1)
    fps = {0: _wall(0.0, 60.0), 1: _wall(60.0, 60.0), 2: _wall(200.0, 10.0)}
    labels = {0: np.zeros(120, np.int64), 1: np.zeros(120, np.int64), 2: np.ones(20, np.int64)}
    near, ds = np.array([0, 1, 2]), np.zeros(3)
    p = JointParams(window_m=100.0, cell_m=0.5, kernel="tricube", outline_points=40)
    out = joint_footprint(fps, near, ds, p, labels)
    assert ((out[:, 0] < 150).sum(), (out[:, 0] > 150).sum()) == (40, 20)
    assert out[:, 0][out[:, 0] < 150].max() > 100          # spread over both segments of the building
    uncapped = joint_footprint(fps, near, ds, JointParams(window_m=100.0, cell_m=0.5, kernel="tricube"), labels)
    assert len(uncapped) == 260


def test_joint_outline_cap_still_averages_out_outline_errors():
    grid, label, fps, T_true, route, centres, shifts = _street(1)
    own = np.stack([rigid2d(0.0, shifts[i]) @ T_true for i in fps])
    joint = joint_transforms(fps, own, route, centres, grid, label,
                             JointParams(window_m=120.0, kernel="tricube", outline_points=40))
    assert np.median(_centre_errors(joint, T_true, fps)) < 0.65 * np.median(_centre_errors(own, T_true, fps))


def _straight_wall_scene():
    """An 80 m block, its street wall at y = 30; the true levelled → scene transform."""
    W, H = 200, 120
    grid = Grid((GSD, 0.0, E0, 0.0, -GSD, N0 + H * GSD), W, H, "EPSG:32617")
    rows, cols = np.mgrid[0:H, 0:W]
    cx, cy = cols * GSD + GSD / 2, (H - rows) * GSD - GSD / 2
    label = -np.ones((H, W), np.int32)
    label[(cx >= 10) & (cx < 90) & (cy >= 30) & (cy < 50)] = 0
    return grid, label, rigid2d(np.radians(25.0), np.array([E0 + 7.0, N0 - 3.0]))


def _walls(T_true, spans):
    """Levelled footprints of straight pieces of the wall at y = 30 (no corner), one per span (x0, x1)."""
    inv = np.linalg.inv(T_true)
    walls = [np.column_stack([np.arange(x0, x1, 0.25), np.full(int(round((x1 - x0) / 0.25)), 30.0)]) + [E0, N0]
             for x0, x1 in spans]
    return walls, {k: w @ inv[:2, :2].T + inv[:2, 2] for k, w in enumerate(walls)}


def test_a_window_of_one_straight_wall_keeps_its_own_transform():
    # at the ends of the route, or where the neighbours were rejected, a window may hold one wall: a
    # re-fit would be its own search again, without the penalty that kept its position along the wall
    grid, label, T_true = _straight_wall_scene()
    _, fps = _walls(T_true, [(30.0, 60.0)])
    seed = T_true @ rigid2d(0.0, np.array([0.4, 0.0]))       # the own search's result, 0.4 m along the wall
    out = joint_transforms(fps, seed[None], np.array([0.0]), fps[0].mean(axis=0)[None], grid, label,
                           JointParams(window_m=50.0))
    np.testing.assert_array_equal(out[0], seed)


def test_a_window_of_straight_walls_keeps_its_seed_along_them_with_the_shift_penalty():
    # two pieces of one straight wall: the window's cost is flat along it, and only the shift penalty
    # keeps the seed's position
    grid, label, T_true = _straight_wall_scene()
    walls, fps = _walls(T_true, [(22.0, 40.0), (46.0, 64.0)])
    route, centres = np.array([0.0, 24.0]), np.array([f.mean(axis=0) for f in fps.values()])
    moved = {}
    for penalty in (0.0, 0.03):
        out = joint_transforms(fps, np.stack([T_true, T_true]), route, centres, grid, label,
                               JointParams(window_m=50.0, shift_penalty=penalty))
        moved[penalty] = np.linalg.norm((fps[0] @ out[0][:2, :2].T + out[0][:2, 2]).mean(axis=0) - walls[0].mean(axis=0))
    assert moved[0.03] < 0.05, moved
    assert moved[0.0] > 1.0, moved       # without it the walls slide to the edge of the search
