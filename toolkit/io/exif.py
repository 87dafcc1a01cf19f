"""GPS fixes from the photos' EXIF (Pillow), for the images a COLMAP model names.

An image ``frames/f01.jpg`` of the model is looked for as ``DIR/frames/f01.jpg``, then as
``DIR/f01.jpg``. Its fix is the EXIF GPS IFD: GPSLatitude/GPSLongitude (degrees, minutes, seconds
as rationals) with their N/S, E/W references, and GPSHPositioningError as σ (metres) when present.
Only the EXIF header is read, never the pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, Sequence

GPS_IFD = 0x8825
LAT_REF, LAT, LON_REF, LON, H_POSITIONING_ERROR = 1, 2, 3, 4, 31  # GPS IFD tags (EXIF 2.32)
GPS_HEADER = ("image_name", "lon", "lat", "sigma_m")


@dataclass(frozen=True)
class ExifFix:
    """One image's fix: WGS 84 degrees, σ in metres (NaN when the photo states none)."""

    image_name: str
    lon: float
    lat: float
    sigma_m: float


@dataclass(frozen=True)
class ExifScan:
    """fixes: the images with a GPS fix; found: image files found; images: images the model names."""

    fixes: tuple[ExifFix, ...]
    found: int
    images: int


def scan_images(folder: Path, image_names: Sequence[str]) -> ExifScan:
    """The EXIF GPS fix of every model image found in ``folder``."""
    fixes, found = [], 0
    for name in image_names:
        path = image_file(folder, name)
        if path is None:
            continue
        found += 1
        fix = read_exif_gps(path)
        if fix is not None:
            fixes.append(ExifFix(name, *fix))
    return ExifScan(tuple(fixes), found, len(image_names))


def image_file(folder: Path, name: str) -> Path | None:
    """``folder/name``, else ``folder/<file name of name>``, else None."""
    for candidate in (folder / name, folder / PurePosixPath(name.replace("\\", "/")).name):
        if candidate.is_file():
            return candidate
    return None


def read_exif_gps(path: Path) -> tuple[float, float, float] | None:
    """(lon, lat, sigma_m) of a photo, or None when it has no readable, in-range GPS position."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as img:
            gps = dict(img.getexif().get_ifd(GPS_IFD))
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError):  # not an image, corrupt EXIF
        return None
    lat = _degrees(gps.get(LAT), gps.get(LAT_REF), "S")
    lon = _degrees(gps.get(LON), gps.get(LON_REF), "W")
    if lat is None or lon is None or abs(lat) > 90 or abs(lon) > 180:
        return None
    return lon, lat, _number(gps.get(H_POSITIONING_ERROR))


def _degrees(value: Any, ref: Any, negative: str) -> float | None:
    """Degrees from EXIF's (degrees, minutes, seconds) rationals (or a single value) and its reference."""
    parts = value if isinstance(value, (tuple, list)) else (value,)
    numbers = [_number(p) for p in parts[:3]]
    if not numbers or any(math.isnan(n) for n in numbers):
        return None
    degrees = sum(n / 60 ** k for k, n in enumerate(numbers))
    ref = ref.decode("ascii", "replace") if isinstance(ref, bytes) else str(ref or "")
    return -degrees if ref.strip().upper().startswith(negative) else degrees


def _number(value: Any) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return float("nan")
    return number if math.isfinite(number) else float("nan")


def write_gps_csv(path: Path, fixes: Sequence[ExifFix]) -> None:
    """``image_name,lon,lat,sigma_m`` (street/gps.csv), σ empty when not stated."""
    import csv

    with open(path, "w", newline="", encoding="utf-8") as fh:
        out = csv.writer(fh, lineterminator="\n")
        out.writerow(GPS_HEADER)
        out.writerows((f.image_name, f"{f.lon:.9f}", f"{f.lat:.9f}", "" if math.isnan(f.sigma_m) else f"{f.sigma_m:g}")
                      for f in fixes)
