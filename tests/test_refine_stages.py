"""refine.exhaustive and refine.icp on a small synthetic street with known per-segment transforms."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plugins.refine_exhaustive import Exhaustive
from plugins.refine_icp import IcpRefine
from tests.refine_warp_world import matches_for, world, write_scene
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
    tr = Exhaustive()(matches_for(w, dxy=2.5, dth_deg=6.0), w["street"], w["overview"], scene, NullObserver())
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
    tr = Exhaustive.from_config({"propagate": False})(_wrong_and_unmatched(w), w["street"], w["overview"], scene, obs)
    assert tr.valid.tolist() == [False, True, False, True]
    assert tr.confidence[0] == 0 and tr.confidence[2] == 0
    assert any("inconsistent" in msg for msg in obs.warnings)
    assert _errors(w, tr)[[1, 3], 0].max() < 0.05


def test_exhaustive_propagates_to_unmatched_and_rejected_segments(small):
    w, scene = small
    obs = NullObserver()
    tr = Exhaustive()(_wrong_and_unmatched(w), w["street"], w["overview"], scene, obs)
    assert tr.valid.all()
    assert any("propagation" in msg for msg in obs.warnings)
    err = _errors(w, tr)
    assert err[:, 0].max() < 0.05 and err[:, 1].max() < 0.05, err
    assert tr.confidence[0] < tr.confidence[1]       # propagated segments are trusted less


def test_exhaustive_without_consistency_keeps_the_wrong_match(small):
    w, scene = small
    params = {"check_consistency": False, "propagate": False, "neighbour_passes": 0}
    tr = Exhaustive.from_config(params)(matches_for(w, wrong=(2,)), w["street"], w["overview"], scene, NullObserver())
    assert tr.valid[2]
    assert _errors(w, tr)[2, 0] > 10
    # the neighbour pass alone re-places it where its neighbours put it
    params["neighbour_passes"] = 1
    tr = Exhaustive.from_config(params)(matches_for(w, wrong=(2,)), w["street"], w["overview"], scene, NullObserver())
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
    Exhaustive()(matches_for(w), w["street"], w["overview"], scene, obs)
    assert "footprints_registered" in obs.seen


@pytest.mark.parametrize("target,tol_h", [("outline", 0.2), ("cloud", 0.25)])
def test_icp_refines_the_match(small, target, tol_h):
    w, scene = small
    m = matches_for(w, dxy=2.5, dth_deg=4.0)
    tr = IcpRefine.from_config({"target": target})(m, w["street"], w["overview"], scene, NullObserver())
    assert tr.valid.all()
    err = _errors(w, tr)
    assert err[:, 0].max() < tol_h, err
    assert err[:, 1].max() < 0.1, err


def test_icp_scene_needs():
    assert "overview_cloud" in IcpRefine.scene_needs(IcpRefine.Params(target="cloud"))
    assert IcpRefine.scene_needs(IcpRefine.Params()) == ("street_cloud",)


def test_exhaustive_gives_the_same_bytes_with_its_searches_in_a_forked_child(small, monkeypatch):
    from functools import partial

    import plugins.refine_exhaustive as refine_module
    from toolkit.forked import can_fork
    from toolkit.threads import thread_budget, thread_cap

    if thread_budget() < 2 or not can_fork():
        pytest.skip("needs two threads and fork")
    w, scene = small
    m = matches_for(w, dxy=2.5, dth_deg=6.0)
    with thread_cap(1):
        here = Exhaustive()(m, w["street"], w["overview"], scene, NullObserver())
    # four segments: below the usual minimum, so fork for any number of them
    monkeypatch.setattr(refine_module, "map_chunks_forked", partial(refine_module.map_chunks_forked, min_jobs=2))
    split = Exhaustive()(m, w["street"], w["overview"], scene, NullObserver())
    for a, b in ((here.T, split.T), (here.valid, split.valid), (here.cost, split.cost),
                 (here.confidence, split.confidence)):
        assert a.tobytes() == b.tobytes()
