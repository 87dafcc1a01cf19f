"""Per-segment scale along the route (toolkit.refine.scale) and similarity transforms downstream."""

from __future__ import annotations

import numpy as np

from toolkit.arrays import weighted_median
from toolkit.refine.scale import ScaleConfig, route_scales, scaling_about
from toolkit.refine.transforms import rotation_part


def _route(n=60, step_m=25.0, trend=0.03, noise_m=0.3, seed=0):
    """Segment centres on a winding route; the input frame's step lengths drift in scale by ``trend``."""
    rng = np.random.default_rng(seed)
    heading = np.cumsum(rng.normal(0, 0.2, n))
    steps = step_m * np.column_stack([np.cos(heading), np.sin(heading)])
    truth = np.cumsum(steps, axis=0)
    s = 1.0 + trend * np.arange(n) / (n - 1)           # the frame's scale at each segment
    inp = np.cumsum(steps * s[:, None], axis=0)
    placed = truth + rng.normal(0, noise_m, truth.shape)
    route_s = np.cumsum(np.full(n, step_m))
    # placed/input: the registration maps the input back to the truth, so the segment's scale is 1/s
    return placed, inp, route_s, 1.0 / s


def test_route_scales_recover_a_drifting_scale_within_a_few_tenths_of_a_percent():
    placed, inp, route_s, want = _route()
    got = route_scales(placed, inp, route_s, np.ones(len(want), bool), np.ones(len(want)), ScaleConfig())
    assert (got.pairs >= 3).all()
    assert np.abs(got.scale - want).max() < 0.006, np.abs(got.scale - want).max()
    assert np.abs(got.scale - want).mean() < np.abs(1.0 - want).mean() / 4


def test_route_scales_clip_and_skip():
    placed, inp, route_s, _ = _route(trend=0.3)
    valid = np.ones(len(route_s), bool)
    valid[::2] = False
    cfg = ScaleConfig(max_deviation=0.05)
    got = route_scales(placed, inp, route_s, valid, np.ones(len(valid)), cfg)
    assert got.scale.min() >= 1 / 1.05 - 1e-12 and got.scale.max() <= 1.05 + 1e-12
    assert (got.scale[~valid] == 1.0).all() and (got.pairs[~valid] == 0).all()
    no_route = route_scales(placed, inp, np.full(len(valid), np.nan), valid, np.ones(len(valid)), cfg)
    assert (no_route.scale == 1.0).all()


def test_route_scales_outvote_a_misplaced_neighbour():
    placed, inp, route_s, want = _route(trend=0.0, noise_m=0.05)
    placed[30] += 40.0                                   # one segment registered on the wrong building
    got = route_scales(placed, inp, route_s, np.ones(len(want), bool), np.ones(len(want)), ScaleConfig())
    others = np.arange(len(want)) != 30
    assert np.abs(got.scale[others] - 1.0).max() < 0.01


def test_scaling_about_keeps_the_pivot_and_rotation_part_undoes_the_scale():
    M = scaling_about(np.array([[10.0, -5.0, 2.0]]), np.array([1.03]))[0]
    assert np.allclose(M[:3, :3] @ [10.0, -5.0, 2.0] + M[:3, 3], [10.0, -5.0, 2.0])
    assert np.allclose(M[:3, :3] @ [11.0, -5.0, 2.0] + M[:3, 3], [11.03, -5.0, 2.0])
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert np.allclose(rotation_part(1.03 * R), R)


def test_weighted_median():
    assert weighted_median(np.array([3.0, 1.0, 2.0]), np.ones(3)) == 2.0
    assert weighted_median(np.array([1.0, 2.0, 3.0]), np.array([1.0, 1.0, 5.0])) == 3.0
