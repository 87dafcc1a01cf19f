"""street.region_growing on small clouds built from planes (toolkit.testing.street_toy) and bad inputs."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from plugins.street_region_growing import RegionGrowing
from toolkit.capture import StreetCapture
from toolkit.errors import StageError
from toolkit.io.cloud import write_ply
from toolkit.observe import DebugLines, DebugPoints, DebugScalar, NullObserver
from toolkit.scene import load_scene, write_manifest
from toolkit.street.clock import STEP_SHARES
from toolkit.street.params import nested_groups
from toolkit.street.score import angle_deg, found_up, score_segments
from toolkit.street.split import SplitConfig
from toolkit.testing.street_toy import toy_street
from toolkit.types import StreetSegments


@pytest.fixture(scope="module")
def toy():
    return toy_street(seed=0, density=12.0)


@pytest.fixture(scope="module")
def segmented(toy):
    obs = NullObserver()
    return RegionGrowing().segment(toy.points, obs), obs


def test_toy_quality(toy, segmented):
    seg, obs = segmented
    assert angle_deg(found_up(seg), toy.up) < 0.5
    s = score_segments(seg, toy.labels, toy.points)
    assert s.facade_precision >= 0.95
    assert s.facade_recall >= 0.75  # side walls under 5 m and corner points are lost by design
    assert s.coverage >= 0.9
    assert s.segments_pure >= 0.9 * s.segments
    assert not obs.warnings


def test_output_contract(toy, segmented):
    seg, _ = segmented
    n, s = len(toy.points), len(seg)
    assert isinstance(seg, StreetSegments) and s > 5
    np.testing.assert_allclose(seg.up_rotation @ seg.up_rotation.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(seg.up_rotation) == pytest.approx(1.0)
    assert seg.origin.shape == (3,) and np.linalg.norm(seg.origin - toy.points.mean(axis=0)) < 100
    assert seg.point_labels.shape == (n,) and seg.point_labels.dtype == np.int32
    assert seg.carrier.shape == (n,) and seg.carrier.dtype == np.int32
    assert seg.point_labels.min() >= -2 and seg.point_labels.max() == s - 1
    in_seg = seg.point_labels >= 0
    assert np.array_equal(seg.carrier[in_seg], seg.point_labels[in_seg])  # segment points carry themselves
    assert (seg.carrier[seg.point_labels == -1] >= 0).mean() > 0.95  # ground moves with a segment
    assert seg.ids.tolist() == list(range(s))
    assert seg.centroids.shape == (s, 2) and seg.extent_m.shape == (s,)
    assert (seg.extent_m >= 5.0).all()
    assert len(seg.boundary_xy) == s and all(0 < len(b) <= 2000 for b in seg.boundary_xy)
    assert seg.ground_z.shape == (s,) and np.isfinite(seg.ground_z).all()
    np.testing.assert_allclose(np.linalg.norm(seg.ground_normal, axis=1), 1.0, atol=1e-6)
    assert (seg.ground_normal[:, 2] > np.cos(np.radians(5))).all()  # the toy's slope is 1.1°
    assert seg.normals.shape == (n, 3) and seg.normals.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(seg.normals, axis=1), 1.0, atol=1e-4)
    # levelled: ground at about the same height as each segment's ground, façades above it
    lev = seg.level(toy.points)
    for i in range(min(s, 5)):
        z = lev[seg.point_labels == i, 2]
        assert np.median(z) > seg.ground_z[i]
    # boundary points are façade points projected to z = 0
    lab0 = lev[seg.point_labels == 0, :2]
    d = np.min(np.linalg.norm(seg.boundary_xy[0][:50, None] - lab0[None, ::7], axis=2), axis=1)
    assert d.max() < 0.5


@pytest.mark.parametrize("tilt_deg", [0.0, 30.0, 45.0, 90.0, 180.0])
def test_vertical_any_rotation(tilt_deg):
    rng = np.random.default_rng(int(tilt_deg))
    yaw = rng.uniform(0, 2 * np.pi)
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    t = np.radians(tilt_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    toy = toy_street(seed=1, density=6.0, rotation=rx @ rz)
    seg = RegionGrowing().segment(toy.points, NullObserver())
    assert angle_deg(found_up(seg), toy.up) < 0.5  # signed: a flipped up would be ~180°
    assert score_segments(seg, toy.labels, toy.points).coverage >= 0.8


def test_labels_follow_input_order_and_translation(toy, segmented):
    seg, _ = segmented
    rng = np.random.default_rng(5)
    perm = rng.permutation(len(toy.points))
    moved = toy.points[perm] + [3.0e6, -2.0e6, 500.0]
    other = RegionGrowing().segment(moved, NullObserver())
    a, b = seg.point_labels[perm], other.point_labels
    # the same partition up to renumbering, bar a few points on ties
    pairs = np.unique(np.stack([a, b], axis=1), axis=0, return_counts=True)
    majority = {}
    for (x, y), c in zip(*pairs):
        if c > majority.get(x, (0, 0))[1]:
            majority[x] = (y, c)
    agree = sum(c for _, c in majority.values()) / len(a)
    assert agree > 0.99
    assert angle_deg(found_up(other), found_up(seg)) < 0.05


def test_deterministic(toy, segmented):
    seg, _ = segmented
    again = RegionGrowing().segment(toy.points, NullObserver())
    assert np.array_equal(again.point_labels, seg.point_labels)
    assert np.array_equal(again.carrier, seg.carrier)
    np.testing.assert_array_equal(again.up_rotation, seg.up_rotation)


def test_full_resolution_and_voxel_agree(toy, segmented):
    seg, _ = segmented
    full = RegionGrowing.from_config({"voxel_m": 0}).segment(toy.points, NullObserver())
    assert angle_deg(found_up(full), toy.up) < 0.5
    s = score_segments(full, toy.labels, toy.points)
    assert s.facade_precision >= 0.95 and s.coverage >= 0.9
    both = (seg.point_labels >= 0) == (full.point_labels >= 0)
    assert both.mean() > 0.9


def test_voxel_labels_reach_every_point():
    toy = toy_street(seed=2, density=6.0)
    seg = RegionGrowing.from_config({"voxel_m": 0.5}).segment(toy.points, NullObserver())
    lev = seg.level(toy.points)
    assert len(seg.point_labels) == len(toy.points)
    s = score_segments(seg, toy.labels, toy.points)
    assert s.facade_precision >= 0.95 and s.coverage >= 0.8
    assert np.isfinite(lev).all()


def test_multiscale_vote_runs_and_is_stricter(toy, segmented):
    seg, _ = segmented
    multi = RegionGrowing.from_config({"multiscale_knn": [10, 20, 30], "multiscale_min_votes": 3}).segment(
        toy.points, NullObserver())
    assert (multi.point_labels >= 0).sum() <= (seg.point_labels >= 0).sum() * 1.02
    assert score_segments(multi, toy.labels, toy.points).facade_precision >= 0.95


def test_params_validation():
    with pytest.raises(ValidationError):
        RegionGrowing.from_config({"knn": 20, "radius": 3})
    with pytest.raises(ValidationError):
        RegionGrowing.from_config({"multiscale_knn": [10, 20], "multiscale_min_votes": 3})
    with pytest.raises(ValidationError):
        RegionGrowing.from_config({"facade_angle_deg": 95})
    p = RegionGrowing.Params()
    assert (p.knn, p.facade.angle_deg, p.facade.neighbour_fraction, p.ground_angle_deg, p.min_diameter_m) == (
        20, 75.0, 0.75, 15.0, 5.0)
    for name, field in RegionGrowing.Params.model_fields.items():
        assert field.description, name
    for group in nested_groups(RegionGrowing.Params).values():
        for name, field in group.model_fields.items():
            assert field.description and len(field.description) <= 120, name


def test_old_flat_keys_read_as_their_group():
    old = {"split_window_m": 2.0, "facade_angle_deg": 70, "multiscale_knn": [10, 20], "vertical_bin_deg": 3,
           "merge_gap_m": 1.5, "absorb_hops": 0, "boundary_max_points": 50, "smooth_angle_deg": 12}
    p = RegionGrowing.Params(**old)
    assert p == RegionGrowing.Params(
        split={"window_m": 2.0}, facade={"angle_deg": 70}, multiscale={"knn": [10, 20]}, vertical={"bin_deg": 3},
        merge={"gap_m": 1.5}, absorb={"hops": 0}, boundary={"max_points": 50}, growing={"smooth_angle_deg": 12})
    assert RegionGrowing.Params(split_bin_m=1.0, split={"window_m": 2.0}).split.model_dump() == {
        **SplitConfig().model_dump(), "window_m": 2.0, "bin_m": 1.0}
    # given both ways, the spelling given later wins (an override or a child recipe is later)
    assert RegionGrowing.Params(split_window_m=2.0, split={"window_m": 3.0}).split.window_m == 3.0
    assert RegionGrowing.Params(split={"window_m": 3.0}, split_window_m=2.0).split.window_m == 2.0
    with pytest.raises(ValidationError, match="split_windw_m"):  # a typo is rejected under its own name
        RegionGrowing.Params(split_windw_m=2.0)
    with pytest.raises(ValidationError, match=r"split\.window_m"):  # bounds are checked under the new key
        RegionGrowing.Params(split_window_m=-1.0)


def test_scene_entry_point(tmp_path, toy):
    root = tmp_path / "scene"
    (root / "street").mkdir(parents=True)
    write_ply(root / "street" / "cloud.ply", toy.points[::3])
    write_manifest(root, "toy", "EPSG:32617", {"street": {"cloud": "street/cloud.ply"}})
    assert RegionGrowing.scene_needs(RegionGrowing.Params()) == ("street_cloud",)
    scene = load_scene(root)
    seg = RegionGrowing()(scene, StreetCapture(scene), NullObserver())
    assert len(seg.point_labels) == len(toy.points[::3]) and len(seg) > 5


class RecordingObserver(NullObserver):
    def __init__(self):
        super().__init__()
        self.calls = []

    @property
    def wants_debug(self):
        return True

    def debug(self, name, value, it=None, timeline=None):
        self.calls.append((name, value))


def test_debug_payloads_only_when_wanted(toy):
    obs = RecordingObserver()
    RegionGrowing().segment(toy.points[::4], obs)
    kinds = {name: type(v) for name, v in obs.calls if not name.startswith("timings/")}
    assert kinds == {"raw": DebugPoints, "vertical": DebugLines, "facade": DebugPoints, "segments": DebugPoints}
    timings = {name: v for name, v in obs.calls if name.startswith("timings/")}
    assert list(timings) == [f"timings/{step}" for step in STEP_SHARES]  # every step, in order, once
    assert all(isinstance(v, DebugScalar) and v.value >= 0 for v in timings.values())
    seg = dict(obs.calls)["segments"]
    assert len(seg.class_ids) == len(seg.xyz)


# --- bad inputs ---------------------------------------------------------------------------------
def test_empty_cloud_is_an_error():
    with pytest.raises(StageError, match="no points"):
        RegionGrowing().segment(np.zeros((0, 3)), NullObserver())
    with pytest.raises(StageError, match=r"\(N,3\)"):
        RegionGrowing().segment(np.zeros((10, 2)), NullObserver())


def test_all_nan_is_an_error_and_some_nan_are_ignored():
    with pytest.raises(StageError, match="NaN"):
        RegionGrowing().segment(np.full((100, 3), np.nan), NullObserver())
    toy = toy_street(seed=3, density=6.0)
    pts = toy.points.copy()
    pts[::50] = np.nan
    pts[1::97, 2] = np.inf
    obs = NullObserver()
    seg = RegionGrowing().segment(pts, obs)
    bad = ~np.isfinite(pts).all(axis=1)
    assert any("NaN" in w for w in obs.warnings)
    assert (seg.point_labels[bad] == -2).all() and (seg.carrier[bad] == -1).all()
    assert np.isnan(seg.normals[bad]).all() and np.isfinite(seg.normals[~bad]).all()
    assert len(seg) > 5


def test_collinear_and_tiny_clouds_are_errors():
    t = np.linspace(0, 100, 5000)[:, None]
    with pytest.raises(StageError, match="line"):
        RegionGrowing().segment(np.hstack([t, 2 * t, -t]) + 7.0, NullObserver())
    with pytest.raises(StageError, match="knn"):
        RegionGrowing().segment(np.random.default_rng(0).normal(size=(15, 3)), NullObserver())


def test_no_vertical_structure_is_an_error():
    rng = np.random.default_rng(1)
    blob = rng.normal(size=(20000, 3)) * 10.0  # a volume: normals point everywhere
    with pytest.raises(StageError, match="no vertical structure"):
        RegionGrowing().segment(blob, NullObserver())


def test_ground_only_gives_empty_segments_with_warning():
    rng = np.random.default_rng(2)
    ground = np.c_[rng.uniform(0, 60, (20000, 2)), rng.normal(0, 0.02, 20000)]
    rot = toy_street(seed=0, density=1.0).rotation
    obs = NullObserver()
    seg = RegionGrowing().segment(ground @ rot.T + [1e5, 2e5, 30.0], obs)
    assert len(seg) == 0 and any("empty" in w for w in obs.warnings)
    assert (seg.point_labels >= -2).all() and (seg.point_labels < 0).all() and (seg.carrier == -1).all()
    assert seg.centroids.shape == (0, 2) and seg.boundary_xy == ()
    assert angle_deg(np.abs(found_up(seg)), np.abs(rot @ [0, 0, 1.0])) < 1.0


def test_stages_verbose_lists_groups_field_by_field(capsys):
    from toolkit.cli import main

    assert main(["stages", "-v"]) == 0
    lines = capsys.readouterr().out.splitlines()
    keys = {line.split()[0] for line in lines if line.startswith("    ")}
    assert {"split", "split.window_m", "vertical.min_support", "growing.graph_knn", "scale.max_deviation",
            "route_prior.window_m"} <= keys
    assert not any("Config(" in line for line in lines)  # no group printed as one repr
    window = next(line for line in lines if line.split()[:1] == ["split.window_m"])
    assert "= 0.0" in window and "façade top" in window
