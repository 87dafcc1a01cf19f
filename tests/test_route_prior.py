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
    assert placed.figures()["links_broken"] == 0


def test_a_window_placed_apart_from_its_neighbours_is_a_broken_link():
    """links_broken counts the links whose disagreement exceeds what the chain accepts there
    (agree_m + 5 % of the windows' distance): 20 m is within it at 125 m apart, 930 m is not."""
    cfg = RoutePriorConfig()
    centres = np.array([125.0, 250.0, 375.0, 625.0])
    links = np.array([20.0, 930.0, agree_m(cfg, 250.0) - 0.1])
    placed = RoutePlacement(None, (), centres, np.full(4, 0.6), links, 1.0, link_agree_m=agree_m(cfg, np.diff(centres)))
    assert agree_m(cfg, 125.0) > 20.0
    assert placed.figures()["links_broken"] == 1 and placed.figures()["links"] == 3


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
