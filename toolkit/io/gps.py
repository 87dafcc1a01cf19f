"""GPS fixes of the street images (street/gps.csv) and their match with the COLMAP images.

Layouts read (header names case-insensitive):
- ours: ``image_name,lon,lat[,sigma_m]`` (WGS 84 degrees, σ in metres);
- exiftool's ``exiftool -csv -n -GPSLatitude -GPSLongitude [-GPSHPositioningError] DIR``:
  ``SourceFile,GPSLatitude,GPSLongitude,...``; without ``-n`` the degrees-minutes-seconds text
  (``40 deg 26' 46.30" N``) is read too, and ``GPSLatitudeRef``/``GPSLongitudeRef`` columns give
  the hemisphere of unsigned values;
- the common aliases ``name``/``image``/``filename``, ``longitude``/``lng``, ``latitude``.

Image names match the COLMAP model's exactly, else by file name (``images/f01.jpg`` and
``f01.jpg`` are one image) when that file name is unique in the model.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from toolkit.errors import SceneError

NAME_COLUMNS = ("image_name", "sourcefile", "name", "image", "filename", "file")
LON_COLUMNS = ("lon", "gpslongitude", "longitude", "lng", "long")
LAT_COLUMNS = ("lat", "gpslatitude", "latitude")
SIGMA_COLUMNS = ("sigma_m", "gpshpositioningerror", "accuracy_m", "horizontal_accuracy_m")
EXPECTED = "image_name,lon,lat[,sigma_m] (or exiftool -csv -n: SourceFile,GPSLatitude,GPSLongitude)"
_DMS = re.compile(r"^\s*([+-]?\d+(?:\.\d+)?)(?:\s*(?:deg|°)\s*(\d+(?:\.\d+)?)?'?\s*(\d+(?:\.\d+)?)?\"?)?\s*([NSEW])?\s*$",
                  re.IGNORECASE)


DEFAULT_SIGMA_M = 10.0  # the σ assumed for a fix that states none


@dataclass(frozen=True)
class GpsFixes:
    """names: (N,) image names as written; lonlat: (N,2) WGS 84 degrees; sigma_m: (N,) (NaN: not given)."""

    names: tuple[str, ...]
    lonlat: np.ndarray
    sigma_m: np.ndarray

    def __len__(self) -> int:
        return len(self.names)

    def scene_xy(self, crs: str) -> np.ndarray:
        """(N,2) the fixes' x, y in ``crs``."""
        from pyproj import Transformer

        east, north = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(self.lonlat[:, 0],
                                                                                      self.lonlat[:, 1])
        return np.column_stack([east, north])

    def sigma_or_default(self, default_m: float | None = None) -> np.ndarray:
        """(N,) the stated σ (m), ``default_m`` (DEFAULT_SIGMA_M) where none or a non-positive one is given."""
        default_m = DEFAULT_SIGMA_M if default_m is None else default_m
        return np.where(np.isfinite(self.sigma_m) & (self.sigma_m > 0), self.sigma_m, default_m)


def read_gps_csv(path: str | Path) -> GpsFixes:
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            header = list(reader.fieldnames or [])
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise SceneError(f"{path}: cannot read GPS fixes ({exc})") from exc
    columns = _columns(path, header)
    try:
        names = tuple(r[columns["name"]].strip() for r in rows)
        lon = [_degrees(r[columns["lon"]], _ref(r, columns, "lon")) for r in rows]
        lat = [_degrees(r[columns["lat"]], _ref(r, columns, "lat")) for r in rows]
        sigma = [float(r.get(columns.get("sigma", ""), "") or "nan") for r in rows]
    except (ValueError, TypeError, AttributeError) as exc:
        raise SceneError(f"{path}: non-numeric lon/lat/sigma_m ({exc})") from exc
    lonlat = np.array([lon, lat], dtype=np.float64).T.reshape(-1, 2)
    bad = ~((np.abs(lonlat[:, 0]) <= 180) & (np.abs(lonlat[:, 1]) <= 90))
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise SceneError(f"{path}: fix {names[k]!r} is not WGS 84 lon/lat degrees ({lonlat[k, 0]}, {lonlat[k, 1]})")
    return GpsFixes(names, lonlat, np.array(sigma, dtype=np.float64))


def _columns(path: Path, header: list[str]) -> dict[str, str]:
    """Role (name, lon, lat, sigma, lon_ref, lat_ref) → header name."""
    lower = {h.strip().lower(): h for h in header if h}
    found = {}
    for role, aliases in (("name", NAME_COLUMNS), ("lon", LON_COLUMNS), ("lat", LAT_COLUMNS),
                          ("sigma", SIGMA_COLUMNS), ("lon_ref", ("gpslongituderef",)),
                          ("lat_ref", ("gpslatituderef",))):
        hit = next((lower[a] for a in aliases if a in lower), None)
        if hit is not None:
            found[role] = hit
    if not {"name", "lon", "lat"} <= set(found):
        raise SceneError(f"{path}: expected columns {EXPECTED}, got {header}")
    return found


def _ref(row: dict, columns: dict[str, str], axis: str) -> str:
    return (row.get(columns.get(f"{axis}_ref", ""), "") or "").strip()


def _degrees(text: str, ref: str = "") -> float:
    """Decimal degrees from '40.4462', '-3.7', '40 deg 26\\' 46.30" N' or '40.4462 N'; S and W are negative."""
    m = _DMS.match(text or "")
    if not m:
        raise ValueError(f"cannot read {text!r} as degrees")
    value = float(m.group(1)) + float(m.group(2) or 0) / 60 + float(m.group(3) or 0) / 3600
    hemisphere = (m.group(4) or ref[:1]).upper()
    return -abs(value) if hemisphere in ("S", "W") else value


def match_images(fix_names: tuple[str, ...] | list[str], image_names: tuple[str, ...]) -> np.ndarray:
    """(N,) index of each fix's image in ``image_names`` (-1: none): exact name, else unique basename."""
    exact = {n: i for i, n in enumerate(image_names)}
    by_base: dict[str, int] = {}
    for i, n in enumerate(image_names):
        by_base[_basename(n)] = -1 if _basename(n) in by_base else i  # -1: ambiguous
    out = np.array([exact.get(n, by_base.get(_basename(n), -1)) for n in fix_names], dtype=np.int64)
    return out.reshape(len(fix_names))


def _basename(name: str) -> str:
    return PurePosixPath(name.replace("\\", "/")).name
