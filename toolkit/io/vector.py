"""Building footprints from GeoJSON, GeoPackage, Shapefile, OSM XML and OSM PBF, projected to a target CRS.

GeoJSON follows RFC 7946 (lon/lat, WGS 84) unless it carries a legacy ``crs`` member naming
another CRS; coordinates outside ±180/±90 without one are an error. GeoPackage and Shapefile
layers are read with pyogrio (GDAL) in the CRS they declare (a Shapefile's ``.prj``); Z is
dropped. OSM files are read with osmium (``toolkit.io.osm``): closed ways and multipolygon relations tagged
``building`` (``building=no`` and ``building:part`` excluded) become areas. Invalid polygons
are repaired with ``shapely.make_valid(method="structure")`` (counted in ``Footprints.repaired``); geometries that
stay empty are reported in ``Footprints.skipped``.

Ids: the OSM number of the way or relation (GeoJSON: the feature ``id``, ``"way/12"`` /
``"relation/7"`` as Overpass / osmtogeojson write them, or an ``@id`` / ``osm_id`` / ``id``
property), so the three formats agree. OSM numbers ways and relations separately: a relation
whose number is also a way's gets ``RELATION_ID_OFFSET`` added. Features without an id are
numbered after the largest id, in file order.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from toolkit.errors import SceneError
from toolkit.io.osm import OsmKey

RELATION_ID_OFFSET = 10**15
LEVEL_HEIGHT_M = 3.0
LONLAT = "OGC:CRS84"  # lon/lat axis order, WGS 84 (RFC 7946)

OSM_SUFFIXES = (".osm", ".osm.pbf", ".pbf", ".osm.bz2", ".osm.gz", ".xml", ".o5m", ".opl")
GEOJSON_SUFFIXES = (".geojson", ".json")
OGR_SUFFIXES = (".gpkg", ".shp")  # read with pyogrio
BUILDING_LAYER = re.compile(r"build|bati|geb", re.IGNORECASE)  # picks one of several polygon layers


@dataclass(frozen=True)
class Footprints:
    """Building polygons in ``crs``.

    geometries: (B,) object array of shapely Polygon/MultiPolygon; ids: (B,) int64;
    height_m: (B,) float64 from ``height`` or ``building:levels`` × 3 m (NaN when untagged);
    tags: B mappings of the source properties/tags; repaired: count fixed by make_valid;
    skipped: one message per feature dropped (not polygonal, empty after repair).
    """

    geometries: np.ndarray
    ids: np.ndarray
    height_m: np.ndarray
    tags: tuple[Mapping[str, Any], ...]
    crs: str
    repaired: int = 0
    skipped: tuple[str, ...] = field(default_factory=tuple)

    def __len__(self) -> int:
        return len(self.ids)


def footprint_format(path: str | Path) -> str:
    """'geojson', 'ogr' (GeoPackage, Shapefile) or 'osm' from the file name."""
    name = Path(path).name.lower()
    if name.endswith(GEOJSON_SUFFIXES):
        return "geojson"
    if name.endswith(OGR_SUFFIXES):
        return "ogr"
    if name.endswith(OSM_SUFFIXES):
        return "osm"
    raise SceneError(f"{path}: unknown footprint format {Path(path).suffix or name!r} (expected .geojson or "
                     ".json (RFC 7946), .gpkg, .shp, .osm or .osm.pbf)")


def read_footprints(path: str | Path, target_crs: str) -> Footprints:
    """Read building footprints from GeoJSON / GeoPackage / Shapefile / OSM, projected to ``target_crs``."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    fmt = footprint_format(path)
    if fmt == "geojson":
        geoms, ids, tags, src_crs, skipped = _read_geojson(path)
    elif fmt == "ogr":
        geoms, ids, tags, src_crs, skipped = _read_ogr(path)
    else:
        from toolkit.io.osm import read_osm_buildings

        geoms, ids, tags, skipped = read_osm_buildings(path)
        src_crs = LONLAT
    return _finish(path, geoms, ids, tags, src_crs, target_crs, skipped)


def check_footprints(path: str | Path, target_crs: str) -> None:
    """What ``read_footprints`` would reject, without the heavy part (OSM assembly, projection):
    the format, a GeoJSON's CRS and lon/lat range, a GeoPackage/Shapefile's polygon layer and CRS."""
    path = Path(path)
    fmt = footprint_format(path)
    if fmt == "geojson":
        geoms, _, _, src_crs, _ = _read_geojson(path)
        _check_lonlat(path, np.array(geoms, dtype=object), src_crs, target_crs)
    elif fmt == "ogr":
        _ogr_layer(path)


def footprints_crs(path: str | Path) -> str:
    """The CRS a footprint file declares: a GeoJSON's ``crs`` member (lon/lat without one, as RFC
    7946 says), a GeoPackage or Shapefile layer's CRS, lon/lat for OSM."""
    path = Path(path)
    fmt = footprint_format(path)
    if fmt == "geojson":
        return _read_geojson(path)[3]
    if fmt == "ogr":
        return _ogr_layer(path)[1]
    return LONLAT


# --- GeoJSON ------------------------------------------------------------------------------------
def _read_geojson(path: Path) -> tuple[list, list[OsmKey], list[dict], str, list[str]]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SceneError(f"{path}: invalid GeoJSON ({' '.join(str(exc).split())})") from exc
    if not isinstance(doc, dict) or "type" not in doc:
        raise SceneError(f"{path}: not a GeoJSON object (no 'type' member)")
    src_crs = _geojson_crs(path, doc.get("crs"))
    if doc["type"] == "FeatureCollection":
        features = doc.get("features")
        if not isinstance(features, list):
            raise SceneError(f"{path}: FeatureCollection without a 'features' list")
    elif doc["type"] == "Feature":
        features = [doc]
    else:
        features = [{"type": "Feature", "geometry": doc, "properties": {}}]
    geoms, ids, tags, skipped = [], [], [], []
    for k, feat in enumerate(features):
        geom = (feat or {}).get("geometry") if isinstance(feat, dict) else None
        gtype = geom.get("type") if isinstance(geom, dict) else None
        if gtype not in ("Polygon", "MultiPolygon"):
            skipped.append(f"feature {k}: geometry {gtype} is not a polygon")
            continue
        try:
            g = shapely.geometry.shape(geom)
        except (TypeError, ValueError, IndexError, shapely.errors.ShapelyError) as exc:  # malformed coordinates
            skipped.append(f"feature {k}: bad coordinates ({exc})")
            continue
        props = feat.get("properties") or {}
        geoms.append(g)
        ids.append(_feature_id(feat.get("id"), props))
        tags.append(dict(props))
    return geoms, ids, tags, src_crs, skipped


def _geojson_crs(path: Path, crs_member: Any) -> str:
    """The legacy (GeoJSON 2008) ``crs`` member, or RFC 7946 lon/lat when absent."""
    if crs_member is None:
        return LONLAT
    name = crs_member.get("properties", {}).get("name") if isinstance(crs_member, dict) else None
    if not isinstance(name, str):
        raise SceneError(f"{path}: unsupported 'crs' member {crs_member!r} (expected a named CRS)")
    if re.search(r"CRS:?84$", name.replace("::", ":")) or name.upper() in ("EPSG:4326", "URN:OGC:DEF:CRS:EPSG::4326"):
        return LONLAT  # GeoJSON writers put lon/lat order under 4326 too
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        return CRS.from_user_input(name).to_string()
    except CRSError as exc:
        raise SceneError(f"{path}: unknown CRS {name!r} in its 'crs' member") from exc


def _feature_id(fid: Any, props: Mapping[str, Any]) -> OsmKey:
    kind = props.get("osm_type") or props.get("@type") or props.get("type")
    for value in (fid, props.get("@id"), props.get("osm_id"), props.get("id")):
        parsed = _parse_id(value, kind)
        if parsed[1] is not None:
            return parsed
    return (False, None)


def _parse_id(value: Any, osm_type: Any = None) -> OsmKey:
    is_rel = osm_type in ("relation", "r", "multipolygon")
    if isinstance(value, bool) or value is None:
        return (False, None)
    if isinstance(value, (int, np.integer)):
        return (is_rel, int(value))
    if isinstance(value, float) and value.is_integer():
        return (is_rel, int(value))
    if isinstance(value, str):
        m = re.fullmatch(r"\s*(?:(way|relation|w|r)[/ ]?)?(-?\d+)\s*", value)
        if m:
            return ((m.group(1) in ("relation", "r")) if m.group(1) else is_rel, int(m.group(2)))
    return (False, None)


# --- GeoPackage, Shapefile (pyogrio) ------------------------------------------------------------
def _read_ogr(path: Path) -> tuple[list, list[OsmKey], list[dict], str, list[str]]:
    import pyogrio.raw

    layer, crs = _ogr_layer(path)
    try:
        meta, _, wkb, columns = pyogrio.raw.read(path, layer=layer)
    except Exception as exc:  # GDAL's errors: corrupt file, missing .shx/.dbf
        raise SceneError(f"{path}: cannot read layer {layer!r} ({' '.join(str(exc).split())})") from exc
    parsed = shapely.force_2d(shapely.from_wkb(wkb))
    values = [np.asarray(c).tolist() for c in columns]
    geoms, ids, tags, skipped = [], [], [], []
    for k, g in enumerate(parsed):
        gtype = None if g is None else g.geom_type
        if gtype not in ("Polygon", "MultiPolygon"):
            skipped.append(f"feature {k}: geometry {gtype} is not a polygon")
            continue
        props = {name: col[k] for name, col in zip(meta["fields"], values)}
        geoms.append(g)
        ids.append(_feature_id(None, props))
        tags.append(props)
    return geoms, ids, tags, crs, skipped


def _ogr_layer(path: Path) -> tuple[str, str]:
    """(name, CRS) of the building layer: the file's only polygon layer, else the one named like buildings."""
    import pyogrio

    try:
        layers = [(str(name), str(gtype)) for name, gtype in pyogrio.list_layers(path)]
    except Exception as exc:
        raise SceneError(f"{path}: cannot open ({' '.join(str(exc).split())})") from exc
    polygonal = [name for name, gtype in layers if "Polygon" in gtype]
    if len(polygonal) > 1:
        polygonal = [name for name in polygonal if BUILDING_LAYER.search(name)] or polygonal
    listed = ", ".join(f"{name} ({gtype})" for name, gtype in layers) or "none"
    if len(polygonal) != 1:
        what = "no polygon layer" if not polygonal else "several polygon layers"
        raise SceneError(f"{path}: {what} (layers: {listed}); keep one layer of building polygons in the file")
    crs = pyogrio.read_info(path, layer=polygonal[0])["crs"]
    if crs is None:
        fix = "add its .prj" if path.suffix.lower() == ".shp" else "assign one"
        raise SceneError(f"{path}: layer {polygonal[0]!r} has no CRS; {fix} (e.g. ogr2ogr -a_srs EPSG:… out{path.suffix} {path.name})")
    return polygonal[0], crs


# --- common -------------------------------------------------------------------------------------
def _check_lonlat(path: Path, geoms: np.ndarray, src_crs: str, target_crs: str) -> None:
    """Coordinates read as lon/lat must be within ±180/±90: projected ones need a ``crs`` member."""
    if src_crs != LONLAT or not len(geoms):
        return
    minx, miny, maxx, maxy = shapely.total_bounds(geoms)
    if min(minx, miny) < -180 or maxx > 180 or maxy > 90 or miny < -90:
        member = json.dumps({"crs": {"type": "name", "properties": {"name": target_crs}}})[1:-1]
        raise SceneError(f"{path}: coordinates are not lon/lat (x {minx:.0f}..{maxx:.0f}, y {miny:.0f}..{maxy:.0f}) "
                         f"and there is no 'crs' member; RFC 7946 GeoJSON is lon/lat: reproject it (ogr2ogr -s_srs "
                         f"<its CRS> -t_srs EPSG:4326 out.geojson {path.name}) or, if it is in {target_crs}, add "
                         f"the member {member}")


def _finish(path: Path, geoms: list, ids: list[OsmKey], tags: list[dict], src_crs: str,
            target_crs: str, skipped: list[str]) -> Footprints:
    arr = np.array(geoms, dtype=object) if geoms else np.empty(0, dtype=object)
    _check_lonlat(path, arr, src_crs, target_crs)
    try:
        arr = project(arr, src_crs, target_crs)
    except SceneError as exc:
        raise SceneError(f"{path}: {exc}") from exc
    arr, repaired, keep = _repair(arr)
    skipped += [f"feature {i}: empty after repair" for i in np.flatnonzero(~keep)]
    id_arr = _fill_ids([ids[i] for i in np.flatnonzero(keep)])
    kept_tags = tuple(tags[i] for i in np.flatnonzero(keep))
    heights = np.array([building_height_m(t) for t in kept_tags], dtype=np.float64)
    if len(np.unique(id_arr)) != len(id_arr):
        raise SceneError(f"{path}: duplicate building ids (first: {_first_duplicate(id_arr)})")
    return Footprints(arr[keep], id_arr, heights, kept_tags, target_crs, repaired, tuple(skipped))


def project(geoms: np.ndarray, src_crs: str, dst_crs: str) -> np.ndarray:
    """Reproject an array of shapely geometries (always x=easting/lon, y=northing/lat)."""
    if len(geoms) == 0:
        return geoms
    from pyproj import CRS, Transformer

    if CRS.from_user_input(src_crs).equals(CRS.from_user_input(dst_crs), ignore_axis_order=True):
        return geoms
    tr = Transformer.from_crs(src_crs, dst_crs, always_xy=True)

    def fn(xy: np.ndarray) -> np.ndarray:
        x, y = tr.transform(xy[:, 0], xy[:, 1])
        return np.column_stack([x, y])

    out = shapely.transform(geoms, fn)
    if not np.isfinite(shapely.bounds(out)).all():
        raise SceneError(f"coordinates cannot be projected from {src_crs} to {dst_crs} (out of range?)")
    return out


def _repair(geoms: np.ndarray) -> tuple[np.ndarray, int, np.ndarray]:
    """make_valid the invalid ones and keep only their polygonal part."""
    if len(geoms) == 0:
        return geoms, 0, np.zeros(0, bool)
    bad = ~shapely.is_valid(geoms)
    out = geoms.copy()
    for i in np.flatnonzero(bad):
        # "structure": union of the shells minus the holes; the default "linework" method drops
        # the overlap of two overlapping parts (their XOR), which would punch holes in buildings
        out[i] = _polygonal(shapely.make_valid(geoms[i], method="structure", keep_collapsed=False))
    keep = ~shapely.is_empty(out) & (shapely.area(out) > 0)
    return out, int(bad.sum()), keep


def _polygonal(g: Any) -> Any:
    if g.geom_type in ("Polygon", "MultiPolygon"):
        return g
    parts = [p for p in getattr(g, "geoms", []) if p.geom_type in ("Polygon", "MultiPolygon")]
    return shapely.union_all(parts) if parts else shapely.Polygon()


def _fill_ids(keys: list[OsmKey]) -> np.ndarray:
    """OSM keys → int64 ids (see the module doc for relations and missing ids)."""
    way_numbers = {n for rel, n in keys if n is not None and not rel}
    out = np.empty(len(keys), dtype=np.int64)
    for k, (rel, n) in enumerate(keys):
        if n is not None:
            out[k] = n + RELATION_ID_OFFSET if rel and n in way_numbers else n
    missing = [k for k, (_, n) in enumerate(keys) if n is None]
    known = out[[k for k in range(len(keys)) if keys[k][1] is not None]]
    start = int(known.max()) + 1 if known.size else 1
    out[missing] = np.arange(start, start + len(missing))
    return out


def _first_duplicate(ids: np.ndarray) -> int:
    u, c = np.unique(ids, return_counts=True)
    return int(u[c > 1][0])


_NUMBER = re.compile(r"^\s*(-?\d+(?:[.,]\d+)?)\s*(m|meters|metres|ft|')?\s*$", re.IGNORECASE)


def building_height_m(tags: Mapping[str, Any]) -> float:
    """Height from ``height`` (m or ft) or ``building:levels`` × 3 m; NaN when neither parses."""
    h = _number(tags.get("height"))
    if h is not None:
        return h
    levels = _number(tags.get("building:levels"), allow_units=False)
    return levels * LEVEL_HEIGHT_M if levels is not None else float("nan")


def _number(value: Any, allow_units: bool = True) -> float | None:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, str):
        return None
    m = _NUMBER.match(value)
    if not m or (m.group(2) and not allow_units):
        return None
    v = float(m.group(1).replace(",", "."))
    return v * 0.3048 if m.group(2) in ("ft", "'") else v


def iter_polygons(geom: Any) -> Iterable[Any]:
    """The Polygon parts of a Polygon / MultiPolygon."""
    return geom.geoms if geom.geom_type == "MultiPolygon" else (geom,)
