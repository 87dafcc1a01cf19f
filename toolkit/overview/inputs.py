"""Scene rasters for the over-view stages: DSM, ortho bands by role, grids, resampling."""

from __future__ import annotations

import numpy as np

from toolkit.errors import SceneError
from toolkit.scene import load_raster, need
from toolkit.types import Grid, Raster, Scene

BAND_ALIASES: dict[str, tuple[str, ...]] = {
    "red": ("red", "r", "rouge", "band_red"),
    "green": ("green", "g", "vert", "band_green"),
    "blue": ("blue", "b", "bleu", "band_blue"),
    "nir": ("nir", "near-infrared", "near infrared", "nearinfrared", "infrared", "ir", "nir1", "band_nir"),
}
ROLE_OF_ALIAS = {alias: role for role, aliases in BAND_ALIASES.items() for alias in aliases}


def band_roles(raster: Raster, bands: tuple[str, ...] | None, path: object, who: str,
               required: tuple[str, ...] = ("red", "nir")) -> dict[str, int]:
    """Role → band index, from ``bands`` (the stage parameter) or else the band descriptions."""
    return roles_of_bands(raster.data.shape[0], raster.band_names, bands, path, who, required)


def check_ortho_bands(scene: Scene, who: str, bands: tuple[str, ...] | None,
                      required: tuple[str, ...] = ("red", "nir")) -> None:
    """What ``band_roles`` would reject, from the ortho's header alone (run by ``build()``)."""
    from toolkit.io.raster import read_header

    path = need(scene, "ortho", who)
    header = read_header(path)
    roles_of_bands(header.count, header.band_names, bands, path, who, required)


def roles_of_bands(count: int, band_names: tuple[str, ...], bands: tuple[str, ...] | None, path: object,
                   who: str, required: tuple[str, ...]) -> dict[str, int]:
    if bands is not None:
        if len(bands) != count:
            raise SceneError(f"{path}: has {count} bands but {who} params.bands lists {len(bands)} ({', '.join(bands)})")
        names, origin = [b.strip().lower() for b in bands], "params.bands"
    else:
        names, origin = list(band_names), "band descriptions"
    roles: dict[str, int] = {}
    for i, name in enumerate(names):
        role = ROLE_OF_ALIAS.get(name)
        if role is not None and role not in roles:
            roles[role] = i
    missing = [r for r in required if r not in roles]
    if missing:
        found = ", ".join(repr(n) for n in names) if any(names) else "none"
        raise SceneError(f"{path}: cannot find the {' and '.join(missing)} band(s) of this {count}-band ortho "
                         f"({origin}: {found}); {_bands_fix(count, roles, missing, who)}")
    return roles


def _bands_fix(count: int, roles: dict[str, int], missing: list[str], who: str) -> str:
    named = "set" if roles else "describe its bands in the GeoTIFF (red, green, blue, nir) or set"
    fix = f"{named} {who} params.bands to the roles in file order, e.g. [red, green, blue, nir]"
    described_rgb = {"red", "green", "blue"} <= set(roles)
    if "nir" in missing and (count == 3 or described_rgb):
        use_dsm = (f"an RGB-only ortho has no near-infrared band for NDVI: set use_ortho: false in the "
                   f"params of {who} (buildings from the DSM alone)")
        return use_dsm if described_rgb else f"{use_dsm}, or {fix}"
    return fix


def load_ortho(scene: Scene, who: str, bands: tuple[str, ...] | None, grid: Grid,
               required: tuple[str, ...] = ("red", "nir")) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Ortho bands by role on ``grid`` (file dtype; float32 when resampled because the ortho's
    grid differs), and the (H,W) valid mask."""
    path = need(scene, "ortho", who)
    ortho = load_raster(scene, "ortho", who)
    roles = band_roles(ortho, bands, path, who, required)
    out = {role: ortho.data[i] for role, i in roles.items()}
    valid = ~ortho.nodata_mask
    if not same_grid(ortho.grid, grid):
        out = {role: resample(a.astype(np.float32), ortho.grid, grid, "bilinear") for role, a in out.items()}
        valid = resample(valid.astype(np.float32), ortho.grid, grid, "nearest") > 0.5
    return out, valid


def load_dsm(scene: Scene, who: str) -> tuple[np.ndarray, np.ndarray, Grid]:
    """(H,W) float32 heights, (H,W) valid mask and grid of the scene DSM."""
    need(scene, "dsm", who)
    dsm = load_raster(scene, "dsm", who)
    if dsm.data.shape[0] != 1:
        raise SceneError(f"{scene.files.dsm}: a DSM has one band, this one has {dsm.data.shape[0]}")
    return dsm.data[0].astype(np.float32, copy=False), ~dsm.nodata_mask, dsm.grid


def dsm_on_grid(scene: Scene, who: str, grid: Grid) -> tuple[np.ndarray, np.ndarray] | None:
    """The scene DSM resampled to ``grid`` (None when the scene has no DSM)."""
    if not scene.has("dsm"):
        return None
    z, valid, g = load_dsm(scene, who)
    if same_grid(g, grid):
        return z, valid
    zz = resample(np.where(valid, z, np.nan).astype(np.float32), g, grid, "bilinear")
    return zz, np.isfinite(zz)


def same_grid(a: Grid, b: Grid) -> bool:
    return (a.width, a.height) == (b.width, b.height) and np.allclose(a.transform, b.transform, rtol=0,
                                                                      atol=1e-6 * a.gsd_m)


def resample(array: np.ndarray, src: Grid, dst: Grid, method: str) -> np.ndarray:
    """Resample a (H,W) array between grids of the same CRS (rasterio.warp.reproject)."""
    from rasterio.transform import Affine
    from rasterio.warp import Resampling, reproject

    out = np.full((dst.height, dst.width), np.nan if array.dtype.kind == "f" else 0, dtype=array.dtype)
    reproject(array, out, src_transform=Affine(*src.transform), src_crs=src.crs,
              dst_transform=Affine(*dst.transform), dst_crs=dst.crs,
              resampling=getattr(Resampling, method), src_nodata=np.nan if array.dtype.kind == "f" else None,
              dst_nodata=np.nan if array.dtype.kind == "f" else None)
    return out


def grid_from_bounds(bounds: tuple[float, float, float, float], gsd_m: float, crs: str,
                     margin_m: float) -> Grid:
    """A north-up grid covering ``bounds`` (minx, miny, maxx, maxy) plus a margin, snapped to gsd."""
    minx, miny, maxx, maxy = bounds
    x0 = np.floor((minx - margin_m) / gsd_m) * gsd_m
    y1 = np.ceil((maxy + margin_m) / gsd_m) * gsd_m
    width = int(np.ceil((maxx + margin_m - x0) / gsd_m))
    height = int(np.ceil((y1 - (miny - margin_m)) / gsd_m))
    return Grid((gsd_m, 0.0, float(x0), 0.0, -gsd_m, float(y1)), width, height, crs)


def scene_grid(scene: Scene, who: str) -> Grid | None:
    """The over-view grid of the scene (``toolkit.scene.scene_grid``), which every scene raster is
    read onto; None when the scene has no raster."""
    from toolkit.scene import scene_grid as grid_of

    found = grid_of(scene)
    return None if found is None else found.grid
