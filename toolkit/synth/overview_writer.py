"""Write the over-view products of a world: dsm.tif, ortho.tif, labels.tif, cloud.ply, dem.tif,
footprints.geojson and map.osm (plus truth/buildings.geojson)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.io.cloud import write_ply
from toolkit.io.raster import write_geotiff
from toolkit.synth import footprints as fp
from toolkit.synth.config import SynthConfig
from toolkit.synth.overview import (
    DSM_NODATA,
    LABEL_NODATA,
    dsm_product,
    label_product,
    land_cover,
    make_grid,
    ortho_product,
    render,
)
from toolkit.synth.raycast import Caster
from toolkit.synth.world import World
from toolkit.types import Grid


@dataclass
class OverviewResult:
    grid: Grid
    dsm: np.ndarray
    dsm_nodata: float
    cover: np.ndarray  # land cover (H,W) uint8, for street ground colours
    footprint_geoms: list  # OSM-like outlines in the scene CRS (for the preview)


def write_overview(world: World, cfg: SynthConfig, root: Path, rngs: dict) -> OverviewResult:
    from toolkit.synth.timing import timed

    grid = make_grid(world, cfg)
    with timed("  render"):
        r = render(Caster(world.overview_mesh()), grid, world.origin, cfg)
    cover = land_cover(world, grid)
    dsm = dsm_product(r, cfg, rngs["dsm"])
    write_geotiff(root / "overview/dsm.tif", dsm, grid, nodata=DSM_NODATA, band_names=("height",))
    ortho = ortho_product(r, cover, cfg, rngs["ortho"])
    write_geotiff(root / "overview/ortho.tif", ortho, grid, band_names=("red", "green", "blue", "nir"))
    with timed("  labels"):
        labels = label_product(r, cfg, rngs["labels"])
    write_geotiff(root / "overview/labels.tif", labels, grid, nodata=LABEL_NODATA, band_names=("building",))
    _write_cloud(root / "overview/cloud.ply", dsm, ortho, grid, cfg.overview_cloud_step_px)
    _write_dem(root / "overview/dem.tif", world, grid, cfg, rngs["dem"])

    feats = fp.osm_like(
        world.overview_buildings(),
        world.origin,
        cfg.footprint_shift_m,
        cfg.footprint_missing_fraction,
        cfg.footprint_merged_fraction,
        rngs["footprints"],
    )
    fp.write_geojson(root / "overview/footprints.geojson", feats, cfg.crs)
    fp.write_osm(root / "overview/map.osm", feats, cfg.crs)
    missing = set(world.missing_ids.tolist())
    truth = fp.true_footprints(
        world.buildings, world.origin, {b.id: {"in_overview": b.id not in missing} for b in world.buildings}
    )
    fp.write_geojson(root / "truth/buildings.geojson", truth, cfg.crs)
    return OverviewResult(grid, dsm, DSM_NODATA, cover, [f.geom for f in feats])


def _write_dem(path: Path, world: World, grid: Grid, cfg: SynthConfig, rng: np.random.Generator) -> None:
    """Bare-earth terrain at ``dem_gsd_m`` over the over-view grid's extent, with ``dem_noise_m`` noise."""
    g = cfg.dem_gsd_m
    _, _, e0, _, _, n1 = grid.transform
    w = int(np.ceil(grid.width * grid.gsd_m / g))
    h = int(np.ceil(grid.height * grid.gsd_m / g))
    dem_grid = Grid((g, 0.0, e0, 0.0, -g, n1), w, h, grid.crs)
    rows, cols = np.mgrid[0:h, 0:w]
    xy = dem_grid.pixel_to_world(rows.ravel(), cols.ravel()) - world.origin[:2]
    z = world.terrain(xy[:, 0], xy[:, 1]) + rng.normal(0.0, cfg.dem_noise_m, len(xy))
    write_geotiff(path, z.reshape(h, w).astype(np.float32), dem_grid, band_names=("height",))


def _write_cloud(path: Path, dsm: np.ndarray, ortho: np.ndarray, grid: Grid, step: int) -> None:
    rows, cols = np.mgrid[0 : grid.height : step, 0 : grid.width : step]
    rows, cols = rows.ravel(), cols.ravel()
    z = dsm[rows, cols].astype(np.float64)
    ok = z != DSM_NODATA
    xy = grid.pixel_to_world(rows[ok], cols[ok])
    rgb = np.moveaxis(ortho[:3], 0, -1)[rows[ok], cols[ok]]
    write_ply(path, np.column_stack([xy, z[ok]]), rgb)
