"""unary.distance_map: the data term on hand-built blocks with known answers (METHOD.md §4)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest
from pydantic import ValidationError

from plugins.graph_knn import KnnGraph
from plugins.unary_distance_map import DistanceMap
from toolkit.capture import StreetCapture
from toolkit.errors import StageError
from toolkit.testing.matching_toy import make_toy, overview_from_labels, street_from_boundaries
from toolkit.observe import DebugPoints2D, DebugText, NullObserver
from toolkit.types import ConjugateGraphs, Grid


@dataclass
class RecordingObserver(NullObserver):
    records: dict = field(default_factory=dict)

    @property
    def wants_debug(self) -> bool:
        return True

    def debug(self, name, value, it=None, timeline=None):
        self.records[name] = value


def _rot(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def true_labels(graphs: ConjugateGraphs, truth: np.ndarray) -> np.ndarray:
    """Label of each street edge mapping both ends to their true segments (-1: none exists)."""
    index = {tuple(p): i for i, p in enumerate(graphs.label_pairs.tolist())}
    return np.array([index.get((int(truth[j]), int(truth[k])), -1) for j, k in graphs.street_edges])


@pytest.fixture(scope="module")
def toy():
    return make_toy((3, 3), seed=3)


@pytest.fixture(scope="module")
def cameras(toy, tmp_path_factory):
    """The toy's scene folder with street cameras (free-space term) and no GPS."""
    return _scene(tmp_path_factory.mktemp("cameras"), toy, gps=False)


@pytest.fixture(scope="module")
def solved(toy, cameras):
    graphs = KnnGraph()(toy.street, toy.overview, NullObserver())
    # the exhaustive data term (no route placement), which the GPS tests below are compared with
    full = DistanceMap(DistanceMap.Params(route_prior={"enabled": False}))
    return graphs, full(graphs, toy.street, toy.overview, cameras, StreetCapture(cameras), NullObserver())


def test_costs_follow_the_contract(solved):
    graphs, costs = solved
    E, L = graphs.n_nodes, graphs.n_labels
    assert costs.cost.shape == (E, L) and costs.theta_rad.shape == (E, L - 1) and costs.t.shape == (E, L - 1, 2)
    assert (costs.cost[:, -1] == 1).all()
    finite = np.isfinite(costs.cost)
    assert (costs.cost[finite] >= 0).all() and (costs.cost[finite] <= 1).all()
    assert np.isposinf(costs.cost[~finite]).all()
    scored = finite[:, :-1]
    assert np.isfinite(costs.theta_rad[scored]).all() and np.isfinite(costs.t[scored]).all()
    assert np.isnan(costs.theta_rad[~scored]).all()
    assert 0.05 < scored.mean() < 1.0  # length/extent pruning removes some, not all


def test_true_labels_score_low_and_their_transform_is_right(toy, solved):
    graphs, costs = solved
    lab = true_labels(graphs, toy.truth)
    e = np.nonzero(lab >= 0)[0]
    assert len(e) > 50
    c = costs.cost[e, lab[e]]
    assert np.isfinite(c).all(), "a true label was pruned"
    assert np.mean(c < 0.25) >= 0.9
    # straight façades fit many outlines, so the data term alone ranks the truth near the top,
    # not always first (the smoothness term settles it): within the best 10 % of each edge's list
    rank = (costs.cost[e, :-1] < c[:, None]).sum(axis=1)
    assert np.mean(rank < 0.1 * np.isfinite(costs.cost[e, :-1]).sum(axis=1)) >= 0.8
    # T̂ puts both segment centres where the true transform does (two façades of one rectangular
    # building also fit it turned by 180°: only neighbouring labels tell, so those are left out)
    e = e[graphs.label_pairs[lab[e], 0] != graphs.label_pairs[lab[e], 1]]
    th, t = costs.theta_rad[e, lab[e]], costs.t[e, lab[e]]
    dth = np.abs(np.mod(th - toy.theta + np.pi, 2 * np.pi) - np.pi)
    assert np.mean(dth < np.deg2rad(2)) >= 0.9
    for side in (0, 1):
        x = toy.street.centroids[graphs.street_edges[e, side]]
        placed = np.einsum("eij,ej->ei", np.stack([_rot(a) for a in th]), x) + t
        truth = x @ _rot(toy.theta).T + toy.t
        err = np.linalg.norm(placed - truth, axis=1)
        # façades on collinear walls may slide along them at equal cost: allow a few larger errors
        assert np.median(err) < 0.75 and np.mean(err < 1.5) >= 0.85


def test_label_orders_are_symmetric(toy, solved, cameras):
    """Listing the street segments in reverse flips every street edge; the same physical
    assignment then sits under the other order of the same over-view edge (2f ↔ 2f+1)."""
    graphs, costs = solved
    S = len(toy.street)
    rev = street_from_boundaries(list(toy.street.boundary_xy[::-1]))
    g2 = KnnGraph()(rev, toy.overview, NullObserver())
    c2 = DistanceMap(DistanceMap.Params(route_prior={"enabled": False}))(g2, rev, toy.overview, cameras,
                                                                         StreetCapture(cameras), NullObserver())
    where = {tuple(e): i for i, e in enumerate(g2.street_edges.tolist())}
    diffs = []
    for e, (j, k) in enumerate(graphs.street_edges):
        e2 = where[(S - 1 - k, S - 1 - j)]
        swapped = c2.cost[e2, :-1].reshape(-1, 2)[:, ::-1].ravel()
        a = costs.cost[e, :-1]
        assert np.array_equal(np.isfinite(a), np.isfinite(swapped))
        ok = np.isfinite(a)
        diffs.append(np.abs(a[ok] - swapped[ok]))
    d = np.concatenate(diffs)
    assert np.mean(d < 1e-9) > 0.99 and d.max() < 0.1


def _one_building(same_segment_labels: bool):
    grid = Grid((0.5, 0.0, 500_000.0, 0.0, -0.5, 4_400_100.0), 200, 200, "EPSG:32617")
    label = np.full((200, 200), -1, np.int32)
    label[60:140, 50:150] = 0                       # 50 m × 40 m
    overview = overview_from_labels(label, grid)
    corners = grid.pixel_to_world(np.array([60, 60, 139, 139]) - 0.0, np.array([50, 149, 149, 50]))
    rng = np.random.default_rng(0)
    walls = []
    for a, b in ((0, 1), (1, 2), (2, 3)):  # three façades seen from the street
        u = rng.uniform(0.1, 0.9, 300)[:, None]
        walls.append(corners[a] + u * (corners[b] - corners[a]) + rng.normal(0, 0.05, (300, 2)))
    theta, t = 0.7, np.array([500_050.0, 4_400_050.0])
    street = street_from_boundaries([(w - t) @ _rot(theta) for w in walls])  # x = R⁻¹(w - t)
    graphs = KnnGraph(KnnGraph.Params(same_segment_labels=same_segment_labels))(street, overview, NullObserver())
    return graphs, street, overview, theta


def test_one_building_is_matched_through_the_same_segment_label():
    graphs, street, overview, theta = _one_building(True)
    assert graphs.n_labels == 3 and (graphs.label_pairs == 0).all()
    costs = DistanceMap()(graphs, street, overview, None, None, NullObserver())
    assert np.isfinite(costs.cost).all() and (costs.cost[:, :2] < 0.2).all()
    assert np.array_equal(costs.cost[:, 0], costs.cost[:, 1])   # 2f and 2f+1 coincide for (p, p)
    # right up to the rectangle's half-turn symmetry, which only the other edges can settle
    dth = np.mod(costs.theta_rad - theta + np.pi / 2, np.pi) - np.pi / 2
    assert np.abs(dth).max() < np.deg2rad(2)


def test_one_building_without_same_segment_labels_leaves_only_null():
    graphs, street, overview, _ = _one_building(False)
    assert graphs.n_labels == 1
    costs = DistanceMap()(graphs, street, overview, None, None, NullObserver())
    assert costs.cost.shape == (graphs.n_nodes, 1) and (costs.cost == 1).all()


def test_nothing_in_common_scores_high(toy, solved):
    """Zig-zag walls that no building outline explains: every candidate stays far from the truth's
    costs (the matching scene's best candidates are near 0)."""
    rng = np.random.default_rng(5)
    walls = []
    for _ in range(12):
        c = rng.uniform(0, 250, 2) + [500_000.0, 4_400_000.0]
        s = np.linspace(0, 20, 200)
        walls.append(c + np.stack([s, 2.5 * np.sin(1.3 * s)], axis=1))
    street = street_from_boundaries(walls)
    graphs = KnnGraph()(street, toy.overview, NullObserver())
    costs = DistanceMap()(graphs, street, toy.overview, None, None, NullObserver())
    best_foreign = np.min(costs.cost, axis=1)
    best_true = np.min(solved[1].cost, axis=1)
    assert np.median(best_true) < 0.15
    assert best_foreign.min() > 0.3


def _scene(root, toy, gps: bool = True, n_fixes: int | None = None):
    """A scene folder holding what the data term may read: street/sparse (cameras in the street,
    one per façade) and optionally street/gps.csv (their true positions + 2 m noise, σ = 3 m)."""
    from pyproj import Transformer

    from toolkit.io.colmap import write_model
    from toolkit.scene import load_scene, write_manifest
    from toolkit.types import Camera, SparseModel

    (root / "street").mkdir(parents=True)
    cams = toy.cameras
    n = len(cams)
    centres = np.column_stack([cams, np.full(n, 2.0)])
    names = tuple(f"img{i:04d}.jpg" for i in range(n))
    model = SparseModel(
        cameras={1: Camera(1, "PINHOLE", 640, 480, np.array([500.0, 500, 320, 240]))}, image_names=names,
        image_ids=np.arange(1, n + 1), camera_ids=np.ones(n, np.int64), R=np.stack([np.eye(3)] * n),
        t=-centres, points3d_ids=np.array([1]), points3d=np.zeros((1, 3)),
        points3d_rgb=np.zeros((1, 3), np.uint8),
        # every image observes the point: the text reader rejects a last image without observations
        observations=np.column_stack([np.arange(n), np.zeros(n), np.full(n, 320.0), np.full(n, 240.0)]))
    write_model(model, root / "street/sparse")
    entries = {"street": {"sparse": "street/sparse"}}
    if gps:
        m = n if n_fixes is None else n_fixes
        world = cams[:m] @ _rot(toy.theta).T + toy.t + np.random.default_rng(1).normal(0, 2.0, (m, 2))
        to_lonlat = Transformer.from_crs("EPSG:32617", "EPSG:4326", always_xy=True)
        lon, lat = to_lonlat.transform(world[:, 0], world[:, 1])
        lines = ["image_name,lon,lat,sigma_m"] + [f"{a},{b:.9f},{c:.9f},3.0" for a, b, c in zip(names, lon, lat)]
        (root / "street/gps.csv").write_text("\n".join(lines) + "\n")
        entries["street"]["gps"] = "street/gps.csv"
    write_manifest(root, "toy", "EPSG:32617", entries)
    return load_scene(root)


def test_gps_prunes_candidates_but_keeps_the_true_ones(tmp_path, toy, solved):
    graphs, costs = solved
    scene = _scene(tmp_path / "gps", toy)
    with_gps = DistanceMap(DistanceMap.Params(gps_radius_m=30))(graphs, toy.street, toy.overview, scene,
                                                                 StreetCapture(scene), NullObserver())
    n_without = np.isfinite(costs.cost[:, :-1]).sum()
    n_with = np.isfinite(with_gps.cost[:, :-1]).sum()
    assert n_with < 0.3 * n_without
    lab = true_labels(graphs, toy.truth)
    e = np.nonzero(lab >= 0)[0]
    assert np.mean(np.isfinite(with_gps.cost[e, lab[e]])) >= 0.95


def test_gps_pruned_candidates_are_infinite_and_survivors_obey_the_prior(tmp_path, toy, solved):
    """Every finite candidate puts both street centres within the GPS radius of their GPS-implied
    positions and turns within gps_angle_deg of the GPS heading: a candidate failing the final pose
    test is +inf, not clipped to 1 (a tie with null that winner-takes-all would pick)."""
    from toolkit.matching.gps import gps_prior

    graphs, _ = solved
    scene = _scene(tmp_path / "gps", toy)
    params = DistanceMap.Params(gps_radius_m=15, route_prior={"with_gps": False})  # the fixes' prior alone
    costs = DistanceMap(params)(graphs, toy.street, toy.overview, scene, StreetCapture(scene), NullObserver())
    prior = gps_prior(StreetCapture(scene), toy.street)
    e, lab = np.nonzero(np.isfinite(costs.cost[:, :-1]))
    assert len(e) > 0
    th, t = costs.theta_rad[e, lab], costs.t[e, lab]
    for side in (0, 1):
        seg = graphs.street_edges[e, side]
        x = toy.street.centroids[seg]
        placed = np.einsum("nij,nj->ni", np.stack([np.stack([np.cos(th), -np.sin(th)], 1),
                                                   np.stack([np.sin(th), np.cos(th)], 1)], 1), x) + t
        assert np.linalg.norm(placed - prior.position[seg], axis=1).max() <= 15 + 1e-6
        turn = np.abs((th - prior.angle[seg] + np.pi) % (2 * np.pi) - np.pi)
        assert np.degrees(turn).max() <= params.gps.angle_deg + 1e-6


def test_gps_heading_orients_same_segment_labels(tmp_path, toy, solved):
    """A (p, p) label (two façades of one building) has no over-view centre line; with GPS its pose
    search is centred on the GPS heading, so a rectangular outline cannot be fitted turned by 90°
    or 180°: the true self-loop labels get the true rotation and a low cost."""
    graphs, _ = solved
    scene = _scene(tmp_path / "gps", toy)
    costs = DistanceMap()(graphs, toy.street, toy.overview, scene, StreetCapture(scene), NullObserver())
    lab = true_labels(graphs, toy.truth)
    j, k = graphs.street_edges[:, 0], graphs.street_edges[:, 1]
    e = np.nonzero((lab >= 0) & (toy.truth[j] == toy.truth[k]))[0]
    assert len(e) >= 3, "precondition: the toy has street edges between façades of one building"
    turn = np.degrees(np.abs((costs.theta_rad[e, lab[e]] - toy.theta + np.pi) % (2 * np.pi) - np.pi))
    assert np.all(turn < 5.0)
    assert np.median(costs.cost[e, lab[e]]) < 0.5


def test_gps_radius_widens_where_the_local_fit_residual_is_large(tmp_path, toy):
    """Fixes that no rigid motion explains (here: every other fix shifted 30 m, as biased fixes or
    a bent SfM frame would be) give a large local-fit residual; the radius grows to
    gps_radius_fit_sigmas residuals (+ margin) there, and stays gps_radius_sigmas·σ + margin when that
    is off. Consistent fixes (2 m noise,
    σ = 3 m) leave the σ-based radius."""
    import dataclasses

    from toolkit.matching.gps import gps_prior, prior_radii

    clean = gps_prior(StreetCapture(_scene(tmp_path / "clean", toy)), toy.street)
    assert clean.fit_rms_m is not None and clean.fit_rms_m.shape == (len(toy.street),)
    assert np.all(3.0 * clean.fit_rms_m < 5.0 * 3.0)
    stage, fixed = DistanceMap(), DistanceMap(DistanceMap.Params(gps_radius_fit_sigmas=None))
    base = 5.0 * 3.0 + 5.0
    assert np.allclose(prior_radii(clean, len(toy.street), stage.params.gps), base)

    scene = _scene(tmp_path / "bent", toy)
    lines = scene.files.gps.read_text().splitlines()
    rows = [ln.split(",") for ln in lines[1:]]
    for r in rows[::2]:
        r[2] = f"{float(r[2]) + 30.0 / 111_000:.9f}"  # 30 m north
    scene.files.gps.write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")
    bent = gps_prior(StreetCapture(scene), toy.street)
    assert np.all(bent.fit_rms_m > 10.0)
    radii = prior_radii(bent, len(toy.street), stage.params.gps)
    assert np.allclose(radii, 3.0 * bent.fit_rms_m + 5.0) and np.all(radii > base + 9.0)
    assert np.allclose(prior_radii(bent, len(toy.street), fixed.params.gps), base)
    explicit = DistanceMap(DistanceMap.Params(gps_radius_m=12.0))
    assert np.allclose(prior_radii(dataclasses.replace(bent), len(toy.street), explicit.params.gps), 12.0)


def test_gps_with_too_few_fixes_warns_and_falls_back_to_the_route_placement(tmp_path):
    small = make_toy((2, 2), seed=4)
    graphs = KnnGraph()(small.street, small.overview, NullObserver())
    cams = _scene(tmp_path / "cams", small, gps=False)
    without = DistanceMap()(graphs, small.street, small.overview, cams, StreetCapture(cams), NullObserver())
    obs = NullObserver()
    few = _scene(tmp_path / "gps2", small, n_fixes=2)
    out = DistanceMap()(graphs, small.street, small.overview, few, StreetCapture(few), obs)
    assert any("GPS pruning off" in w for w in obs.warnings)
    assert np.array_equal(np.isfinite(out.cost), np.isfinite(without.cost))


@pytest.mark.parametrize("params", [{"directional": True}, {"search": "window"}])
def test_other_modes_find_the_true_labels(params):
    toy = make_toy((2, 2), seed=4)
    graphs = KnnGraph()(toy.street, toy.overview, NullObserver())
    # raw costs (no rescaling): the directional term raises every cost
    stage = DistanceMap(DistanceMap.Params(raw_cost_at_null=1.0, **params))
    costs = stage(graphs, toy.street, toy.overview, None, None, NullObserver())
    lab = true_labels(graphs, toy.truth)
    e = np.nonzero(lab >= 0)[0]
    c = costs.cost[e, lab[e]]
    scored = costs.cost[:, :-1][np.isfinite(costs.cost[:, :-1])]
    assert np.median(c) < 0.5 * np.median(scored)
    rank = (costs.cost[e, :-1] < c[:, None]).sum(axis=1)
    assert np.mean(rank < 0.1 * np.isfinite(costs.cost[e, :-1]).sum(axis=1)) >= 0.75


def test_inconsistent_graph_is_a_stage_error(toy, solved):
    graphs, _ = solved
    bad = ConjugateGraphs(graphs.street_graph, graphs.overview_graph, graphs.street_edges + len(toy.street),
                          graphs.overview_edges, graphs.label_pairs, graphs.conj_edges, graphs.conj_shared,
                          graphs.conjugate_graph)
    with pytest.raises(StageError, match="street segment"):
        DistanceMap()(bad, toy.street, toy.overview, None, None, NullObserver())


def test_params_are_validated():
    with pytest.raises(ValidationError):
        DistanceMap.Params(truncate_px=0)
    with pytest.raises(ValidationError):
        DistanceMap.Params(search="grid")
    with pytest.raises(ValidationError):
        DistanceMap.Params(trunc_px=5)


def test_old_flat_keys_are_read_as_the_nested_keys():
    from toolkit.matching.config import MatchingConfig

    groups = {name: f.annotation for name, f in DistanceMap.Params.model_fields.items()
              if isinstance(f.annotation, type) and issubclass(f.annotation, MatchingConfig)}
    assert set(groups) == {"pose", "chamfer", "anchor", "prune", "gps", "free_space"}
    n_keys = 0
    for group, cls in groups.items():
        for key, name in cls.flat_keys().items():
            default = getattr(getattr(DistanceMap.Params(), group), name)
            # another valid value: the other boolean, half a number, 7 for an unset one
            value = (not default) if isinstance(default, bool) else 7.0 if default is None else type(default)(default / 2)
            flat = DistanceMap.Params(**{key: value})
            assert getattr(getattr(flat, group), name) == value, key
            assert flat == DistanceMap.Params(**{group: {name: value}}), key
            n_keys += 1
    assert n_keys == 32  # every flat key of the groups (the other five stayed at the top)
    p = DistanceMap.Params(gps_radius_m=12.0, anchor_spacing_m=2.0, free_space_weight=0.2, refine_top_k=3)
    assert (p.gps.radius_m, p.anchor.spacing_m, p.free_space.weight, p.pose.refine_top_k) == (12.0, 2.0, 0.2, 3)
    assert p.gps.angle_deg == 45.0  # the group's other fields keep their defaults
    # given both ways, the later spelling wins
    assert DistanceMap.Params(gps_radius_m=12.0, gps={"radius_m": 10.0}).gps.radius_m == 10.0
    assert DistanceMap.Params(gps={"radius_m": 10.0}, gps_radius_m=12.0).gps.radius_m == 12.0
    with pytest.raises(ValidationError, match="gps.radius_m"):  # the error names the nested key
        DistanceMap.Params(gps_radius_m=-1)


def test_dotted_overrides_reach_the_nested_groups():
    from pathlib import Path

    from toolkit.recipe import load_recipe

    dsm = Path(__file__).resolve().parents[1] / "recipes" / "dsm.yaml"

    def params(*overrides: str):
        return DistanceMap.from_config(load_recipe(dsm, overrides).step("unary").params).params

    nested = params("steps.unary.params.gps.radius_m=20", "steps.unary.params.pose.refine_top_k=4")
    assert (nested.gps.radius_m, nested.pose.refine_top_k) == (20.0, 4)
    assert params("steps.unary.params.gps_radius_m=20", "steps.unary.params.refine_top_k=4") == nested


def test_every_option_has_a_one_line_description():
    from pydantic import BaseModel

    fields = dict(DistanceMap.Params.model_fields)
    for name, top in DistanceMap.Params.model_fields.items():
        if isinstance(top.annotation, type) and issubclass(top.annotation, BaseModel):
            fields.update({f"{name}.{key}": f for key, f in top.annotation.model_fields.items()})
    assert len(fields) == 11 + 32 + 16  # the top level (7 groups among them), 6 groups' 32 options, route_prior's 16
    for name, f in fields.items():
        assert f.description and "\n" not in f.description and len(f.description) <= 120, name


def test_debug_payloads(toy):
    toy2 = make_toy((2, 2), seed=4)
    graphs = KnnGraph()(toy2.street, toy2.overview, NullObserver())
    obs = RecordingObserver()
    DistanceMap()(graphs, toy2.street, toy2.overview, None, None, obs)
    assert isinstance(obs.records["stats"], DebugText)
    pts = obs.records["best_candidates"]
    assert isinstance(pts, DebugPoints2D) and len(pts.xy) > 0


def test_the_prefetched_atlas_is_handed_off_and_gives_the_same_costs(toy, solved, cameras):
    # the stage takes the atlas out of its Handoff, so that it is freed before the (E,L) arrays are made
    graphs, want = solved
    stage = DistanceMap(DistanceMap.Params(route_prior={"enabled": False}))
    capture = StreetCapture(cameras)
    handoff = stage.prefetch(toy.overview, capture)
    got = stage(graphs, toy.street, toy.overview, cameras, capture, NullObserver(), prefetched=handoff)
    for a, b in ((got.cost, want.cost), (got.theta_rad, want.theta_rad), (got.t, want.t)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(RuntimeError, match="already taken"):
        handoff.take()


def _corner_of_a_block():
    """One 200 m × 100 m block and two façades around its south-west corner, 60-90 m from its centre
    (a perimeter block of a real city is one over-view segment), in a street frame turned by 0.4 rad."""
    grid = Grid((0.5, 0.0, 500_000.0, 0.0, -0.5, 4_400_200.0), 500, 400, "EPSG:32617")
    label = np.full((400, 500), -1, np.int32)
    label[100:300, 50:450] = 0                       # x 500 025-500 225, y 4 400 050-4 400 150
    overview = overview_from_labels(label, grid)
    rng = np.random.default_rng(2)
    south = np.column_stack([rng.uniform(500_027, 500_050, 300), np.full(300, 4_400_050.0)])
    west = np.column_stack([np.full(200, 500_025.0), rng.uniform(4_400_052, 4_400_068, 200)])
    theta, t = 0.4, np.array([500_100.0, 4_400_100.0])
    walls = [w + rng.normal(0, 0.05, w.shape) for w in (south, west)]
    street = street_from_boundaries([(w - t) @ _rot(theta) for w in walls])  # x = R⁻¹(w - t)
    graphs = KnnGraph()(street, overview, NullObserver())
    true_centres = np.array([w.mean(axis=0) for w in walls])
    return graphs, street, overview, theta, t, true_centres


def test_a_prior_reaches_facades_far_from_a_large_blocks_centre(monkeypatch):
    """With a prior (GPS or the route placement) the anchored poses are searched within the prior
    radius of where it puts the façades, not within the 20 m offset cap about the block's centre
    (where a façade of a 200 m block never is): the same-segment label is found at the true pose."""
    from toolkit.matching import data_term as DT
    from toolkit.matching.gps import GpsPrior, PruningPrior

    graphs, street, overview, theta, t, true_centres = _corner_of_a_block()
    off_centre = np.linalg.norm(true_centres - np.asarray(overview.centroids)[0], axis=1)
    params = DistanceMap.Params()
    assert off_centre.min() > params.pose.offset_cap_m + 20, "precondition: beyond the cap plus the radius"
    prior = GpsPrior(position=true_centres + np.array([3.0, -2.0]), angle=np.full(2, theta + 0.05), n_fixes=10,
                     sigma_m=3.0)
    monkeypatch.setattr(DT, "choose_prior", lambda *a, **k: PruningPrior(prior, np.full(2, 20.0), "gps"))
    costs = DistanceMap(params)(graphs, street, overview, None, None, NullObserver())
    assert graphs.n_nodes == 1 and np.isfinite(costs.cost[0, 0]) and costs.cost[0, 0] < 0.2
    th, tt = costs.theta_rad[0, 0], costs.t[0, 0]
    placed = np.asarray(street.centroids) @ _rot(th).T + tt
    assert np.linalg.norm(placed - true_centres, axis=1).max() < 1.0
