"""GeoTIFF I/O with rasterio: CRS, transform, nodata and band descriptions are kept.

Rasters in another CRS or on another grid than the scene's are reprojected onto it with
``rasterio.warp.reproject`` (``warp_raster``); ``grid_in_crs`` gives the grid a raster covers in
another CRS at its own ground sample distance (``rasterio.warp.calculate_default_transform``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from toolkit.errors import SceneError
from toolkit.types import Grid, Raster


def read_raster(path: str | Path, expect_crs: str | None = None) -> Raster:
    import rasterio
    from rasterio.errors import RasterioIOError

    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    try:
        with rasterio.open(path) as ds:
            if ds.crs is None:
                raise SceneError(f"{path}: GeoTIFF has no CRS")
            data = ds.read()
            masks = ds.read_masks() if ds.nodata is not None else None
            nodata_mask = (masks == 0).all(axis=0) if masks is not None else np.zeros(data.shape[1:], bool)
            if np.issubdtype(data.dtype, np.floating):
                nodata_mask |= ~np.isfinite(data).all(axis=0)
            grid, names = _grid_of(ds), _band_names(ds)
    except SceneError:
        raise
    except (RasterioIOError, Exception) as exc:
        raise SceneError(f"{path}: cannot read GeoTIFF ({exc})") from exc
    if expect_crs is not None and not same_crs(grid.crs, expect_crs):
        raise SceneError(f"{path}: CRS {grid.crs} differs from the scene CRS {expect_crs}")
    return Raster(data=data, grid=grid, nodata_mask=nodata_mask, band_names=names)


@dataclass(frozen=True)
class RasterHeader:
    """What a GeoTIFF's header tells: its grid (in its own CRS), bands, dtype and nodata value."""

    grid: Grid
    count: int
    dtype: str
    nodata: float | None
    band_names: tuple[str, ...]


def read_header(path: str | Path) -> RasterHeader:
    """The header of a GeoTIFF (no pixel is read); a one-line error when it has no CRS."""
    import rasterio

    path = Path(path)
    try:
        with rasterio.open(path) as ds:
            if ds.crs is None:
                raise SceneError(f"{path}: GeoTIFF has no CRS")
            return RasterHeader(_grid_of(ds), ds.count, ds.dtypes[0], ds.nodata, _band_names(ds))
    except SceneError:
        raise
    except Exception as exc:
        raise SceneError(f"{path}: cannot read GeoTIFF ({' '.join(str(exc).split())})") from exc


def _grid_of(ds) -> Grid:
    return Grid(tuple(float(v) for v in tuple(ds.transform)[:6]), ds.width, ds.height, ds.crs.to_string())


def _band_names(ds) -> tuple[str, ...]:
    return tuple((d or "").strip().lower() for d in ds.descriptions)


def on_grid(a: Grid, b: Grid) -> bool:
    """Same CRS, size and transform (to a millionth of a pixel): such a raster is read as it is."""
    return (a.width, a.height) == (b.width, b.height) and same_crs(a.crs, b.crs) and \
        np.allclose(a.transform, b.transform, rtol=0, atol=1e-6 * b.gsd_m)


def grid_bounds(grid: Grid) -> tuple[float, float, float, float]:
    """(left, bottom, right, top) of a grid in its CRS."""
    from rasterio.transform import Affine, array_bounds

    west, south, east, north = array_bounds(grid.height, grid.width, Affine(*grid.transform))
    return min(west, east), min(south, north), max(west, east), max(south, north)


MAX_GROWTH = 4  # a reprojected grid with more pixels than this many times the source's is a wrong CRS


def grid_in_crs(grid: Grid, crs: str, where: object) -> Grid:
    """``grid`` itself when it is in ``crs``, else the north-up grid covering it in ``crs`` at its own
    ground sample distance (metres; a geographic source keeps calculate_default_transform's)."""
    from rasterio.warp import calculate_default_transform

    from toolkit.io.crs import linear_unit_m, parse_crs

    if same_crs(grid.crs, crs):
        return grid
    _check_in_area(grid, crs, where)
    src = parse_crs(grid.crs, where)
    gsd = grid.gsd_m * linear_unit_m(src) if src.is_projected else None
    try:
        transform, width, height = calculate_default_transform(
            grid.crs, crs, grid.width, grid.height, *grid_bounds(grid), resolution=gsd)
    except Exception as exc:
        raise SceneError(f"{where}: cannot be reprojected from {grid.crs} to the scene CRS {crs} "
                         f"({' '.join(str(exc).split())})") from exc
    coeffs = tuple(float(v) for v in tuple(transform)[:6])
    if not np.isfinite(coeffs).all() or width * height > MAX_GROWTH * grid.width * grid.height + 10**6:
        raise SceneError(f"{where}: reprojected from {grid.crs} to the scene CRS {crs} its {grid.width}x"
                         f"{grid.height} pixels would span {width}x{height}: is its CRS right?")
    return Grid(coeffs, int(width), int(height), crs)


AREA_MARGIN_DEG = 5.0  # projections are used a little beyond their official area of use


def _check_in_area(grid: Grid, crs: str, where: object) -> None:
    """A raster far outside the scene CRS's area of use has a wrong CRS (or the scene has)."""
    from rasterio.warp import transform_bounds

    from toolkit.io.crs import parse_crs

    area = parse_crs(crs, where).area_of_use
    try:
        west, south, east, north = transform_bounds(grid.crs, "EPSG:4326", *grid_bounds(grid))
    except Exception as exc:
        raise SceneError(f"{where}: its extent in {grid.crs} cannot be located in lon/lat "
                         f"({' '.join(str(exc).split())})") from exc
    if area is None or (area.east - area.west) % 360 >= 360 - 2 * AREA_MARGIN_DEG:
        return
    m = AREA_MARGIN_DEG
    if east < area.west - m or west > area.east + m or north < area.south - m or south > area.north + m:
        raise SceneError(f"{where}: in {grid.crs} it lies at lon {west:.2f}..{east:.2f}, lat {south:.2f}..{north:.2f}, "
                         f"outside the area of the scene CRS {crs} (lon {area.west:g}..{area.east:g}, lat "
                         f"{area.south:g}..{area.north:g}); is its CRS right?")


def overlaps(a: Grid, b: Grid) -> bool:
    """Whether the extent of grid ``a`` meets grid ``b``'s (compared in ``b``'s CRS)."""
    from rasterio.warp import transform_bounds

    try:
        left, bottom, right, top = transform_bounds(a.crs, b.crs, *grid_bounds(a))
    except Exception:
        return False
    bl, bb, br, bt = grid_bounds(b)
    return bool(np.isfinite([left, bottom, right, top]).all() and left < br and right > bl
                and bottom < bt and top > bb)


def warp_raster(path: str | Path, grid: Grid, resampling: str) -> Raster:
    """A GeoTIFF reprojected onto ``grid`` (rasterio.warp.reproject, ``resampling`` by name). Its
    nodata value stays nodata; pixels it does not cover and pixels whose source pixels all are
    nodata are masked. The dtype is kept."""
    import rasterio
    from rasterio.transform import Affine
    from rasterio.warp import Resampling, reproject

    path = Path(path)
    try:
        with rasterio.open(path) as ds:
            src, masks, nodata = ds.read(), ds.read_masks(), ds.nodata
            src_transform, src_crs, names = ds.transform, ds.crs, _band_names(ds)
    except Exception as exc:
        raise SceneError(f"{path}: cannot read GeoTIFF ({' '.join(str(exc).split())})") from exc
    floating = np.issubdtype(src.dtype, np.floating)
    if nodata is None and floating:
        nodata = np.nan
    out = np.full((src.shape[0], grid.height, grid.width), 0 if nodata is None else nodata, dtype=src.dtype)
    where = dict(src_transform=src_transform, src_crs=src_crs, dst_transform=Affine(*grid.transform),
                 dst_crs=grid.crs)
    reproject(src, out, src_nodata=nodata, dst_nodata=nodata, resampling=getattr(Resampling, resampling), **where)
    covered = np.zeros((grid.height, grid.width), np.uint8)
    reproject((masks != 0).any(axis=0).astype(np.uint8), covered, src_nodata=0, dst_nodata=0,
              resampling=Resampling.nearest, **where)
    nodata_mask = covered == 0
    if nodata is not None and not (floating and np.isnan(nodata)):
        nodata_mask |= (out == nodata).all(axis=0)
    if floating:
        nodata_mask |= ~np.isfinite(out).all(axis=0)
    return Raster(data=out, grid=grid, nodata_mask=nodata_mask, band_names=names)


def same_crs(a: str, b: str) -> bool:
    from pyproj import CRS

    try:
        return CRS.from_user_input(a).equals(CRS.from_user_input(b), ignore_axis_order=True)
    except Exception:
        return a == b


def write_geotiff(path: str | Path, data: np.ndarray, grid: Grid, nodata: float | None = None,
                  band_names: Sequence[str] = ()) -> None:
    """Write (H,W) or (bands,H,W) data; deflate-compressed, deterministic."""
    import rasterio
    from rasterio.transform import Affine

    arr = data[None] if data.ndim == 2 else data
    profile = dict(driver="GTiff", width=grid.width, height=grid.height, count=arr.shape[0],
                   dtype=arr.dtype, crs=grid.crs, transform=Affine(*grid.transform),
                   compress="deflate", nodata=nodata)
    with rasterio.open(path, "w", **profile) as ds:
        ds.write(arr)
        for i, name in enumerate(band_names, start=1):
            ds.set_band_description(i, name)
