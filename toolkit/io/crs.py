"""Coordinate reference systems: the scene CRS must be projected with every axis in metres.

A CRS in feet or degrees is refused with a suggestion: the metre twin of a feet CRS (same name
without the unit, e.g. EPSG:6548 for EPSG:6549 "NAD83(2011) / Ohio North (ftUS)"), else the UTM
zone of the CRS's area of use, else the local UTM zone in general.
"""

from __future__ import annotations

import re
from typing import Any

from toolkit.errors import SceneError

METRE = "metre"
_UNIT_SUFFIX = re.compile(r"\s*\((?:ft|ch|lk|yd|mi)[A-Za-z]*\)")  # EPSG names: "... (ftUS)", "(ftIn)"
_ESRI_FEET = re.compile(r"_Feet(?:_Intl)?$")
LOCAL_AREA_DEG = 12.0  # an area of use at most this wide is local enough to name its UTM zone


def parse_crs(crs: Any, where: object) -> Any:
    """A pyproj CRS from any user input, or a one-line error naming ``where``."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        return CRS.from_user_input(crs)
    except CRSError as exc:
        raise SceneError(f"{where}: unknown CRS {crs!r}") from exc


def axis_units(crs: Any) -> tuple[str, ...]:
    """The unit name of each axis (pyproj ``axis_info``), e.g. ('metre', 'metre')."""
    return tuple(a.unit_name for a in crs.axis_info)


def linear_unit_m(crs: Any) -> float:
    """Metres per unit of the first axis of a projected CRS (0.3048006… for US survey feet)."""
    return float(crs.axis_info[0].unit_conversion_factor)


def check_metric_crs(where: object, crs_text: str) -> None:
    """The scene CRS must be projected and in metres: otherwise a one-line error with the fix."""
    crs = parse_crs(crs_text, where)
    units = [u for u in axis_units(crs) if u != METRE]
    if crs.is_projected and not units:
        return
    label = f"CRS {crs_text} ({crs.name})"
    if units:
        what = f"{'is not metric' if crs.is_projected else 'is not projected'}: its axes are in {units[0]}, not metres"
    else:
        what = f"is not projected (a {crs.type_name})"
    raise SceneError(f"{where}: {label} {what}; {suggest_metric(crs)}")


def suggest_metric(crs: Any) -> str:
    crs = crs.sub_crs_list[0] if crs.is_compound else crs
    twin = metre_twin(crs)
    if twin is not None:
        return f"use its metre twin {twin[0]} ({twin[1]})"
    utm = utm_of_area(crs)
    if utm is not None:
        return f"use a metric projected CRS such as the UTM zone of its area, {utm[0]} ({utm[1]})"
    return "use a metric projected CRS such as the local UTM zone (EPSG:326zz north, EPSG:327zz south)"


def metre_twin(crs: Any) -> tuple[str, str] | None:
    """(code, name) of the projected CRS named as ``crs`` without its unit, on the same datum."""
    if not crs.is_projected:
        return None
    from pyproj import CRS
    from pyproj.database import query_crs_info
    from pyproj.enums import PJType

    names = {_UNIT_SUFFIX.sub("", crs.name), _ESRI_FEET.sub("", crs.name), _ESRI_FEET.sub("_Meters", crs.name)}
    names.discard(crs.name)
    auth = (crs.to_authority() or ("EPSG", ""))[0]
    for info in query_crs_info(auth_name=auth, pj_types=PJType.PROJECTED_CRS):
        if info.name in names and not info.deprecated:
            twin = CRS.from_authority(info.auth_name, info.code)
            if set(axis_units(twin)) == {METRE} and twin.datum == crs.datum:
                return f"{info.auth_name}:{info.code}", info.name
    return None


def utm_of_area(crs: Any) -> tuple[str, str] | None:
    """(code, name) of the WGS 84 UTM zone at the centre of a local CRS's area of use."""
    area = crs.area_of_use
    if area is None or (area.east - area.west) % 360 > LOCAL_AREA_DEG or area.north - area.south > LOCAL_AREA_DEG:
        return None
    from pyproj.aoi import AreaOfInterest
    from pyproj.database import query_utm_crs_info

    lon, lat = (area.west + area.east) / 2, (area.south + area.north) / 2
    found = query_utm_crs_info(datum_name="WGS 84", area_of_interest=AreaOfInterest(lon, lat, lon, lat))
    return (f"{found[0].auth_name}:{found[0].code}", found[0].name) if found else None


def horizontal_crs(crs: Any) -> Any:
    """The horizontal part of a compound CRS (``EPSG:32617+5703`` → EPSG:32617); others as they are."""
    if crs.is_compound:
        return next((sub for sub in crs.sub_crs_list if not sub.is_vertical), crs)
    return crs


def crs_label(crs: Any) -> str:
    """``AUTH:CODE (name)`` when pyproj finds a code, else the CRS name."""
    auth = crs.to_authority(min_confidence=90)
    if auth:
        return f"{auth[0]}:{auth[1]} ({crs.name})"
    subs = [sub.to_authority(min_confidence=90) for sub in crs.sub_crs_list] if crs.is_compound else [None]
    if all(subs):  # a compound CRS without a code of its own: EPSG:32618+5703
        return f"{subs[0][0]}:{'+'.join(code for _, code in subs)} ({crs.name})"
    return repr(crs.name)


def check_cloud_crs(path: object, cloud_crs: Any, scene_crs: str) -> None:
    """A LAS/LAZ cloud that declares a CRS must declare the scene's (a vertical component ignored).

    No CRS, a vertical-only CRS or an engineering (local) CRS passes: the coordinates are then an
    arbitrary frame (SfM), which registration is for. A geographic or projected CRS other than the
    scene's means the points are in another frame than the one the run will assume.
    """
    if cloud_crs is None:
        return
    cloud = horizontal_crs(cloud_crs)
    if cloud.is_vertical or cloud.is_engineering or not (cloud.is_projected or cloud.is_geographic):
        return
    scene = parse_crs(scene_crs, scene_crs)
    if cloud.equals(horizontal_crs(scene), ignore_axis_order=True):
        return
    raise SceneError(f"{path}: the cloud's header declares CRS {crs_label(cloud_crs)}, which contradicts the "
                     f"scene CRS {scene_crs} ({scene.name}); reproject the cloud to {scene_crs}, or, if its "
                     f"coordinates are an arbitrary SfM frame, remove its CRS VLR (the WKT or GeoTIFF keys)")
