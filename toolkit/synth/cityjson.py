"""Read a CityJSON city model (1.x/2.0, LoD1 or LoD2) into labelled triangles.

Buildings (and their BuildingParts) keep their walls and roofs; the terrain (TINRelief) and
terrain-like objects (Road, LandUse, PlantCover, WaterBody) become the ground. Surfaces are typed
from their semantics, else from their normal (vertical → wall, facing up → roof, down → ground).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from toolkit.errors import SceneError

GROUND_TYPES = {
    "TINRelief": "terrain",
    "Road": "road",
    "LandUse": "pavement",
    "PlantCover": "grass",
    "WaterBody": "water",
    "TransportSquare": "pavement",
    "Railway": "road",
}
BUILDING_TYPES = {"Building", "BuildingPart"}


@dataclass
class CityModel:
    crs: str  # horizontal EPSG of the file, e.g. EPSG:28992
    building_keys: list[str]  # CityJSON ids of the Buildings (index + 1 = building id)
    tris: dict[str, list] = field(default_factory=dict)  # kind → list of (T,3,3) arrays
    tri_building: list = field(default_factory=list)  # per wall/roof block: building index
    footprints: dict[int, list] = field(default_factory=dict)  # building index → ground rings (2D)
    ground_z: dict[int, float] = field(default_factory=dict)
    cover: dict[str, list] = field(default_factory=dict)  # land cover → 2D polygons (exterior rings)


def read_cityjson(path: Path) -> CityModel:
    try:
        doc = json.loads(Path(path).read_text())
    except Exception as exc:
        raise SceneError(f"{path}: cannot read CityJSON ({exc})") from exc
    if doc.get("type") != "CityJSON":
        raise SceneError(f"{path}: not a CityJSON file (type {doc.get('type')!r})")
    verts = np.asarray(doc["vertices"], np.float64)
    if "transform" in doc:
        verts = verts * np.asarray(doc["transform"]["scale"]) + np.asarray(doc["transform"]["translate"])
    crs = _horizontal_crs(path, (doc.get("metadata") or {}).get("referenceSystem", ""))
    objs = doc["CityObjects"]
    buildings = sorted(k for k, v in objs.items() if v.get("type") == "Building")
    bindex = {k: i for i, k in enumerate(buildings)}
    model = CityModel(crs, buildings)
    walls, roofs, grounds, bldg_of_wall, bldg_of_roof = [], [], [], [], []
    for key in sorted(objs):
        obj = objs[key]
        kind = obj.get("type")
        geoms = obj.get("geometry") or []
        if not geoms:
            continue
        geom = max(geoms, key=lambda g: float(str(g.get("lod", 0)).split(".")[0] or 0) + 0.01 * _lod_minor(g))
        if kind in BUILDING_TYPES:
            owner = key if kind == "Building" else (obj.get("parents") or [key])[0]
            if owner not in bindex:
                continue
            b = bindex[owner]
            for sem, ring_list in _surfaces(geom):
                typ = sem or _classify(verts[ring_list[0]])
                if typ == "GroundSurface":
                    ring = verts[ring_list[0]]
                    model.footprints.setdefault(b, []).append(ring[:, :2])
                    model.ground_z[b] = min(model.ground_z.get(b, np.inf), float(ring[:, 2].min()))
                    continue
                if typ == "ClosureSurface":
                    continue
                t = triangulate(ring_list, verts)
                if typ == "RoofSurface":
                    roofs.append(t)
                    bldg_of_roof.append(np.full(len(t), b))
                else:
                    walls.append(t)
                    bldg_of_wall.append(np.full(len(t), b))
        elif kind in GROUND_TYPES:
            for _, ring_list in _surfaces(geom):
                grounds.append(triangulate(ring_list, verts))
                model.cover.setdefault(GROUND_TYPES[kind], []).append(verts[ring_list[0]][:, :2])
    model.tris = {
        k: [verts[np.concatenate(v)]] if v else []
        for k, v in (("wall", walls), ("roof", roofs), ("ground", grounds))
    }
    model.tri_building = [bldg_of_wall, bldg_of_roof]
    _footprints_from_roofs(model)
    return model


def _footprints_from_roofs(model: CityModel) -> None:
    """Buildings without a GroundSurface (e.g. 3dfier LoD1 shells): footprint = roofs seen from above."""
    import shapely

    if not model.tris["roof"]:
        return
    roofs = model.tris["roof"][0]
    owner = np.concatenate(model.tri_building[1])
    walls = model.tris["wall"][0] if model.tris["wall"] else np.zeros((0, 3, 3))
    wall_owner = np.concatenate(model.tri_building[0]) if model.tri_building[0] else np.zeros(0, int)
    for b in np.unique(owner):
        if int(b) in model.footprints:
            continue
        tri = roofs[owner == b]
        polys = shapely.polygons(tri[:, :, :2])
        merged = shapely.union_all(shapely.buffer(polys[shapely.area(polys) > 1e-6], 0.01)).buffer(-0.01)
        rings = [np.asarray(p.exterior.coords) for p in getattr(merged, "geoms", [merged]) if not p.is_empty]
        if rings:
            model.footprints[int(b)] = rings
            zs = walls[wall_owner == b][:, :, 2] if len(walls) else tri[:, :, 2]
            model.ground_z[int(b)] = float(zs.min())


def _lod_minor(g) -> float:
    parts = str(g.get("lod", 0)).split(".")
    return float(parts[1]) if len(parts) > 1 and parts[1].isdigit() else 0.0


def _horizontal_crs(path: Path, ref: str) -> str:
    from pyproj import CRS

    # https://www.opengis.net/def/crs/EPSG/0/7415 (CityJSON ≥ 1.1) or urn:ogc:def:crs:EPSG::7415 (1.0)
    code = ref.rstrip("/").replace(":", "/").split("/")[-1] if ref else ""
    if not code.isdigit():
        raise SceneError(f"{path}: CityJSON metadata.referenceSystem {ref!r} is not an EPSG URL or URN")
    crs = CRS.from_epsg(int(code))
    if crs.is_compound:
        crs = crs.sub_crs_list[0]
    if not crs.is_projected:
        raise SceneError(f"{path}: CRS EPSG:{code} is not projected")
    return f"EPSG:{crs.to_epsg()}"


def _surfaces(geom):
    """Yield (semantic type or None, [ring vertex index arrays]) for every surface of a geometry."""
    typ, bnd = geom["type"], geom["boundaries"]
    sem = geom.get("semantics") or {}
    surfaces, values = sem.get("surfaces") or [], sem.get("values")
    if typ in ("MultiSurface", "CompositeSurface"):
        flat = [(bnd, values)]
    elif typ == "Solid":
        flat = [(shell, values[i] if values else None) for i, shell in enumerate(bnd)]
    elif typ in ("MultiSolid", "CompositeSolid"):
        flat = [
            (shell, values[i][j] if values else None)
            for i, solid in enumerate(bnd)
            for j, shell in enumerate(solid)
        ]
    else:
        return
    for surf_list, vals in flat:
        for k, surf in enumerate(surf_list):
            idx = vals[k] if vals is not None and k < len(vals) else None
            name = surfaces[idx]["type"] if idx is not None and idx < len(surfaces) else None
            yield name, [np.asarray(r, np.int64) for r in surf if len(r) >= 3]


def _newell(p: np.ndarray) -> np.ndarray:
    q = np.roll(p, -1, axis=0)
    n = np.array(
        [
            np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
            np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
            np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
        ]
    )
    norm = np.linalg.norm(n)
    return n / norm if norm > 0 else np.array([0.0, 0.0, 1.0])


def _classify(ring: np.ndarray) -> str:
    nz = _newell(ring)[2]
    if abs(nz) < 0.3:
        return "WallSurface"
    return "RoofSurface" if nz > 0 else "GroundSurface"


def triangulate(rings: list[np.ndarray], verts: np.ndarray) -> np.ndarray:
    """(T,3) vertex indices triangulating a planar polygon given as index rings (exterior, holes)."""
    ext = rings[0]
    if len(ext) > 3 and ext[0] == ext[-1]:
        ext = ext[:-1]
    if len(ext) < 3:
        return np.zeros((0, 3), np.int64)
    if len(rings) == 1 and len(ext) <= 4:  # triangles and quads (most walls): a fan
        return np.array([[ext[0], ext[i], ext[i + 1]] for i in range(1, len(ext) - 1)], np.int64)
    import shapely
    from scipy.spatial import cKDTree
    from shapely.geometry import Polygon

    p3 = verts[ext]
    n = _newell(p3)
    u = np.cross(n, [0, 0, 1.0]) if abs(n[2]) < 0.9 else np.cross(n, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    idx = np.concatenate([ext, *rings[1:]])
    pts = verts[idx] - p3[0]
    uv = np.column_stack([pts @ u, pts @ v])
    sizes = np.cumsum([0, len(ext)] + [len(r) for r in rings[1:]])
    poly = Polygon(uv[: sizes[1]], [uv[sizes[i] : sizes[i + 1]] for i in range(1, len(rings))])
    if not poly.is_valid:
        poly = poly.buffer(0)
    if poly.is_empty:
        return np.zeros((0, 3), np.int64)
    tri = shapely.get_parts(shapely.constrained_delaunay_triangles(poly))
    if len(tri) == 0:
        return np.zeros((0, 3), np.int64)
    corners = shapely.get_coordinates(shapely.get_exterior_ring(tri)).reshape(len(tri), 4, 2)[:, :3]
    # CDT adds no points: map each corner back to its input vertex
    _, j = cKDTree(uv).query(corners.reshape(-1, 2))
    return idx[j].reshape(-1, 3)
