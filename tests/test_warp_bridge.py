"""toolkit.warp.bridge: camera poses across route gaps follow the street trajectory."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from toolkit.warp.bridge import CameraPoses, bridge_gaps, ground_gap_m, grounded_cameras, sequence_breaks


def drifted_route(n: int = 301, step_m: float = 1.0, rate_deg_per_m: float = 0.02, seed: int = 0):
    """A curving true route; the street frame's heading drifts at ``rate_deg_per_m``, so the
    correction street → scene at camera k is a rotation by rate × s_k (s: metres travelled)."""
    rng = np.random.default_rng(seed)
    heading = np.cumsum(rng.normal(0.0, 0.02, n))                     # a street that bends
    steps = step_m * np.column_stack([np.cos(heading), np.sin(heading), np.zeros(n)])
    truth = np.cumsum(steps, axis=0) + [500_000.0, 5_000_000.0, 10.0]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(truth, axis=0), axis=1))])
    corr = Rotation.from_euler("z", np.radians(rate_deg_per_m) * s[:, None]).as_matrix()   # street → scene
    # street steps: truth steps turned back by the correction of the step's end camera
    street_steps = np.einsum("nba,nb->na", corr[1:], np.diff(truth, axis=0))
    street = np.concatenate([[np.zeros(3)], np.cumsum(street_steps, axis=0)])
    return truth, street, corr


def nearest_grounded(grounded):
    """(C,) the grounded camera nearest each camera in the sequence: what a blend holds in a gap."""
    g = np.flatnonzero(grounded)
    return g[np.abs(np.arange(len(grounded))[:, None] - g[None]).argmin(axis=1)]


def test_a_gap_follows_the_trajectory_between_grounded_cameras():
    truth, street, corr = drifted_route()
    grounded = np.ones(len(truth), bool)
    grounded[60:240] = False                                          # a 180 m gap
    # the gap's cameras start from the nearest grounded camera's transform, as the blend leaves them
    near = nearest_grounded(grounded)
    held = np.einsum("nab,nb->na", corr[near], street - street[near]) + truth[near]
    poses = CameraPoses(held, corr[near], np.ones(len(truth)), np.zeros(len(truth)))
    out, bridged = bridge_gaps(street, poses, grounded)
    assert bridged[60:240].all() and not bridged[:60].any() and not bridged[240:].any()
    before = np.linalg.norm(held - truth, axis=1)[60:240]
    after = np.linalg.norm(out.centres - truth, axis=1)[60:240]
    assert before.max() > 1.0                                         # the drift the gap accumulates
    assert after.max() < 0.05                                         # a linear drift is followed exactly
    angle = Rotation.from_matrix(np.einsum("nba,nbc->nac", out.rotations[60:240], corr[60:240])).magnitude()
    assert np.degrees(angle).max() < 0.05
    # grounded cameras are untouched; the chain closes, so the bridged cameras get no spread
    assert np.array_equal(out.centres[:60], held[:60]) and np.array_equal(out.centres[240:], held[240:])
    assert out.spread.max() < 1e-3


def test_a_random_walk_drift_is_reduced_and_the_misclosure_sets_the_spread():
    # a heading random walk (0.08° per m): against holding the nearer grounded camera's exact pose
    # (the best a blend of one side can do), the bridge is better on average over 20 routes
    held_err, bridged_err = [], []
    for seed in range(20):
        truth, street, _ = drifted_route(rate_deg_per_m=0.0, seed=seed)
        yaw = np.cumsum(np.random.default_rng(100 + seed).normal(0.0, np.radians(0.08), len(truth)))
        corr = Rotation.from_euler("z", yaw[:, None]).as_matrix()
        steps = np.einsum("nba,nb->na", corr[1:], np.diff(truth, axis=0))
        street = np.concatenate([[np.zeros(3)], np.cumsum(steps, axis=0)])
        grounded = np.ones(len(truth), bool)
        grounded[60:240] = False
        near = nearest_grounded(grounded)
        held = np.einsum("nab,nb->na", corr[near], street - street[near]) + truth[near]
        out, _ = bridge_gaps(street, CameraPoses(held, corr[near], np.ones(len(truth)), np.zeros(len(truth))),
                             grounded)
        held_err.append(np.median(np.linalg.norm(held - truth, axis=1)[60:240]))
        bridged_err.append(np.median(np.linalg.norm(out.centres - truth, axis=1)[60:240]))
        mid = out.spread[60:240]
        assert mid.max() > 0 and mid.argmax() not in (0, len(mid) - 1)   # largest inside the gap
    assert np.mean(bridged_err) < 0.8 * np.mean(held_err)


def test_an_ungrounded_start_integrates_back_from_the_first_grounded_camera():
    truth, street, corr = drifted_route(rate_deg_per_m=0.0)           # no drift: the path itself is exact
    grounded = np.zeros(len(truth), bool)
    grounded[100:] = True
    poses = CameraPoses(np.zeros_like(truth), np.repeat(np.eye(3)[None], len(truth), 0),
                        np.ones(len(truth)), np.zeros(len(truth)))
    poses.centres[100:] = truth[100:]
    out, bridged = bridge_gaps(street, poses, grounded)
    assert bridged[:100].all()
    assert np.abs(out.centres[:100] - truth[:100]).max() < 1e-6


def test_a_sequence_break_is_not_bridged_across():
    truth, street, corr = drifted_route(rate_deg_per_m=0.0)
    street = street.copy()
    street[150:] += [5_000.0, 0.0, 0.0]                               # a second video starts at image 150
    assert np.flatnonzero(sequence_breaks(street)).tolist() == [149]
    grounded = np.ones(len(truth), bool)
    grounded[120:180] = False
    poses = CameraPoses(truth.copy(), np.repeat(np.eye(3)[None], len(truth), 0),
                        np.ones(len(truth)), np.zeros(len(truth)))
    poses.centres[120:180] = np.nan                                   # must all be replaced
    out, bridged = bridge_gaps(street, poses, grounded)
    assert bridged[120:180].all()
    # each side integrates from its own grounded end only: the 5 km jump never enters a chain
    assert np.abs(out.centres[120:180] - truth[120:180]).max() < 1e-6


def test_nothing_grounded_or_nothing_to_bridge_leaves_the_poses():
    truth, street, corr = drifted_route(n=50)
    poses = CameraPoses(truth, corr, np.ones(50), np.zeros(50))
    for grounded in (np.zeros(50, bool), np.ones(50, bool)):
        out, bridged = bridge_gaps(street, poses, grounded)
        assert not bridged.any() and np.array_equal(out.centres, truth)


def test_grounded_cameras_count_observations_of_registered_facade_points():
    obs = np.array([[0, 0, 1, 1], [0, 1, 1, 1], [0, 2, 1, 1], [1, 2, 1, 1], [1, 3, 1, 1], [2, 3, 1, 1]], float)
    on_registered = np.array([True, True, False, True])
    assert grounded_cameras(obs, on_registered, 4, 2).tolist() == [True, False, False, False]
    assert grounded_cameras(obs, on_registered, 4, 1).tolist() == [True, True, True, False]


def _linear_drift_gap():
    truth, street, corr = drifted_route()
    grounded = np.ones(len(truth), bool)
    grounded[60:240] = False
    near = nearest_grounded(grounded)
    held = np.einsum("nab,nb->na", corr[near], street - street[near]) + truth[near]
    return truth, street, corr, grounded, CameraPoses(held, corr[near], np.ones(len(truth)), np.zeros(len(truth)))


def test_one_poorly_placed_camera_at_a_gap_edge_does_not_tilt_the_bridge():
    truth, street, corr, grounded, poses = _linear_drift_gap()
    poses.centres[240] += [2.0, -1.0, 0.0]          # the first grounded camera after the gap, 2.2 m off
    out, _ = bridge_gaps(street, poses, grounded)
    assert np.linalg.norm(out.centres[60:240] - truth[60:240], axis=1).max() < 0.05


def test_gaps_shorter_than_min_gap_keep_the_blend():
    truth, street, corr, grounded, poses = _linear_drift_gap()
    kept, bridged = bridge_gaps(street, poses, grounded, min_gap_m=200.0)   # the gap is 181 m
    assert not bridged.any() and np.array_equal(kept.centres, poses.centres)
    _, bridged = bridge_gaps(street, poses, grounded, min_gap_m=150.0)
    assert bridged[60:240].all()


def test_the_gap_to_a_grounded_camera_is_measured_along_the_route_within_its_sequence():
    street = np.column_stack([np.arange(10.0) * 2.0, np.zeros(10), np.zeros(10)])   # 2 m steps
    street[7:] += [1_000.0, 0.0, 0.0]                   # a second video starts at image 7
    grounded = np.zeros(10, bool)
    grounded[[1, 5]] = True                             # none in the second video
    gap = ground_gap_m(street, grounded)
    assert gap[:7].tolist() == [2.0, 0.0, 2.0, 4.0, 2.0, 0.0, 2.0]
    assert np.isinf(gap[7:]).all()                      # the 1 km jump is no route to a grounded camera
    assert np.isinf(ground_gap_m(street, np.zeros(10, bool))).all()
