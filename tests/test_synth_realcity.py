"""``crossview synth --city``: scenes built on real city models (CityJSON, OSM)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

RAW = Path(__file__).resolve().parents[2] / "shared" / "data" / "raw"
DENHAAG = RAW / "denhaag-lod2" / "DenHaag_01.city.json"
HELSINKI = RAW / "helsinki-osm" / "Helsinki.osm.pbf"
LIECHTENSTEIN = RAW / "liechtenstein-osm" / "liechtenstein.osm.pbf"
DELFT = RAW / "delft-3dfier" / "delft_cjio_v2.0.city.json"
DELFT_V1 = RAW / "delft-3dfier" / "testarea_3dfier_v1.0.city.json"
SCHAAN = (9.5085, 47.165)  # a village of Liechtenstein (the country's median centre is between villages)
SMALL = dict(
    route_length_m=250.0,
    city_crop_m=320.0,
    point_spacing_m=0.3,
    ray_step_deg=0.6,
    sparse_points=1500,
    preview=False,
)


def _needs(path: Path):
    return pytest.mark.skipif(
        not path.is_file(), reason=f"real data not present: {path} (../shared is only in CI)"
    )


def _check_contract(root: Path, crs: str) -> None:
    """Loads as a scene; truth exact; labels name true buildings; labelled points lie on them."""
    import shapely

    from toolkit.evaluation.truth import read_true_buildings
    from toolkit.io.cloud import read_points
    from toolkit.scene import load_raster, load_scene
    from toolkit.synth.drift import Drift

    scene = load_scene(root)
    assert scene.crs == crs
    assert load_raster(scene, "dsm").grid.crs.upper().endswith(crs.split(":")[1])
    street = read_points(root / "street/cloud.ply")
    truth = np.load(root / "truth/street_points.npy")
    labels = np.load(root / "truth/street_labels.npy")
    d = np.load(root / "truth/drift.npz")
    drift = Drift(
        **{
            k: d[k]
            for k in (
                "true_centres",
                "drift_centres",
                "drift_rotation",
                "drift_scale",
                "global_rotation",
                "global_translation",
            )
        }
    )
    assert np.abs(drift.undo(street, d["camera_index"]) - truth).max() < 1e-6
    ids, geoms = read_true_buildings(root / "truth/buildings.geojson", crs)
    seen = np.unique(labels[labels > 0])
    assert len(seen) >= 5 and set(seen.tolist()) <= set(ids.tolist())
    by_id = dict(zip(ids.tolist(), geoms))
    for bid in seen[:8]:
        rows = np.flatnonzero(labels == bid)[:300]
        dist = shapely.distance(by_id[int(bid)], shapely.points(truth[rows, :2]))
        assert np.median(dist) < 0.5, bid


def test_osm_without_streets_is_driven_through_open_space(tmp_path):
    """An OSM file with buildings only: the route must find its way between them."""
    from shapely.geometry import box

    from toolkit.synth.footprints import Footprint, write_osm
    from toolkit.synth.generate import generate_from_city
    from toolkit.synth.osmcity import read_osm

    e0, n0 = 500_000.0, 5_000_000.0  # UTM 31N
    feats = [
        Footprint(
            100 + 10 * i + j,
            box(e0 + 36 * i, n0 + 36 * j, e0 + 36 * i + 22, n0 + 36 * j + 20),
            9.0,
            {"building": "yes", "height": 9.0},
        )
        for i in range(5)
        for j in range(5)
    ]
    path = tmp_path / "blocks.osm"
    write_osm(path, feats, "EPSG:32631")
    assert len(read_osm(path).buildings) == 25 and read_osm(path).ways == []
    root = generate_from_city(
        path,
        0,
        tmp_path / "scene",
        route_length_m=120.0,
        point_spacing_m=0.3,
        ray_step_deg=0.6,
        sparse_points=500,
        preview=False,
    )
    _check_contract(root, "EPSG:32631")
    d = np.load(root / "truth/drift.npz")
    cams = d["true_centres"][:, :2] - [e0, n0]
    assert np.ptp(cams, axis=0).max() > 50  # it went somewhere
    # ... along the 14-16 m wide gaps, never through a building
    inside = [(0 <= (x % 36) <= 22) and (0 <= (y % 36) <= 20) for x, y in cams]
    assert not any(inside)


@_needs(DENHAAG)
def test_den_haag_lod2_scene(tmp_path):
    from toolkit.io.cloud import read_points
    from toolkit.synth.generate import generate_from_city

    root = generate_from_city(DENHAAG, 0, tmp_path / "denhaag", **SMALL)
    _check_contract(root, "EPSG:28992")
    # LoD2 roofs are kept: the reference cloud shows sloped roofs (heights spread within a footprint)
    lidar = read_points(root / "truth/lidar.ply")
    assert np.ptp(lidar[:, 2]) > 10


@_needs(HELSINKI)
def test_helsinki_osm_scene_follows_street_centrelines(tmp_path):
    import shapely
    from pyproj import Transformer

    from toolkit.synth.generate import generate_from_city
    from toolkit.synth.osmcity import read_osm

    root = generate_from_city(HELSINKI, 0, tmp_path / "helsinki", **SMALL)
    _check_contract(root, "EPSG:32635")
    ways = read_osm(HELSINKI).ways
    tr = Transformer.from_crs("EPSG:4326", "EPSG:32635", always_xy=True)
    lines = [shapely.LineString(np.column_stack(tr.transform(ll[:, 0], ll[:, 1]))) for _, _, ll, _ in ways]
    cams = np.load(root / "truth/drift.npz")["true_centres"][:, :2]
    dist = shapely.distance(shapely.union_all(lines), shapely.points(cams))
    assert np.percentile(dist, 90) < 4.0  # in the right lane of a real street


# --- crop centre, loops on real street graphs, CityJSON 1.0 --------------------------------------
def test_crop_centre_needs_a_crop_and_a_lonlat():
    from toolkit.errors import CrossviewError
    from toolkit.synth.config import config_for

    with pytest.raises(CrossviewError, match="city_crop_m > 0"):
        config_for("campus", city_crop_centre_lonlat=SCHAAN)
    with pytest.raises(CrossviewError, match="WGS84"):
        config_for("campus", city_crop_m=500.0, city_crop_centre_lonlat=(547_000.0, 5_224_000.0))
    assert config_for("campus", city_crop_m=500.0, city_crop_centre_lonlat=[9.5, 47.1]).city_crop_centre_lonlat == (
        9.5,
        47.1,
    )


@pytest.fixture(scope="module")
def schaan():
    """Liechtenstein's OSM file cropped to 600 m around Schaan, streets and all."""
    from toolkit.synth.config import config_for
    from toolkit.synth.generate import _rng
    from toolkit.synth.realcity import CITY_DEFAULTS, load_city

    cfg = config_for(
        "campus",
        **{**CITY_DEFAULTS, "city_crop_m": 600.0, "city_crop_centre_lonlat": SCHAAN, "ground_height_m": 450.0},
    )
    return load_city(LIECHTENSTEIN, cfg, _rng(0, "city")), cfg


@_needs(LIECHTENSTEIN)
def test_crop_centre_picks_the_village(schaan):
    from pyproj import Transformer

    world, cfg = schaan
    assert world.crs == "EPSG:32632"
    centre = np.array(Transformer.from_crs("EPSG:4326", world.crs, always_xy=True).transform(*SCHAAN)) - world.origin
    cents = np.array([np.asarray(b.footprint.centroid.coords[0]) for b in world.buildings])
    assert len(cents) > 150  # the median-centre crop of the same size holds a handful
    assert np.abs(cents - centre).max() <= 300.0 + 1e-6
    assert np.linalg.norm(np.median(cents, axis=0) - centre) < 120
    # the synthetic terrain is anchored at the crop, not at the country's south-west corner
    assert abs(float(world.terrain(*centre)) - 450.0) <= cfg.terrain_undulation_m + 1e-6
    assert world.street_graph.number_of_edges() > 30


@_needs(LIECHTENSTEIN)
def test_closed_loop_on_a_real_street_graph(schaan):
    import shapely

    from toolkit.synth.generate import _rng
    from toolkit.synth.route import _cycle_route, plan_route

    world, cfg = schaan
    g = world.street_graph
    streets = shapely.union_all([d["geom"] for _, _, d in g.edges(data=True)]).buffer(0.5)
    for target in (500.0, 1200.0):
        line, closed = plan_route(world, cfg.model_copy(update={"route_length_m": target, "route_closed": True}),
                                  _rng(3, "route"))
        length = np.linalg.norm(np.diff(line, axis=0), axis=1).sum()
        assert closed and np.linalg.norm(line[0] - line[-1]) < 1e-6
        assert abs(length - target) <= 0.1 * target
        assert streets.contains(shapely.LineString(line))
    # the fallback when random walks close on no loop of the right length: the graph's own cycles
    centre = np.mean([g.nodes[n]["xy"] for n in g.nodes], axis=0)
    loop = _cycle_route(g, 500.0, centre)
    assert loop is not None and np.linalg.norm(loop[0] - loop[-1]) < 1e-6
    assert abs(np.linalg.norm(np.diff(loop, axis=0), axis=1).sum() - 500.0) <= 50.0


def test_cycle_fallback_takes_the_roundest_loop_and_open_fallback_says_so(caplog):
    """On a 3 x 3 grid of 100 m blocks: an 800 m loop is the outer square (not an L); on a street
    without loops a closed route falls back to an open one and plan_route reports it."""
    from types import SimpleNamespace

    import networkx as nx
    from shapely.geometry import LineString

    from toolkit.synth.config import config_for
    from toolkit.synth.route import _cycle_route, plan_route, route_on_graph

    def graph(edges):
        g = nx.Graph()
        for a, b in edges:
            g.add_node(a, xy=np.array(a, float) * 100)
            g.add_node(b, xy=np.array(b, float) * 100)
            geom = LineString([np.array(a) * 100.0, np.array(b) * 100.0])
            g.add_edge(a, b, geom=geom, width=12.0, length=geom.length)
        return nx.convert_node_labels_to_integers(g, ordering="sorted", label_attribute="ij")

    grid = graph(nx.grid_2d_graph(3, 3).edges)
    loop = _cycle_route(grid, 800.0, np.array([100.0, 100.0]))
    assert sorted(map(tuple, np.unique(loop.round(6), axis=0))) == sorted(
        (x, y) for x in (0.0, 100.0, 200.0) for y in (0.0, 100.0, 200.0) if (x, y) != (100.0, 100.0)
    )
    cfg = config_for("campus", route_length_m=800.0, route_closed=True)
    line = route_on_graph(grid, cfg, np.random.default_rng(0), attempts=0)  # no walks: cycles only
    assert np.linalg.norm(np.diff(line, axis=0), axis=1).sum() == pytest.approx(800.0)

    street = SimpleNamespace(name="one-street", street_graph=graph([((i, 0), (i + 1, 0)) for i in range(8)]))
    with caplog.at_level("WARNING", logger="toolkit.synth"):
        line, closed = plan_route(street, cfg, np.random.default_rng(0))
    assert not closed and np.linalg.norm(line[0] - line[-1]) > 100
    assert "using a open one" in caplog.text


def test_cityjson_reference_system_as_urn():
    from toolkit.synth.cityjson import _horizontal_crs

    assert _horizontal_crs(Path("x.json"), "urn:ogc:def:crs:EPSG::7415") == "EPSG:28992"
    assert _horizontal_crs(Path("x.json"), "https://www.opengis.net/def/crs/EPSG/0/7415") == "EPSG:28992"


@_needs(DELFT_V1)
def test_delft_cityjson_1_0_loads():
    from toolkit.synth.cityjson import read_cityjson

    m = read_cityjson(DELFT_V1)
    assert m.crs == "EPSG:28992" and len(m.footprints) == 160 and m.cover["road"]


@_needs(DELFT)
def test_delft_block_has_a_loop_along_its_road_surfaces():
    """The canal-side streets are narrow and partly outside the buildings' box: the open-space graph on
    the road surfaces still closes a loop round the block's south-east half (~450 m)."""
    import networkx as nx

    from toolkit.synth.config import config_for
    from toolkit.synth.generate import _rng
    from toolkit.synth.realcity import CITY_DEFAULTS, load_city

    world = load_city(DELFT, config_for("campus", **CITY_DEFAULTS), _rng(0, "city"))
    g = world.street_graph
    loops = [sum(g.edges[a, b]["length"] for a, b in zip(c, c[1:] + c[:1])) for c in nx.simple_cycles(g)]
    assert any(400 <= length <= 500 for length in loops), loops
