"""Points of another pass of the route than their segment (loop start/end) are re-anchored (toolkit.warp.passes)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plugins.warp_inverse_log import InverseLog
from plugins.warp_nearest import Nearest
from toolkit.capture import StreetCapture
from toolkit.io.cloud import write_ply
from toolkit.io.colmap import write_model
from toolkit.observe import NullObserver
from toolkit.scene import load_scene, write_manifest
from toolkit.types import Camera, SegmentTransforms, SparseModel, StreetSegments
from toolkit.warp.passes import reanchor_other_pass, sparse_route_positions


def _model(centres, points3d, observations):
    n = len(centres)
    R = np.repeat(np.eye(3)[None], n, axis=0)
    return SparseModel(
        cameras={1: Camera(1, "PINHOLE", 640, 480, np.array([500.0, 500, 320, 240]))},
        image_names=tuple(f"c{i:03d}.jpg" for i in range(n)), image_ids=np.arange(1, n + 1),
        camera_ids=np.ones(n, int), R=R, t=-centres, points3d_ids=np.arange(1, len(points3d) + 1),
        points3d=points3d, points3d_rgb=np.zeros((len(points3d), 3), np.uint8), observations=observations)


def test_sparse_route_position_is_the_median_of_the_observing_cameras():
    centres = np.column_stack([np.arange(5.0) * 10, np.zeros(5), np.zeros(5)])    # s = 0, 10, ..., 40
    obs = np.array([[0, 0, 1, 1], [1, 0, 1, 1], [4, 0, 1, 1], [3, 1, 1, 1], [2, 2, 1, 1]], float)
    s = sparse_route_positions(_model(centres, np.zeros((4, 3)), obs))
    assert s[0] == 10.0 and s[1] == 30.0 and s[2] == 20.0 and np.isnan(s[3])


def test_reanchor_moves_only_points_of_another_pass_and_only_to_their_own_pass():
    seg_s = np.array([0.0, 1000.0, 20.0])
    fp_xy = np.array([[0.0, 0.0], [0.0, 3.0], [0.0, 1.0]])
    fp_seg = np.array([0, 1, 2])
    xy = np.array([[0.0, 0.5], [0.0, 0.5], [0.0, 0.5], [0.0, 0.5]])
    point_s = np.array([5.0, 990.0, np.nan, 2000.0])   # own pass, other pass, unknown, no segment of its pass
    out = reanchor_other_pass(np.zeros(4, np.int64), xy, point_s, seg_s, fp_xy, fp_seg, 200.0)
    assert out.tolist() == [0, 1, 0, 0]                 # nearer segment 2 is of the wrong pass for point 1


def test_reanchor_never_picks_another_pass_at_the_same_place_over_its_own_pass_farther_off():
    seg_s = np.array([0.0, 300.0, 850.0])      # 0: the point's anchor; 1: another pass here; 2: its own, 80 m off
    fp_xy = np.array([[0.0, 0.0], [0.0, 1.0], [80.0, 0.0]])
    fp_seg = np.array([0, 1, 2])
    out = reanchor_other_pass(np.zeros(1, np.int64), np.array([[0.0, 0.5]]), np.array([900.0]), seg_s, fp_xy,
                              fp_seg, 200.0)
    assert out.tolist() == [2]


def _loop_scene(tmp_path):
    """Façade copies of the first (y = 8) and last (y = 6) pass, merged into segment 0 by the
    segmentation; segment 1 is a façade of the last pass only. Registered, the last pass lies 12 m
    away from where segment 0's transform (fitted to the first pass) would put it."""
    rng = np.random.default_rng(1)
    first = np.column_stack([rng.uniform(0, 20, 600), np.full(600, 8.0), rng.uniform(0, 8, 600)])
    last = np.column_stack([rng.uniform(0, 20, 300), np.full(300, 6.0), rng.uniform(0, 8, 300)])
    other = np.column_stack([rng.uniform(0, 20, 300), np.full(300, 2.0), rng.uniform(0, 8, 300)])
    pts = np.vstack([first, last, other])
    labels = np.concatenate([np.zeros(900, np.int32), np.ones(300, np.int32)])
    street = StreetSegments(
        origin=np.zeros(3), up_rotation=np.eye(3), point_labels=labels, carrier=labels.copy(), ids=np.arange(2),
        boundary_xy=(first[:, :2], other[:, :2]), centroids=np.array([[10.0, 8.0], [10.0, 2.0]]),
        extent_m=np.full(2, 20.0), ground_z=np.zeros(2), ground_normal=np.tile([0, 0, 1.0], (2, 1)))
    # cameras: 20 of the first pass at s = 0..19 m, then the route goes 1 km away and comes back
    cam = np.vstack([np.column_stack([np.arange(20.0), np.full(20, 4.0), np.full(20, 1.5)]),
                     [[500.0, 500.0, 1.5]],
                     np.column_stack([np.arange(20.0), np.full(20, 4.0), np.full(20, 1.5)])])
    seen = np.concatenate([rng.choice(600, 60, replace=False), 600 + rng.choice(300, 30, replace=False),
                           900 + rng.choice(300, 30, replace=False)])
    pass_of = np.where(seen < 600, 0, 1)
    obs = []
    for p, ps in enumerate(pass_of):
        for c in rng.choice(20, 3, replace=False) + (0 if ps == 0 else 21):
            obs.append([c, p, 100.0, 100.0])
    model = _model(cam, pts[seen], np.array(obs, float))
    root = tmp_path / "loop"
    (root / "street").mkdir(parents=True)
    write_ply(root / "street/cloud.ply", pts)
    write_model(model, root / "street/sparse")
    write_manifest(root, "loop", "EPSG:32617", {"street": {"cloud": "street/cloud.ply", "sparse": "street/sparse"}})
    T = np.repeat(np.eye(4)[None], 2, axis=0)
    T[1, :3, 3] = [0.0, 12.0, 0.0]
    truth = pts.copy()
    truth[600:, 1] += 12.0
    tr = SegmentTransforms(T=T, valid=np.ones(2, bool), cost=np.zeros(2), confidence=np.ones(2))
    return street, load_scene(root), tr, truth


@pytest.mark.parametrize("stage", [Nearest, InverseLog], ids=["nearest", "inverse_log"])
def test_points_of_the_other_pass_follow_a_segment_of_their_own_pass(tmp_path, stage):
    street, scene, tr, truth = _loop_scene(tmp_path)
    on = stage.from_config({"neighbours_k": 1} if stage is InverseLog else {})(tr, street, scene, StreetCapture(scene), NullObserver())
    off = stage.from_config({"pass_gap_m": None, **({"neighbours_k": 1} if stage is InverseLog else {})})(
        tr, street, scene, StreetCapture(scene), NullObserver())
    err_on = np.linalg.norm(on.points - truth, axis=1)
    err_off = np.linalg.norm(off.points - truth, axis=1)
    assert np.median(err_off[600:900]) > 10.0                 # without the check: 12 m off
    assert np.median(err_on[600:900]) < 1.0 and np.percentile(err_on[600:900], 90) < 3.0
    assert np.abs(on.points[:600] - truth[:600]).max() < 1e-6      # the first pass stays with segment 0
    assert (on.point_segment[600:900] == 1).mean() > 0.8


@pytest.mark.parametrize("stage", [Nearest, InverseLog], ids=["nearest", "inverse_log"])
def test_cameras_of_the_other_pass_follow_a_segment_of_their_own_pass(tmp_path, stage):
    """A last-pass camera that mostly sees the merged segment 0 (fitted to the first pass) must not
    take its transform: it is anchored on a segment of its own pass (here 1, 12 m away)."""
    street, scene, tr, _ = _loop_scene(tmp_path)
    extra = {"neighbours_k": 1, "camera_neighbours_k": 1} if stage is InverseLog else {}
    on = stage.from_config(extra)(tr, street, scene, StreetCapture(scene), NullObserver())
    off = stage.from_config({"pass_gap_m": None, **extra})(tr, street, scene, StreetCapture(scene), NullObserver())
    truth = np.vstack([np.column_stack([np.arange(20.0), np.full(20, 4.0), np.full(20, 1.5)]),
                       np.column_stack([np.arange(20.0), np.full(20, 16.0), np.full(20, 1.5)])])
    last = np.r_[0:20, 21:41]  # every camera but the one 1 km away

    def centre_err(reg):
        return np.linalg.norm(-np.einsum("cji,cj->ci", reg.R, reg.t)[last] - truth, axis=1)

    assert centre_err(off)[20:].max() > 10.0       # without the check some last-pass camera is 12 m off
    assert centre_err(on)[20:].max() < 1e-6
    assert centre_err(on)[:20].max() < 1e-6        # the first pass keeps segment 0's transform


def test_points_without_a_sparse_point_near_them_take_their_carriers_pass(tmp_path):
    """A last-pass façade (segment 2) left unregistered lies next to a first-pass one (segment 0) in
    the street frame. Its ground has no sparse point within reach, so its own route position is
    unknown: it is of its carrier's pass, and follows segment 1 (last pass), not segment 0."""
    rng = np.random.default_rng(2)
    first = np.column_stack([rng.uniform(0, 20, 300), np.full(300, 8.0), rng.uniform(4, 8, 300)])
    last = np.column_stack([rng.uniform(0, 20, 300), np.full(300, 2.0), rng.uniform(4, 8, 300)])
    unreg = np.column_stack([rng.uniform(0, 20, 300), np.full(300, 7.0), rng.uniform(4, 8, 300)])
    ground = np.column_stack([rng.uniform(0, 20, 300), rng.uniform(6.0, 7.0, 300), np.zeros(300)])
    pts = np.vstack([first, last, unreg, ground])
    labels = np.repeat(np.array([0, 1, 2, -1], np.int32), 300)
    carrier = np.repeat(np.array([0, 1, 2, 2], np.int32), 300)
    street = StreetSegments(
        origin=np.zeros(3), up_rotation=np.eye(3), point_labels=labels, carrier=carrier, ids=np.arange(3),
        boundary_xy=(first[:, :2], last[:, :2], unreg[:, :2]), centroids=np.array([[10.0, 8.0], [10.0, 2.0], [10.0, 7.0]]),
        extent_m=np.full(3, 20.0), ground_z=np.zeros(3), ground_normal=np.tile([0, 0, 1.0], (3, 1)))
    cam = np.vstack([np.column_stack([np.arange(20.0), np.full(20, 4.0), np.full(20, 1.5)]),
                     [[500.0, 500.0, 1.5]],
                     np.column_stack([np.arange(20.0), np.full(20, 4.0), np.full(20, 1.5)])])
    seen = np.concatenate([rng.choice(300, 40, replace=False), 300 + rng.choice(600, 80, replace=False)])
    obs = [[c, p, 100.0, 100.0] for p, row in enumerate(seen)
           for c in rng.choice(20, 3, replace=False) + (0 if row < 300 else 21)]
    root = tmp_path / "unreg"
    (root / "street").mkdir(parents=True)
    write_ply(root / "street/cloud.ply", pts)
    write_model(_model(cam, pts[seen], np.array(obs, float)), root / "street/sparse")
    write_manifest(root, "unreg", "EPSG:32617", {"street": {"cloud": "street/cloud.ply", "sparse": "street/sparse"}})
    T = np.repeat(np.eye(4)[None], 3, axis=0)
    T[1:, :3, 3] = [0.0, 12.0, 0.0]
    tr = SegmentTransforms(T=T, valid=np.array([True, True, False]), cost=np.zeros(3), confidence=np.ones(3))
    reg = Nearest()(tr, street, load_scene(root), StreetCapture(load_scene(root)), NullObserver())
    assert (reg.point_segment[900:] == 1).all()                    # the unregistered segment's ground
    assert np.allclose(reg.points[900:], pts[900:] + [0.0, 12.0, 0.0])
    assert (reg.point_segment[:300] == 0).all()


@pytest.mark.parametrize("min_observations", [1, 5, 1000])
def test_bridged_cameras_keep_transforms_that_agree_with_the_trajectory(tmp_path, min_observations):
    """Each pass has one exact transform (identity, a 12 m shift): following the street trajectory
    from grounded cameras reproduces it; the camera 1 km away (a break in the sequence) is left as is."""
    street, scene, tr, _ = _loop_scene(tmp_path)
    extra = {"neighbours_k": 1, "camera_neighbours_k": 1}
    base = InverseLog.from_config(extra)(tr, street, scene, StreetCapture(scene), NullObserver())
    for gap in (200.0, None):   # with and without the pass check (two ways to find registered façades)
        reg = InverseLog.from_config({**extra, "pass_gap_m": gap, "bridge_min_observations": min_observations,
                                      "bridge_min_gap_m": 0})(
            tr, street, scene, StreetCapture(scene), NullObserver())
        centres = -np.einsum("cji,cj->ci", reg.R, reg.t)
        assert np.all(np.isfinite(centres))
        if gap is not None:
            assert np.allclose(centres, -np.einsum("cji,cj->ci", base.R, base.t), atol=1e-6)
            assert np.allclose(reg.R, base.R, atol=1e-9)


def test_bridged_cameras_follow_the_capture_order_not_the_models(tmp_path, monkeypatch):
    """The same cameras listed in reverse (names numbered backwards) are bridged along the same
    trajectory: the bridge walks the images in capture (name) order."""
    import toolkit.warp.apply as warp_apply

    seen = []
    real = warp_apply.bridge_gaps
    monkeypatch.setattr(warp_apply, "bridge_gaps", lambda C, *a, **k: seen.append(C.copy()) or real(C, *a, **k))
    street, scene, tr, _ = _loop_scene(tmp_path)
    cfg = {"neighbours_k": 1, "camera_neighbours_k": 1, "bridge_min_observations": 5, "bridge_min_gap_m": 0}
    forward = InverseLog.from_config(cfg)(tr, street, scene, StreetCapture(scene), NullObserver())
    model = StreetCapture(scene).sparse
    n = len(model.image_names)
    backwards = dataclasses.replace(model, image_names=tuple(f"c{n - 1 - i:03d}.jpg" for i in range(n)))
    root = tmp_path / "backwards"
    (root / "street").mkdir(parents=True)
    write_ply(root / "street/cloud.ply", StreetCapture(scene).points)
    write_model(backwards, root / "street/sparse")
    write_manifest(root, "loop", "EPSG:32617", {"street": {"cloud": "street/cloud.ply", "sparse": "street/sparse"}})
    scene_b = load_scene(root)
    reverse = InverseLog.from_config(cfg)(tr, street, scene_b, StreetCapture(scene_b), NullObserver())
    assert np.allclose(seen[1], seen[0][::-1])          # handed over in capture order both times
    centres = [-np.einsum("cji,cj->ci", r.R, r.t) for r in (forward, reverse)]
    assert np.allclose(centres[0], centres[1], atol=1e-6)


def test_the_registration_says_which_cameras_were_bridged(tmp_path):
    from toolkit.status import bridged_camera_share, camera_gap_p90_m

    street, scene, tr, _ = _loop_scene(tmp_path)
    cfg = {"neighbours_k": 1, "camera_neighbours_k": 1}
    off = InverseLog.from_config({**cfg, "bridge_min_observations": 0})(tr, street, scene, StreetCapture(scene),
                                                                         NullObserver())
    on = InverseLog.from_config({**cfg, "bridge_min_observations": 5, "bridge_min_gap_m": 0})(
        tr, street, scene, StreetCapture(scene), NullObserver())
    assert off.camera_bridged is None and bridged_camera_share(off) is None
    assert on.camera_bridged.dtype == bool and on.camera_bridged.sum() == 2     # two cameras see < 5 façade points
    assert bridged_camera_share(on) == 2 / 41
    # the two are one 1 m step from a camera that sees registered façades; the excursion 700 m
    # away is a sequence of its own, with none
    assert off.camera_gap_m is None and camera_gap_p90_m(off) is None
    gap = on.camera_gap_m
    assert (gap[on.camera_bridged] == 1.0).all() and np.isinf(gap[20])
    assert (gap[~on.camera_bridged & (np.arange(41) != 20)] == 0.0).all() and camera_gap_p90_m(on) == 0.0
