"""Segment rotations smoothed along the route (toolkit.refine.rotation)."""

from __future__ import annotations

import numpy as np

from toolkit.refine.rotation import rotation_deg, smoothed_rotations
from toolkit.refine.transforms import rigid2d


def _row(angles_deg, route_s, spacing_m: float = 20.0):
    """Segments 20 m apart along a straight street, each placed by one true transform (rotation 3°)
    turned by (its angle − 3°) about its own footprint centre, as a search that fits the façade but
    not the rotation leaves it: transforms, footprint centres (levelled), street-frame anchors
    (x, y, z) and route positions."""
    n = len(angles_deg)
    centres = np.column_stack([np.arange(n) * spacing_m, np.full(n, 8.0)])
    true = rigid2d(np.radians(3.0), np.array([500000.0, 4400000.0]))
    T = np.stack([_turned(true, np.radians(a - 3.0), c) for a, c in zip(angles_deg, centres)])
    anchors = np.column_stack([centres, np.zeros(n)])
    return T, centres, anchors, np.asarray(route_s, np.float64)


def _turned(T, angle, centre):
    """T followed by a turn of ``angle`` about where T puts ``centre``."""
    pivot = _apply(T, centre)
    turn = rigid2d(angle, pivot - rigid2d(angle, np.zeros(2))[:2, :2] @ pivot)
    return turn @ T


def _apply(T, xy):
    return xy @ T[:2, :2].T + T[:2, 2]


def test_equal_rotations_are_kept_and_transforms_unchanged():
    T, centres, anchors, s = _row([12.0] * 6, np.arange(6) * 20.0)
    out = smoothed_rotations(T, np.arange(6), s, anchors, centres, np.ones(6), 100.0)
    np.testing.assert_allclose(out, T, atol=1e-9)


def test_an_outlying_rotation_is_pulled_to_its_neighbours_about_its_own_footprint_centre():
    angles = [3.0, 3.0, 3.0, 5.5, 3.0, 3.0, 3.0]
    T, centres, anchors, s = _row(angles, np.arange(7) * 20.0)
    out = smoothed_rotations(T, np.arange(7), s, anchors, centres, np.ones(7), 100.0)
    after = rotation_deg(out)
    assert abs(after[3] - 3.0) < 0.6                 # was 2.5° off
    # a mean: its neighbours lean towards it by a share of that, less than it moved
    assert np.all(np.abs(after[[0, 1, 2, 4, 5, 6]] - 3.0) < 0.5)
    # the footprint centre of each segment stays where its own transform put it
    for i in range(7):
        np.testing.assert_allclose(_apply(out[i], centres[i]), _apply(T[i], centres[i]), atol=1e-6)
    # ground 40 m from the outlier's façade: 1.7 m off before, within 0.4 m after
    far = centres[3] + [0.0, 40.0]
    true = T[0]
    assert np.linalg.norm(_apply(T[3], far) - _apply(true, far)) > 1.6
    assert np.linalg.norm(_apply(out[3], far) - _apply(true, far)) < 0.4


def test_segments_beyond_the_window_or_unlisted_or_of_another_pass_do_not_count():
    angles = [0.0, 0.0, 10.0, 10.0]
    s = np.array([0.0, 10.0, 500.0, 20.0])
    T, centres, anchors, _ = _row(angles, s)
    # segment 3 is next along the route but far in the street frame (another pass next to nothing)
    anchors[3] = [5000.0, 0.0, 0.0]
    out = smoothed_rotations(T, np.array([0, 1, 2, 3]), s, anchors, centres, np.ones(4), 100.0)
    np.testing.assert_allclose(rotation_deg(out), angles, atol=1e-9)
    # a segment left out of idx is neither changed nor used
    T2, c2, a2, s2 = _row([0.0, 0.0, 10.0], [0.0, 10.0, 20.0])
    out2 = smoothed_rotations(T2, np.array([0, 1]), s2, a2, c2, np.ones(3), 100.0)
    np.testing.assert_allclose(out2, T2, atol=1e-9)


def test_weights_and_the_tricube_kernel_set_the_mean():
    T, centres, anchors, s = _row([0.0, 2.0], [0.0, 50.0])
    w = np.array([3.0, 1.0])
    out = smoothed_rotations(T, np.arange(2), s, anchors, centres, w, 100.0)
    k = (1 - 0.5 ** 3) ** 3                          # tricube at half the window
    expected0 = (3.0 * 0.0 + 1.0 * k * 2.0) / (3.0 + k)
    expected1 = (3.0 * k * 0.0 + 1.0 * 2.0) / (3.0 * k + 1.0)
    np.testing.assert_allclose(rotation_deg(out), [expected0, expected1], atol=1e-9)


def test_angles_either_side_of_180_degrees_average_across_it():
    T, centres, anchors, s = _row([179.0, -179.0], [0.0, 0.0])
    out = smoothed_rotations(T, np.arange(2), s, anchors, centres, np.ones(2), 100.0)
    np.testing.assert_allclose(np.abs(rotation_deg(out)), [180.0, 180.0], atol=1e-9)


def test_window_zero_or_a_single_segment_changes_nothing():
    T, centres, anchors, s = _row([0.0, 4.0], [0.0, 10.0])
    np.testing.assert_array_equal(smoothed_rotations(T, np.arange(2), s, anchors, centres, np.ones(2), 0.0), T)
    np.testing.assert_array_equal(smoothed_rotations(T, np.array([1]), s, anchors, centres, np.ones(2), 100.0), T)
