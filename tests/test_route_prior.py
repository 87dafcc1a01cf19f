"""toolkit.matching.route_prior: the route placed by its façades alone (the no-GPS prior)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.conftest import synthetic_scene
from toolkit.capture import StreetCapture
from toolkit.matching.route_prior import RoutePlacement, RoutePriorConfig, agree_m, capture_order, place_route
from toolkit.observe import NullObserver
from toolkit.registry import Registry
from toolkit.scene import load_array, load_scene, load_sparse


@pytest.fixture(scope="module")
def tiny():
    scene = load_scene(synthetic_scene("tiny"))
    reg, obs = Registry(), NullObserver()
    street = reg.get("street.region_growing").from_config({})(scene, StreetCapture(scene), obs)
    overviews = {key: reg.get(key).from_config({})(scene, obs) for key in ("overview.osm", "overview.dsm_tophat")}
    return scene, street, overviews


def _true_centres(scene, street) -> np.ndarray:
    """True scene x, y of each street segment's levelled centroid (its façade points' true mean
    shifted by the centroid's offset from their levelled mean, which a rigid placement keeps)."""
    truth = load_array(scene, "truth_street_points")[:, :2]
    out = np.full((len(street), 2), np.nan)
    for i in range(len(street)):
        on = street.point_labels == i
        if on.sum() > 20:
            out[i] = truth[on].mean(axis=0)
    return out


def test_capture_order_compares_numbers_as_numbers():
    assert capture_order(["f_10.jpg", "f_9.jpg", "f_100.jpg", "a.jpg"]).tolist() == [3, 1, 0, 2]


@pytest.mark.parametrize("source", ["overview.osm", "overview.dsm_tophat"])
def test_the_route_is_placed_within_metres_of_the_truth(tiny, source):
    scene, street, overviews = tiny
    model = load_sparse(scene)
    cams = street.level(model.centres[capture_order(model.image_names)])[:, :2]
    placed = place_route(street, overviews[source], cams, RoutePriorConfig())
    assert placed.prior is not None, placed.reason
    err = np.linalg.norm(placed.prior.position - _true_centres(scene, street), axis=1)
    # the centroid is the mean of the façade cells, the truth the mean of all façade points: a few metres
    assert np.nanmedian(err) < 4.0
    assert placed.window_scores.min() > RoutePriorConfig().min_score
    assert placed.figures()["links_broken"] == 0 and placed.figures()["overruled_share"] == 0.0


def test_a_window_placed_apart_from_its_neighbours_is_a_broken_link():
    """links_broken counts the links whose disagreement exceeds what the chain accepts there
    (agree_m + 5 % of the windows' distance): 20 m is within it at 125 m apart, 930 m is not."""
    cfg = RoutePriorConfig()
    centres = np.array([125.0, 250.0, 375.0, 625.0])
    links = np.array([20.0, 930.0, agree_m(cfg, 250.0) - 0.1])
    placed = RoutePlacement(None, (), centres, np.full(4, 0.6), links, 1.0, link_agree_m=agree_m(cfg, np.diff(centres)))
    assert agree_m(cfg, 125.0) > 20.0
    assert placed.figures()["links_broken"] == 1 and placed.figures()["links"] == 3


def test_a_window_whose_facades_fit_best_elsewhere_is_overruled():
    """alone_m: how far a window's best placement alone (its first, best-scoring candidate) puts its
    cameras from the chosen one; beyond agree_m the chain has overruled the window's own façades."""
    from toolkit.matching.route_prior import Placement, _alone_m

    cams = np.stack([np.linspace(0.0, 500.0, 101), np.zeros(101)], axis=1)
    arc = np.linspace(0.0, 500.0, 101)
    here = Placement(theta=0.0, t=np.zeros(2), pivot=np.zeros(2), score=0.7)
    away = Placement(theta=0.0, t=np.array([0.0, 40.0]), pivot=np.zeros(2), score=0.6)
    windows = [[here, away], [away, here]]   # best first: window 1's own façades prefer 40 m away
    alone = _alone_m(windows, (here, here), cams, arc, np.array([125.0, 250.0]), 250.0)
    assert alone == pytest.approx([0.0, 40.0])
    placed = RoutePlacement(None, (here, here), np.array([125.0, 250.0]), np.array([0.7, 0.6]), np.array([0.0]),
                            0.5, alone_m=alone, overruled_m=RoutePriorConfig().agree_m)
    assert placed.figures()["overruled_share"] == 0.5 and placed.figures()["alone_max_m"] == 40.0


def test_a_street_from_elsewhere_is_not_placed(tiny):
    """Façades that match no outline (the street frame's points mirrored) give no prior: the data term
    then searches every pair, as before the placement existed."""
    scene, street, overviews = tiny
    mirrored = dataclasses.replace(street, boundary_xy=tuple(xy * [1.0, -1.0] * 1.7 for xy in street.boundary_xy))
    model = load_sparse(scene)
    cams = street.level(model.centres[capture_order(model.image_names)])[:, :2] * [1.0, -1.0] * 1.7
    placed = place_route(mirrored, overviews["overview.osm"], cams, RoutePriorConfig())
    assert placed.prior is None and "score" in placed.reason


def test_the_unary_stage_uses_the_placement_without_gps(tiny):
    scene, street, overviews = tiny
    no_gps = dataclasses.replace(scene, files=dataclasses.replace(scene.files, gps=None))
    reg, obs = Registry(), NullObserver()
    graphs = reg.get("graph.knn").from_config({})(street, overviews["overview.osm"], obs)
    unary = reg.get("unary.distance_map")
    placed = unary.from_config({})(graphs, street, overviews["overview.osm"], no_gps, StreetCapture(no_gps), obs)
    full = unary.from_config({"route_prior": {"enabled": False}})(graphs, street, overviews["overview.osm"],
                                                                 no_gps, StreetCapture(no_gps), obs)
    assert not any("route placement not used" in w for w in obs.warnings)
    kept, searched = np.isfinite(placed.cost[:, :-1]).sum(), np.isfinite(full.cost[:, :-1]).sum()
    assert 0 < kept < searched / 3  # the placement prunes most pairs


def test_with_a_gps_track_the_chain_takes_the_placement_near_the_fixes():
    """Two windows, each with a better-scoring placement 40 m off the fixes' track and a slightly worse
    one on it: alone the chain takes the better scores; with the track it takes the placements on it."""
    from toolkit.matching.route_prior import Placement, _chain, _WindowAnchor

    cfg = RoutePriorConfig()
    cams = [np.array([[0.0, 0.0], [50.0, 0.0]]), np.array([[100.0, 0.0], [150.0, 0.0]])]
    windows, anchors = [], []
    for c in cams:
        pivot = c.mean(axis=0)
        on = Placement(theta=0.0, t=pivot.copy(), pivot=pivot, score=0.60)
        off = Placement(theta=0.0, t=pivot + [0.0, 40.0], pivot=pivot, score=0.70)
        windows.append([off, on])
        anchors.append(_WindowAnchor(c, c.copy()))
    links = [np.array([[75.0, 0.0]])]
    alone, _ = _chain(windows, links, cfg, np.array([100.0]))
    near, _ = _chain(windows, links, cfg, np.array([100.0]), anchors=anchors, gps_tolerance_m=5.0)
    assert alone == [0, 0] and near == [1, 1]
    fit = anchors[0].placement(cams[0].mean(axis=0))
    assert anchors[0].distance(fit) < 1e-9


def test_a_segment_placed_far_from_its_gps_position_keeps_the_gps_prior():
    from toolkit.matching.data_term import gated_prior
    from toolkit.matching.gps import GpsConfig, GpsPrior

    fixes = GpsPrior(position=np.array([[0.0, 0.0], [100.0, 0.0]]), angle=np.zeros(2), n_fixes=50, sigma_m=5.0,
                     fit_rms_m=np.array([5.0, 5.0]))
    route = GpsPrior(position=np.array([[3.0, 0.0], [130.0, 0.0]]), angle=np.array([0.1, 0.2]), n_fixes=3,
                     sigma_m=3.0, fit_rms_m=np.zeros(2))
    placed = RoutePlacement(route, (), np.array([125.0]), np.array([0.6]), np.zeros(0), 1.0)
    out = gated_prior(fixes, placed, 2, GpsConfig(), agree_m=10.0)
    assert np.allclose(out.prior.position, [[3.0, 0.0], [100.0, 0.0]]) and np.allclose(out.prior.angle, [0.1, 0.0])
    assert out.radius_m[0] < out.radius_m[1] and out.figures["gated_share"] == 0.5
    # fixes as tight as the placement (σ 3 m: the same radius) keep their own prior
    tight = dataclasses.replace(fixes, sigma_m=3.0, fit_rms_m=np.zeros(2))
    assert gated_prior(tight, placed, 2, GpsConfig(), agree_m=10.0).figures["gated_share"] == 0.0


def test_the_placement_runs_with_gps_only_where_it_could_be_the_tighter_prior():
    from toolkit.matching.data_term import _may_tighten
    from toolkit.matching.gps import GpsConfig, GpsPrior

    def fixes(sigma_m, rms_m):
        return GpsPrior(position=np.zeros((2, 2)), angle=np.zeros(2), n_fixes=50, sigma_m=sigma_m,
                        fit_rms_m=np.array([0.0, rms_m]))

    cfg = RoutePriorConfig()
    assert not _may_tighten(fixes(3.0, 1.0), cfg, GpsConfig())     # σ 3 m fixes: radius 20 m, as the placement's
    assert _may_tighten(fixes(3.0, 8.0), cfg, GpsConfig())         # one segment's fit 8 m off: 29 m
    assert _may_tighten(fixes(5.0, 0.0), cfg, GpsConfig())         # σ 5 m: 30 m
    assert not _may_tighten(fixes(5.0, 0.0), cfg, GpsConfig(radius_m=20.0))  # one radius for both


def _direct_score(fine, pts, theta, t, pivot) -> float:
    """Mean closeness of the points placed at (theta, t), 0 off the map: what _refine scores."""
    c, s = np.cos(theta), np.sin(theta)
    ij = np.floor(((pts - pivot) @ np.array([[c, s], [-s, c]]) + t - fine.corner) / fine.cell_m).astype(int)
    H, W = fine.close.shape
    on = (ij[:, 0] >= 0) & (ij[:, 0] < H) & (ij[:, 1] >= 0) & (ij[:, 1] < W)
    return float(np.where(on, fine.close[np.clip(ij[:, 0], 0, H - 1), np.clip(ij[:, 1], 0, W - 1)], 0.0).mean())


@pytest.mark.parametrize("corner_m", [(0.0, 0.0), (-20.0, -15.0)])   # on the map; hanging off its corner
def test_the_fine_rescoring_finds_the_best_pose_around_a_coarse_one(corner_m):
    from toolkit.matching.route_prior import OutlineMap, Placement, _refine

    rng = np.random.default_rng(7)
    close = rng.random((60, 50)).astype(np.float32)
    fine = OutlineMap(corner=np.array(corner_m), cell_m=1.0, close=close)
    pts = rng.uniform(5.0, 40.0, (200, 2))
    pivot = pts.mean(axis=0)
    cfg = RoutePriorConfig()
    coarse = Placement(theta=0.02, t=pivot + 0.3, pivot=pivot, score=0.0)
    (got,) = _refine(fine, pts, [coarse], cfg)
    # every pose the search covers: 5 rotations within half a rotation step, whole-cell shifts within a coarse cell
    poses = [(coarse.theta + d, coarse.t + np.array([u, v]))
             for d in np.deg2rad(np.arange(-1.0, 1.01, 0.5) * cfg.rotation_step_deg / 2)
             for u in np.arange(-cfg.cell_m, cfg.cell_m + 1e-9) for v in np.arange(-cfg.cell_m, cfg.cell_m + 1e-9)]
    best = max(_direct_score(fine, pts, a, t, pivot) for a, t in poses)
    assert got.score == pytest.approx(_direct_score(fine, pts, got.theta, got.t, pivot), abs=1e-6)
    assert got.score == pytest.approx(best, abs=1e-6)


def test_windows_searched_near_their_rotation_place_the_route_as_every_rotation_does(tiny):
    from toolkit.matching.route_scale import near_rotations

    scene, street, overviews = tiny
    model = load_sparse(scene)
    cams = street.level(model.centres[capture_order(model.image_names)])[:, :2]
    cfg = RoutePriorConfig()
    full = place_route(street, overviews["overview.osm"], cams, cfg)
    near = near_rotations(full, 1.0, cfg.window_m, cfg.rotation_step_deg, 15.0)
    assert len(near) == len(full.windows) and all(9 <= len(v) <= 11 for v in near.values())   # 3° steps within 15°
    again = place_route(street, overviews["overview.osm"], cams, cfg, rotations=near)
    assert [p.theta for p in again.windows] == [p.theta for p in full.windows]
    assert np.allclose([p.t for p in again.windows], [p.t for p in full.windows])
    # the windows turned half a turn search only rotations that cannot place them
    away = {k: (v + np.pi) % (2 * np.pi) for k, v in near.items()}
    turned = place_route(street, overviews["overview.osm"], cams, cfg, rotations=away)
    assert all(abs((p.theta - q.theta + np.pi) % (2 * np.pi) - np.pi) > np.deg2rad(90)
               for p, q in zip(turned.windows, full.windows))
