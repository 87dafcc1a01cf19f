"""Worlds built on real cities: CityJSON LoD1/LoD2 models (roofs kept, terrain from the file) and
OpenStreetMap footprints (.osm/.osm.pbf, heights from ``height`` / ``building:levels`` or sampled,
terrain synthetic). Routes follow OSM street centrelines when there are some, else the open space."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, box
from shapely.ops import unary_union

from toolkit.errors import SceneError
from toolkit.synth import clutter
from toolkit.synth.city import FACADE_COLORS, FLAT_ROOF_COLORS, PITCHED_ROOF_COLORS, SIDEWALK_M
from toolkit.synth.config import SynthConfig
from toolkit.synth.mesh import GROUND, LABEL_GROUND, ROOF, WALL, TriMesh, concat, make, quads_to_tris
from toolkit.synth.world import Building, World, ground_mesh, plane_terrain

CITY_DEFAULTS = dict(route_length_m=800.0, route_closed=False, margin_m=20.0, ground_height_m=5.0)


def load_city(path: Path, cfg: SynthConfig, rng: np.random.Generator) -> World:
    name = path.name.lower()
    if not path.is_file():
        raise SceneError(f"{path}: city file not found")
    if name.endswith(".json"):
        return _from_cityjson(path, cfg, rng)
    if name.endswith((".osm", ".pbf", ".osm.xml")):
        return _from_osm(path, cfg, rng)
    raise SceneError(f"{path}: unknown city format (use CityJSON .json, .osm or .osm.pbf)")


def _crop_box(centres: np.ndarray, cfg: SynthConfig, to_local=None):
    """The ``city_crop_m`` square around ``city_crop_centre_lonlat`` (``to_local``: lon/lat (n,2) →
    local metres) or else around the buildings' median centre; None when not cropping."""
    if cfg.city_crop_m <= 0:
        return None
    if cfg.city_crop_centre_lonlat is not None and to_local is not None:
        c = to_local(np.array([cfg.city_crop_centre_lonlat], np.float64))[0]
    else:
        c = np.median(centres, axis=0)
    h = cfg.city_crop_m / 2
    return box(c[0] - h, c[1] - h, c[0] + h, c[1] + h)


def _finish(
    name: str,
    crs: str,
    origin: np.ndarray,
    buildings: list[Building],
    bmesh: TriMesh,
    terrain,
    ground: TriMesh | None,
    graph,
    cover: dict,
    cfg: SynthConfig,
    rng,
) -> World:
    if not buildings:
        where = f" around {cfg.city_crop_centre_lonlat}" if cfg.city_crop_centre_lonlat is not None else ""
        raise SceneError(f"{name}: no buildings left (check city_crop_m{where})")
    fps = unary_union([b.footprint for b in buildings])
    bounds = tuple(float(v) for v in fps.bounds)
    world = World(
        origin=origin,
        crs=crs,
        bounds=bounds,
        terrain=terrain,
        buildings=buildings,
        building_mesh=bmesh,
        clutter_mesh=TriMesh.empty(),
        ground_mesh=TriMesh.empty(),
        name=name,
    )
    if graph is None:
        from toolkit.synth.openspace import open_space_graph

        roads = unary_union(cover.get("road", []))
        graph = open_space_graph(world, drivable=roads if roads.area > 1000 else None)
    world.street_graph = graph
    lines = [(d["geom"], d["width"]) for _, _, d in graph.edges(data=True)]
    world.streets = lines
    flat = ground_mesh(bounds, terrain)
    world.ground_mesh = flat if ground is None else concat([ground, _skirt(bounds, ground)])
    corridor = unary_union([ln.buffer(w / 2) for ln, w in lines]) if lines else Polygon()
    carriage = (
        unary_union([ln.buffer(max(w / 2 - SIDEWALK_M, 2.0)) for ln, w in lines]) if lines else Polygon()
    )
    world.roads = unary_union([carriage, *cover.get("road", [])])
    world.pavement = unary_union([corridor, *cover.get("pavement", [])])
    world.grass = unary_union(cover.get("grass", []))
    trees, cars, heads, poles = clutter.street_furniture(graph, cfg, rng, SIDEWALK_M)
    world.clutter_mesh = clutter.furniture_mesh(trees, cars, heads, poles, fps, terrain, rng)
    from toolkit.synth.city import spurious_buildings

    free = box(*bounds).buffer(-10.0).difference(corridor)
    world.overview_only_buildings, world.overview_only = spurious_buildings(
        cfg, rng, terrain, free, fps, max(b.id for b in buildings) + 1, len(buildings)
    )
    n_missing = int(round(cfg.missing_building_fraction * len(buildings)))
    if n_missing:
        world.missing_ids = np.sort(rng.choice([b.id for b in buildings], n_missing, replace=False)).astype(
            np.int64
        )
    return world


def _lonlat_to_local(crs: str, origin: np.ndarray):
    from pyproj import Transformer

    tr = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    return lambda ll: np.column_stack(tr.transform(ll[:, 0], ll[:, 1])) - origin[:2]


def _skirt(bounds, ground: TriMesh, margin_m: float = 80.0) -> TriMesh:
    """A flat plane just under the file's terrain so rays leaving it still hit the ground."""
    z = float(np.percentile(ground.vertices[ground.triangles.ravel(), 2], 2)) - 0.3
    xmin, ymin, xmax, ymax = bounds
    v = np.array(
        [
            [xmin - margin_m, ymin - margin_m, z],
            [xmax + margin_m, ymin - margin_m, z],
            [xmax + margin_m, ymax + margin_m, z],
            [xmin - margin_m, ymax + margin_m, z],
        ]
    )
    return make(v, quads_to_tris(np.array([[0, 1, 2, 3]])), LABEL_GROUND, GROUND, (120, 120, 120))


def _raycast_terrain(ground: TriMesh, fallback: float):
    from toolkit.synth.raycast import Caster

    caster = Caster(ground)
    top = float(ground.vertices[:, 2].max()) + 100.0

    def z(x, y):
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        o = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, top)])
        t, _, _ = caster.cast(o, np.tile([0.0, 0.0, -1.0], (x.size, 1)))
        return np.where(np.isfinite(t), top - t, fallback).reshape(x.shape)

    return z


def _colors(rng, n: int):
    return (
        FACADE_COLORS[rng.integers(len(FACADE_COLORS), size=n)],
        np.concatenate([FLAT_ROOF_COLORS, PITCHED_ROOF_COLORS])[rng.integers(9, size=n)],
    )


# --- CityJSON -------------------------------------------------------------------------------------
def _from_cityjson(path: Path, cfg: SynthConfig, rng) -> World:
    from toolkit.synth.cityjson import read_cityjson

    m = read_cityjson(path)
    rings = {b: [Polygon(r) for r in rs if len(r) >= 3] for b, rs in m.footprints.items()}
    fps = {b: unary_union([p if p.is_valid else p.buffer(0) for p in ps]) for b, ps in rings.items()}
    fps = {b: g for b, g in fps.items() if not g.is_empty and g.area > 4.0}
    if not fps:
        raise SceneError(f"{path}: no building footprints (GroundSurface) found")
    cents = np.array([np.asarray(g.centroid.coords[0]) for g in fps.values()])
    origin = np.floor(cents.min(0) / 100) * 100
    crop = _crop_box(cents - origin, cfg, _lonlat_to_local(m.crs, origin))
    facade, roof = _colors(rng, len(m.building_keys))
    buildings, meshes = [], []
    tri_b = {
        "wall": np.concatenate(m.tri_building[0]) if m.tri_building[0] else np.zeros(0, int),
        "roof": np.concatenate(m.tri_building[1]) if m.tri_building[1] else np.zeros(0, int),
    }
    tris = {k: (np.concatenate(v) if v else np.zeros((0, 3, 3))) for k, v in m.tris.items()}
    for k in tris:
        tris[k] = tris[k] - np.array([origin[0], origin[1], 0.0])
    keep = {}
    for b, g in sorted(fps.items()):
        local = shapely.transform(g, lambda xy: xy - origin)
        if crop is not None and not crop.contains(local.centroid):
            continue
        keep[b] = local
    for kind, code in (("wall", WALL), ("roof", ROOF)):
        t, owner = tris[kind], tri_b[kind]
        sel = np.isin(owner, list(keep))
        if sel.any():
            color = (facade if kind == "wall" else roof)[owner[sel]]
            meshes.append(
                TriMesh(
                    t[sel].reshape(-1, 3),
                    np.arange(3 * sel.sum()).reshape(-1, 3),
                    (owner[sel] + 1).astype(np.int32),
                    np.full(sel.sum(), code, np.uint8),
                    color.astype(np.uint8),
                )
            )
    bmesh = concat(meshes)
    for b, local in keep.items():
        vb = bmesh.vertices[bmesh.triangles[bmesh.label == b + 1].ravel()]
        gz = m.ground_z.get(b, float(vb[:, 2].min()) if len(vb) else 0.0)
        top = float(vb[:, 2].max()) if len(vb) else gz
        buildings.append(Building(b + 1, local, top - gz, gz, "lod2" if len(tris["roof"]) else "lod1"))
    ground = None
    if len(tris["ground"]):
        g = tris["ground"]
        if crop is not None:
            c = g.mean(1)[:, :2]
            g = g[shapely.contains_xy(crop.buffer(cfg.margin_m + 60), c[:, 0], c[:, 1])]
        ground = TriMesh(
            g.reshape(-1, 3),
            np.arange(3 * len(g)).reshape(-1, 3),
            np.full(len(g), LABEL_GROUND, np.int32),
            np.full(len(g), GROUND, np.uint8),
            np.tile(np.array([[120, 120, 120]], np.uint8), (len(g), 1)),
        )
    zs = [b.ground_z for b in buildings]
    if ground is not None:
        terrain = _raycast_terrain(
            concat([ground, _skirt(unary_union([b.footprint for b in buildings]).bounds, ground)]),
            float(np.median(zs)),
        )
    else:
        terrain = plane_terrain(float(np.median(zs)), 0.0, 0.0, 0.0, rng)
    cover = {
        k: [shapely.transform(Polygon(r), lambda xy: xy - origin) for r in v if len(r) >= 3]
        for k, v in m.cover.items()
    }
    cover = {k: [p if p.is_valid else p.buffer(0) for p in v] for k, v in cover.items()}
    return _finish(
        path.name.split(".")[0], m.crs, origin, buildings, bmesh, terrain, ground, None, cover, cfg, rng
    )


# --- OSM --------------------------------------------------------------------------------------------
def _from_osm(path: Path, cfg: SynthConfig, rng) -> World:
    from pyproj import Transformer

    from toolkit.synth.osmcity import read_osm, street_graph, utm_crs

    data = read_osm(path)
    allpts = np.concatenate([p[0] for b in data.buildings for p in b[1]])
    crs = utm_crs(float(np.median(allpts[:, 0])), float(np.median(allpts[:, 1])))
    tr = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    proj = np.column_stack(tr.transform(allpts[:, 0], allpts[:, 1]))
    origin = np.floor(proj.min(0) / 100) * 100

    def to_local(ll):
        return np.column_stack(tr.transform(ll[:, 0], ll[:, 1])) - origin

    polys, heights = [], []
    for _, parts, height, levels in data.buildings:
        geoms = []
        for ext, holes in parts:
            p = Polygon(to_local(ext), [to_local(h) for h in holes])
            geoms.append(p if p.is_valid else p.buffer(0))
        g = unary_union(geoms)
        if g.is_empty or g.area < 4.0:
            continue
        if height is None:
            lv = (
                levels
                if levels is not None
                else rng.integers(cfg.default_levels[0], cfg.default_levels[1] + 1)
            )
            height = float(lv) * cfg.level_height_m + rng.uniform(0.3, 1.5)
        polys.append(g)
        heights.append(max(float(height), 3.0))
    cents = np.array([np.asarray(g.centroid.coords[0]) for g in polys])
    crop = _crop_box(cents, cfg, to_local)
    slope = cfg.terrain_slope_pct / 100 * rng.uniform(0.3, 1.0)
    a = rng.uniform(0, 2 * np.pi)
    gx, gy = slope * np.cos(a), slope * np.sin(a)
    z0 = cfg.ground_height_m
    if crop is not None and cfg.city_crop_centre_lonlat is not None:
        # a crop far from the file's south-west corner (a village of a country): ground_height_m there
        cx, cy = np.asarray(crop.centroid.coords[0])
        z0 -= gx * cx + gy * cy
    terrain = plane_terrain(z0, gx, gy, cfg.terrain_undulation_m, rng)
    facade, roof = _colors(rng, len(polys))
    buildings, meshes = [], []
    for i, (g, h) in enumerate(zip(polys, heights)):
        if crop is not None and not crop.contains(g.centroid):
            continue
        bid = len(buildings) + 1
        xy = shapely.get_coordinates(g)
        zg = terrain(xy[:, 0], xy[:, 1])
        gz = float(terrain(*np.asarray(g.centroid.coords[0])))
        meshes.append(extrude(g, float(zg.min()) - 1.0, gz + h, bid, facade[i], roof[i]))
        buildings.append(Building(bid, g, h, gz, "flat"))
    bounds = unary_union([b.footprint for b in buildings]).buffer(40).bounds if buildings else None
    graph = street_graph(data.ways, to_local)
    if bounds is not None and graph.number_of_edges():
        area = box(*bounds)
        graph.remove_edges_from(
            [(u, v) for u, v, d in graph.edges(data=True) if not area.contains(d["geom"])]
        )
        graph.remove_nodes_from([n for n in list(graph.nodes) if graph.degree[n] == 0])
    if graph.number_of_edges():
        import networkx as nx

        graph = graph.subgraph(max(nx.connected_components(graph), key=len)).copy()
    else:
        graph = None
    return _finish(
        path.name.split(".")[0], crs, origin, buildings, concat(meshes), terrain, None, graph, {}, cfg, rng
    )


def extrude(footprint, z0: float, z1: float, label: int, facade, roof) -> TriMesh:
    """A flat-roofed prism over any (multi)polygon with holes: walls per ring, CDT roof."""
    parts = list(footprint.geoms) if isinstance(footprint, MultiPolygon) else [footprint]
    meshes = []
    for p in parts:
        for ring in [p.exterior, *p.interiors]:
            xy = np.asarray(ring.coords)[:-1, :2]
            n = len(xy)
            v = np.concatenate([np.column_stack([xy, np.full(n, z0)]), np.column_stack([xy, np.full(n, z1)])])
            i = np.arange(n)
            j = (i + 1) % n
            meshes.append(make(v, quads_to_tris(np.column_stack([i, j, j + n, i + n])), label, WALL, facade))
        tri = shapely.get_parts(shapely.constrained_delaunay_triangles(p))
        if len(tri):
            c = shapely.get_coordinates(shapely.get_exterior_ring(tri)).reshape(len(tri), 4, 2)[:, :3]
            v = np.column_stack([c.reshape(-1, 2), np.full(3 * len(tri), z1)])
            meshes.append(make(v, np.arange(3 * len(tri)).reshape(-1, 3), label, ROOF, roof))
    return concat(meshes)
