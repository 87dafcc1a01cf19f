"""Over-view rasters: a true-ortho render of the over-view world by casting rays straight down at
every pixel centre, then the products a satellite pipeline would deliver — a stereo-like DSM
(smoothed edges, noise, a few matching holes), an R,G,B,NIR orthophoto (vegetation bright in NIR,
cast shadows away from the sun) and a classifier-like building label map."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from toolkit.synth.config import SynthConfig
from toolkit.synth.mesh import CROWN, GROUND, TRUNK
from toolkit.synth.raycast import Caster
from toolkit.synth.world import World
from toolkit.types import Grid

DSM_NODATA = -9999.0
LABEL_NODATA = 255
ROAD, PAVEMENT, GRASS = 1, 2, 3
# land cover → (R, G, B, NIR)
COVER_RGBN = np.array(
    [[135, 125, 105, 125], [72, 72, 75, 62], [165, 160, 152, 150], [85, 128, 62, 200]], float
)
STRIP_PIXELS = 2_000_000


@dataclass
class Render:
    """Per-pixel truth of the over-view epoch. label: building id, -1 ground, -2 clutter."""

    height: np.ndarray  # (H,W) float64, NaN where nothing was hit
    label: np.ndarray  # (H,W) int32
    kind: np.ndarray  # (H,W) uint8
    color: np.ndarray  # (H,W,3) uint8 surface colour
    normal_z: np.ndarray  # (H,W) float32
    shadow: np.ndarray  # (H,W) bool
    sun_dot: np.ndarray  # (H,W) float32 cosine between surface normal and sun direction


def make_grid(world: World, cfg: SynthConfig) -> Grid:
    xmin, ymin, xmax, ymax = world.bounds
    g = cfg.gsd_m
    e0 = np.floor((world.origin[0] + xmin - cfg.margin_m) / g) * g
    n1 = np.ceil((world.origin[1] + ymax + cfg.margin_m) / g) * g
    w = int(np.ceil((world.origin[0] + xmax + cfg.margin_m - e0) / g))
    h = int(np.ceil((n1 - (world.origin[1] + ymin - cfg.margin_m)) / g))
    return Grid((g, 0.0, float(e0), 0.0, -g, float(n1)), w, h, cfg.crs)


def local_transform(grid: Grid, origin: np.ndarray) -> tuple:
    a, b, c, d, e, f = grid.transform
    return (a, b, c - origin[0], d, e, f - origin[1])


def sun_vector(cfg: SynthConfig) -> np.ndarray:
    az, el = np.deg2rad(cfg.sun_azimuth_deg), np.deg2rad(cfg.sun_elevation_deg)
    return np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])


def render(caster: Caster, grid: Grid, origin: np.ndarray, cfg: SynthConfig) -> Render:
    H, W = grid.height, grid.width
    out = Render(
        np.full((H, W), np.nan),
        np.full((H, W), -1, np.int32),
        np.zeros((H, W), np.uint8),
        np.zeros((H, W, 3), np.uint8),
        np.ones((H, W), np.float32),
        np.zeros((H, W), bool),
        np.zeros((H, W), np.float32),
    )
    mesh = caster.mesh
    top = float(mesh.vertices[:, 2].max()) + 50.0
    sun = sun_vector(cfg)
    rows_per_strip = max(1, STRIP_PIXELS // W)
    for r0 in range(0, H, rows_per_strip):
        r1 = min(H, r0 + rows_per_strip)
        rr, cc = np.meshgrid(np.arange(r0, r1), np.arange(W), indexing="ij")
        xy = grid.pixel_to_world(rr.ravel(), cc.ravel()) - origin
        o = np.column_stack([xy, np.full(len(xy), top)])
        t, prim, nrm = caster.cast(o, np.array([[0.0, 0.0, -1.0]]).repeat(len(xy), 0), want_normals=True)
        hit = prim >= 0
        z = np.where(hit, top - t, np.nan)
        nrm = np.where((nrm[:, 2:] < 0), -nrm, nrm)  # face up
        sl = (slice(r0, r1), slice(None))
        out.height[sl] = z.reshape(r1 - r0, W)
        out.label[sl] = np.where(hit, mesh.label[np.maximum(prim, 0)], -1).reshape(r1 - r0, W)
        out.kind[sl] = np.where(hit, mesh.kind[np.maximum(prim, 0)], GROUND).reshape(r1 - r0, W)
        out.color[sl] = np.where(hit[:, None], mesh.color[np.maximum(prim, 0)], 128).reshape(r1 - r0, W, 3)
        out.normal_z[sl] = nrm[:, 2].reshape(r1 - r0, W)
        out.sun_dot[sl] = (nrm @ sun).reshape(r1 - r0, W)
        surf = np.column_stack([xy, np.where(hit, z, 0)]) + nrm * 0.05
        shadow = caster.occluded(surf, np.broadcast_to(sun, surf.shape).copy()) & hit
        out.shadow[sl] = shadow.reshape(r1 - r0, W)
    return out


def dsm_product(r: Render, cfg: SynthConfig, rng: np.random.Generator) -> np.ndarray:
    """Stereo-like DSM: edges smoothed, white plus correlated noise, holes in dark shadow."""
    z = r.height.copy()
    valid = np.isfinite(z)
    z[~valid] = np.nanmin(z) if valid.any() else 0.0
    if cfg.dsm_edge_sigma_px > 0:
        z = ndi.gaussian_filter(z, cfg.dsm_edge_sigma_px)
    noise = rng.normal(0, 1, z.shape)
    corr = ndi.gaussian_filter(rng.normal(0, 1, z.shape), 3.0)
    corr *= 1.0 / max(corr.std(), 1e-9)
    z = z + cfg.dsm_noise_m * (0.7 * noise + 0.7 * corr)
    holes = ~valid
    if cfg.dsm_hole_fraction > 0:
        holes |= _blobs(r.shadow, cfg.dsm_hole_fraction, rng, radius_px=(2, 6))
    out = z.astype(np.float32)
    out[holes] = DSM_NODATA
    return out


def ortho_product(r: Render, cover: np.ndarray, cfg: SynthConfig, rng: np.random.Generator) -> np.ndarray:
    """(4,H,W) uint8 R, G, B, NIR, made in row strips to bound memory on big grids."""
    H, W = r.label.shape
    out = np.empty((4, H, W), np.uint8)
    flat_sun = 0.35 + 0.65 * np.sin(np.deg2rad(cfg.sun_elevation_deg))
    rows = max(1, STRIP_PIXELS // W)
    for r0 in range(0, H, rows):
        s = slice(r0, min(H, r0 + rows))
        kind, color = r.kind[s], r.color[s]
        rgbn = np.empty(kind.shape + (4,), np.float32)
        rgbn[..., :3] = color
        rgbn[..., 3] = color.mean(-1) * 0.9
        ground = kind == GROUND
        rgbn[ground] = COVER_RGBN[cover[s][ground]]
        veg = kind == CROWN
        rgbn[veg, 3] = 175 + color[veg, 1] * 0.4
        rgbn[kind == TRUNK] = [90, 75, 55, 120]
        rgbn *= ((0.35 + 0.65 * np.clip(r.sun_dot[s], 0, 1)) / flat_sun)[..., None]
        rgbn[r.shadow[s]] *= np.array([0.42, 0.45, 0.55, 0.5], np.float32)
        n = kind.shape
        rgbn += rng.normal(0, 1, n + (1,)).astype(np.float32) * cfg.ortho_noise
        rgbn += rng.normal(0, 1, n + (4,)).astype(np.float32) * (cfg.ortho_noise * 0.4)
        out[:, s] = np.moveaxis(np.round(np.clip(rgbn, 0, 255)).astype(np.uint8), -1, 0)
    return out


def label_product(r: Render, cfg: SynthConfig, rng: np.random.Generator) -> np.ndarray:
    """Classifier-like building map: eroded/dilated edges, ragged boundaries, misses, false blobs."""
    ids = np.where(r.label > 0, r.label, 0)
    uniq = np.unique(ids[ids > 0])
    n_miss = int(round(cfg.label_missed_fraction * len(uniq)))
    if n_miss:
        ids[np.isin(ids, rng.choice(uniq, n_miss, replace=False))] = 0
    mask = ids > 0
    if not mask.any():
        return mask.astype(np.uint8)
    d_in = ndi.distance_transform_edt(mask)
    d_out, (ir, ic) = ndi.distance_transform_edt(~mask, return_indices=True)
    nearest = ids[ir, ic]
    E = cfg.label_edge_px
    per_id = np.zeros(int(uniq.max()) + 1)  # uniq still holds the missed ids (ids.max() may not)
    per_id[uniq] = rng.uniform(-E, E, len(uniq)) if E > 0 else 0.0
    ragged = ndi.gaussian_filter(rng.normal(0, 1, mask.shape), 1.5)
    ragged *= 0.6 / max(ragged.std(), 1e-9)
    signed = np.where(mask, d_in, 0.5 - d_out)
    out = (signed + per_id[nearest] + ragged) > 0.5
    n_blobs = rng.poisson(cfg.label_false_blobs_per_ha * mask.size * cfg.gsd_m**2 / 1e4)
    out |= _blobs(~mask, 0.0, rng, radius_px=(3, 9), count=n_blobs)
    return out.astype(np.uint8)


def _blobs(
    where: np.ndarray,
    fraction: float,
    rng: np.random.Generator,
    radius_px: tuple[int, int],
    count: int | None = None,
) -> np.ndarray:
    """Random roundish blobs seeded inside ``where``: ``count`` of them, or as many as cover about
    ``fraction`` of the image."""
    H, W = where.shape
    cand = np.flatnonzero(where)
    out = np.zeros((H, W), bool)
    if len(cand) == 0:
        return out
    mean_area = np.pi * np.mean(radius_px) ** 2
    n = count if count is not None else int(round(fraction * H * W / mean_area))
    if n == 0:
        return out
    seeds = rng.choice(cand, n, replace=True)
    radii = rng.uniform(*radius_px, n)
    sr, sc = np.divmod(seeds, W)
    rmax = int(np.ceil(radius_px[1]))
    dr, dc = np.mgrid[-rmax : rmax + 1, -rmax : rmax + 1]
    ecc = rng.uniform(0.6, 1.4, n)
    inside = (dr[None] * ecc[:, None, None]) ** 2 + (dc[None] / ecc[:, None, None]) ** 2 <= radii[
        :, None, None
    ] ** 2
    k, rr, cc = np.nonzero(inside)
    r_abs, c_abs = sr[k] + rr - rmax, sc[k] + cc - rmax
    ok = (r_abs >= 0) & (r_abs < H) & (c_abs >= 0) & (c_abs < W)
    out[r_abs[ok], c_abs[ok]] = True
    return out


def land_cover(world: World, grid: Grid) -> np.ndarray:
    """(H,W) uint8: 0 bare, 1 road, 2 pavement, 3 grass."""
    from rasterio.features import rasterize
    from rasterio.transform import Affine

    shapes = [
        (g, v)
        for g, v in ((world.grass, GRASS), (world.pavement, PAVEMENT), (world.roads, ROAD))
        if g is not None and not g.is_empty
    ]
    if not shapes:
        return np.zeros((grid.height, grid.width), np.uint8)
    return rasterize(
        shapes,
        out_shape=(grid.height, grid.width),
        transform=Affine(*local_transform(grid, world.origin)),
        fill=0,
        dtype="uint8",
    )


def cover_colors(cover: np.ndarray, grid: Grid, origin: np.ndarray, xy_local: np.ndarray) -> np.ndarray:
    """RGB of the land cover under local points (bare ground outside the grid)."""
    rc = np.floor(grid.world_to_pixel(xy_local + origin) + 0.5).astype(np.int64)
    ok = (rc[:, 0] >= 0) & (rc[:, 0] < grid.height) & (rc[:, 1] >= 0) & (rc[:, 1] < grid.width)
    cls = np.zeros(len(xy_local), np.int64)
    cls[ok] = cover[rc[ok, 0], rc[ok, 1]]
    return COVER_RGBN[cls, :3].astype(np.uint8)
