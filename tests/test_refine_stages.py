"""refine.exhaustive and refine.icp on a small synthetic street with known per-segment transforms."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plugins.refine_exhaustive import Exhaustive
from plugins.refine_icp import IcpRefine
from tests.refine_warp_world import matches_for, world, write_scene
from toolkit.capture import StreetCapture
from toolkit.io.cloud import write_ply
from toolkit.observe import NullObserver
from toolkit.refine.transforms import apply
from toolkit.scene import load_scene, write_manifest


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    w = world()
    root = tmp_path_factory.mktemp("refine") / "scene"
    write_scene(w, root)
    H, W = w["dsm"].shape
    rows, cols = np.mgrid[0:H, 0:W]
    xy = w["grid"].pixel_to_world(rows.ravel(), cols.ravel())
    write_ply(root / "overview/cloud.ply", np.column_stack([xy, w["dsm"].ravel()]))
    write_manifest(root, "small", "EPSG:32617", {
        "overview": {"dsm": "overview/dsm.tif", "cloud": "overview/cloud.ply"},
        "street": {"cloud": "street/cloud.ply"}})
    return w, load_scene(root)


def _errors(w, tr):
    """Per segment: mean horizontal and mean vertical error of its points (input frame → scene)."""
    out = []
    for b in range(len(tr.T)):
        sel = w["carrier"] == b
        d = apply(tr.T[b], w["inp"][sel]) - w["truth"][sel]
        out.append((np.linalg.norm(d[:, :2], axis=1).mean(), np.abs(d[:, 2]).mean()))
    return np.array(out)


def test_exhaustive_recovers_every_segment_transform(small):
    w, scene = small
    tr = Exhaustive()(matches_for(w, dxy=2.5, dth_deg=6.0), w["street"], w["overview"], scene, StreetCapture(scene), NullObserver())
    assert tr.T.shape == (4, 4, 4) and tr.valid.all()
    err = _errors(w, tr)
    assert err[:, 0].max() < 0.05, err      # horizontal, metres
    assert err[:, 1].max() < 0.05, err      # vertical: tilt and height from the DSM
    assert np.allclose(tr.T[:, 3], [0, 0, 0, 1])
    assert np.all(tr.cost < 0.1) and np.all(tr.confidence > 0.9)


def _wrong_and_unmatched(w):
    m = matches_for(w, wrong=(2,))
    sm = m.segment_match.copy()
    sm[0] = -1
    return dataclasses.replace(m, segment_match=sm)


def test_exhaustive_rejects_a_wrong_match_and_skips_unmatched(small):
    w, scene = small
    obs = NullObserver()
    tr = Exhaustive.from_config({"propagate": False})(_wrong_and_unmatched(w), w["street"], w["overview"], scene, StreetCapture(scene), obs)
    assert tr.valid.tolist() == [False, True, False, True]
    assert tr.confidence[0] == 0 and tr.confidence[2] == 0
    assert any("inconsistent" in msg for msg in obs.warnings)
    assert _errors(w, tr)[[1, 3], 0].max() < 0.05


def test_exhaustive_propagates_to_unmatched_and_rejected_segments(small):
    w, scene = small
    obs = NullObserver()
    tr = Exhaustive()(_wrong_and_unmatched(w), w["street"], w["overview"], scene, StreetCapture(scene), obs)
    assert tr.valid.all()
    assert any("propagation" in msg for msg in obs.warnings)
    err = _errors(w, tr)
    assert err[:, 0].max() < 0.05 and err[:, 1].max() < 0.05, err
    assert tr.confidence[0] < tr.confidence[1]       # propagated segments are trusted less


def test_exhaustive_without_consistency_keeps_the_wrong_match(small):
    w, scene = small
    params = {"check_consistency": False, "propagate": False, "neighbour_passes": 0}
    tr = Exhaustive.from_config(params)(matches_for(w, wrong=(2,)), w["street"], w["overview"], scene, StreetCapture(scene), NullObserver())
    assert tr.valid[2]
    assert _errors(w, tr)[2, 0] > 10
    # the neighbour pass alone re-places it where its neighbours put it
    params["neighbour_passes"] = 1
    tr = Exhaustive.from_config(params)(matches_for(w, wrong=(2,)), w["street"], w["overview"], scene, StreetCapture(scene), NullObserver())
    assert _errors(w, tr)[2, 0] < 0.05


class _DebugObserver(NullObserver):
    def __init__(self):
        super().__init__()
        self.seen = []

    @property
    def wants_debug(self):
        return True

    def debug(self, name, value, it=None, timeline=None):
        self.seen.append(name)


def test_exhaustive_sends_debug_only_when_wanted(small):
    w, scene = small
    obs = _DebugObserver()
    Exhaustive()(matches_for(w), w["street"], w["overview"], scene, StreetCapture(scene), obs)
    assert "footprints_registered" in obs.seen


@pytest.mark.parametrize("target,tol_h", [("outline", 0.2), ("cloud", 0.25)])
def test_icp_refines_the_match(small, target, tol_h):
    w, scene = small
    m = matches_for(w, dxy=2.5, dth_deg=4.0)
    tr = IcpRefine.from_config({"target": target})(m, w["street"], w["overview"], scene, StreetCapture(scene), NullObserver())
    assert tr.valid.all()
    err = _errors(w, tr)
    assert err[:, 0].max() < tol_h, err
    assert err[:, 1].max() < 0.1, err


def test_icp_scene_needs():
    assert "overview_cloud" in IcpRefine.scene_needs(IcpRefine.Params(target="cloud"))
    assert IcpRefine.scene_needs(IcpRefine.Params()) == ("street_cloud",)


def test_exhaustive_gives_the_same_bytes_with_its_searches_in_a_forked_child(small, monkeypatch):
    from functools import partial

    import toolkit.refine.passes as refine_module
    from toolkit.forked import can_fork
    from toolkit.threads import thread_budget, thread_cap

    if thread_budget() < 2 or not can_fork():
        pytest.skip("needs two threads and fork")
    w, scene = small
    m = matches_for(w, dxy=2.5, dth_deg=6.0)
    with thread_cap(1):
        here = Exhaustive()(m, w["street"], w["overview"], scene, StreetCapture(scene), NullObserver())
    # four segments: below the usual minimum, so fork for any number of them
    monkeypatch.setattr(refine_module, "map_chunks_forked", partial(refine_module.map_chunks_forked, min_jobs=2))
    split = Exhaustive()(m, w["street"], w["overview"], scene, StreetCapture(scene), NullObserver())
    for a, b in ((here.T, split.T), (here.valid, split.valid), (here.cost, split.cost),
                 (here.confidence, split.confidence)):
        assert a.tobytes() == b.tobytes()


def test_exhaustive_reads_the_old_flat_keys_as_its_nested_groups():
    from pydantic import ValidationError

    flat = {"rotation_range_deg": 8, "shift_penalty": 0.01, "normal_max_angle_deg": 12, "max_tilt_deg": 4,
            "check_consistency": False, "neighbours_k": 5, "consistency_tol_m": 2, "consistency_tol_ratio": 0.1,
            "reject_groups": True, "route_window_m": 100, "joint_window_m": 160, "joint_kernel": "tricube",
            "joint_outline_points": 80, "joint_rotation_deg": 1, "joint_shift_m": 1.5, "joint_segment_points": 5}
    nested = {"search": {"rotation_range_deg": 8, "shift_penalty": 0.01},
              "ground": {"normal_max_angle_deg": 12, "max_tilt_deg": 4},
              "consistency": {"enabled": False, "k": 5, "tol_m": 2, "tol_ratio": 0.1, "groups": True,
                              "route_window_m": 100},
              "joint": {"window_m": 160, "kernel": "tricube", "outline_points": 80, "rotation_deg": 1,
                        "shift_m": 1.5, "segment_points": 5}}
    assert Exhaustive.Params(**flat) == Exhaustive.Params(**nested)
    assert Exhaustive.Params(**flat).search.rotation_step_deg == 1.0  # the group's other fields keep their defaults
    # given both ways, the later spelling wins
    assert Exhaustive.Params(joint_window_m=10, joint={"window_m": 20}).joint.window_m == 20
    assert Exhaustive.Params(joint={"window_m": 20}, joint_window_m=10).joint.window_m == 10
    with pytest.raises(ValidationError, match="rotation_range_deg"):
        Exhaustive.Params(rotation_range_deg=90)


def test_exhaustive_dotted_overrides_reach_the_nested_groups():
    from pathlib import Path

    from toolkit.recipe import load_recipe

    osm = Path(__file__).resolve().parents[1] / "recipes" / "osm.yaml"

    def params(*overrides: str):
        return Exhaustive.from_config(load_recipe(osm, overrides).step("refine").params).params

    base = params()   # the recipe's flat joint_* keys
    assert (base.joint.window_m, base.joint.kernel, base.joint.outline_points) == (160.0, "tricube", 80)
    nested = params("steps.refine.params.joint.shift_m=1.5", "steps.refine.params.search.truncate_m=2.5",
                    "steps.refine.params.consistency.tol_m=4")
    assert (nested.joint.shift_m, nested.joint.window_m, nested.search.truncate_m, nested.consistency.tol_m) == \
        (1.5, 160.0, 2.5, 4.0)
    assert params("steps.refine.params.joint_shift_m=1.5", "steps.refine.params.truncate_m=2.5",
                  "steps.refine.params.consistency_tol_m=4") == nested
    # an override in the other spelling than the recipe's wins (the recipe sets joint_window_m: 160)
    assert params("steps.refine.params.joint.window_m=200").joint.window_m == 200.0
    assert params("steps.refine.params.joint.window_m=200", "steps.refine.params.joint_window_m=120").joint.window_m == 120.0


def test_exhaustive_options_have_one_line_descriptions():
    from pydantic import BaseModel

    fields = dict(Exhaustive.Params.model_fields)
    for name, top in Exhaustive.Params.model_fields.items():
        if isinstance(top.annotation, type) and issubclass(top.annotation, BaseModel):
            fields.update({f"{name}.{key}": f for key, f in top.annotation.model_fields.items()})
    assert len(fields) == 14 + 7 + 7 + 7 + 7 + 4  # the top level (5 groups), search, ground, consistency, joint, scale
    for name, f in fields.items():
        assert f.description and "\n" not in f.description and len(f.description) <= 120, name


def test_icp_reads_the_old_flat_keys_as_its_nested_groups_with_one_line_descriptions():
    from pydantic import BaseModel

    flat = {"distances_m": (4.0, 2.0), "iterations": 5, "voxel_m": 0.5, "max_points": 500, "min_fitness": 0.5,
            "max_correction_m": 4, "max_correction_deg": 3, "normal_max_angle_deg": 12, "min_ground_points": 20,
            "check_consistency": False, "neighbours_k": 6, "consistency_tol_m": 2, "consistency_tol_ratio": 0.1}
    nested = {"icp": {"distances_m": (4.0, 2.0), "iterations": 5, "voxel_m": 0.5, "max_points": 500,
                      "min_fitness": 0.5, "max_correction_m": 4, "max_correction_deg": 3},
              "ground": {"normal_max_angle_deg": 12, "min_ground_points": 20},
              "consistency": {"enabled": False, "k": 6, "tol_m": 2, "tol_ratio": 0.1}}
    assert IcpRefine.Params(**flat) == IcpRefine.Params(**nested)
    assert IcpRefine.Params().consistency.route_window_m == 150.0  # the group's other fields keep their defaults
    fields = dict(IcpRefine.Params.model_fields)
    for name, top in IcpRefine.Params.model_fields.items():
        if isinstance(top.annotation, type) and issubclass(top.annotation, BaseModel):
            fields.update({f"{name}.{key}": f for key, f in top.annotation.model_fields.items()})
    assert len(fields) == 4 + 7 + 7 + 7  # the top level (3 groups), icp, ground, consistency
    for name, f in fields.items():
        assert f.description and "\n" not in f.description and len(f.description) <= 120, name
