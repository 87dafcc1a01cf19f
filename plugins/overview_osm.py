"""overview.osm — building segments from footprints: GeoJSON, OSM XML or OSM PBF (Ling & Qin 2022, over-view segments).

Polygons are projected to the scene CRS and rasterised (pixel-centre rule) on the scene grid —
the DSM's, else the ortho's or the label map's — or, when the scene has no raster, on a grid of
``gsd_m`` around the footprints. Buildings under ``min_diameter_m`` are dropped; touching
buildings can be merged. When a DSM is present it gives the terrain around each segment.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np
import shapely
from pydantic import Field

from toolkit.errors import SceneError, StageError
from toolkit.io.vector import read_footprints
from toolkit.observe import DebugImage
from toolkit.overview.footprints import feret_diameters_m, merge_groups, rasterise, touching_groups
from toolkit.overview.inputs import dsm_on_grid, grid_from_bounds, scene_grid
from toolkit.overview.segments import build_segments, colour_segments, relabel
from toolkit.scene import need
from toolkit.stage import Stage, StageParams
from toolkit.types import Grid, OverviewSegments, Scene


class OsmFootprints(Stage):
    """Building segments from footprint polygons (GeoJSON, OSM XML, OSM PBF) rasterised on the grid."""

    kind = "overview"
    name = "osm"

    class Params(StageParams):
        source: Literal["auto", "geojson", "osm"] = Field("auto", description=(
            "footprint file: geojson (overview.footprints), osm "
            "(.osm/.osm.pbf) or auto (footprints if named, else osm)"))
        gsd_m: float = Field(0.5, gt=0, description="pixel size of the grid used when the scene has no raster")
        margin_m: float = Field(20.0, ge=0, description="margin around the footprints of that grid (m)")
        min_diameter_m: float = Field(5.0, ge=0, description="buildings under this maximum Feret diameter are dropped (m)")
        merge_touching: bool = Field(False, description="merge buildings that touch (terraces, blocks) into one segment")
        touch_tolerance_m: float = Field(0.2, ge=0, description="gap up to which buildings count as touching")
        all_touched: bool = Field(False, description="burn every pixel a polygon touches (default: pixel centres inside)")
        align_to_dsm: bool = Field(False, description=(
            "shift each footprint by whole pixels, up to align_search_m, onto "
            "the raised area of the scene DSM (needs overview.dsm)"))
        align_search_m: float = Field(3.0, ge=0, description="largest shift tried by align_to_dsm (m)")
        ground_from_dsm: bool = Field(True, description="terrain height/normal around segments from the DSM when present")
        ring_inner_m: float = Field(1.0, ge=0, description="ground ring starts this far from any building (m)")
        ring_outer_m: float = Field(6.0, gt=0, description="ground ring ends this far from the segment (m)")

    @classmethod
    def scene_needs(cls, params: StageParams) -> tuple[str, ...]:
        source = getattr(params, "source", "auto")
        files = {"geojson": ("footprints",), "osm": ("osm",)}.get(source, ("footprints|osm",))
        return files + (("dsm",) if getattr(params, "align_to_dsm", False) else ())

    def __call__(self, scene: Scene, obs: Any) -> OverviewSegments:
        p = self.params
        who = self.key()
        path = self._source_path(scene)
        fp = read_footprints(path, scene.crs)
        if fp.repaired:
            obs.warn(f"{path.name}: {fp.repaired} invalid polygon(s) repaired with make_valid")
        if fp.skipped:
            obs.warn(f"{path.name}: {len(fp.skipped)} feature(s) skipped, first: {fp.skipped[0]}")
        if len(fp) == 0:
            raise SceneError(f"{path}: no building polygons")
        order = np.argsort(fp.ids, kind="stable")  # segment order independent of the file format
        geoms, ids = fp.geometries[order], fp.ids[order]
        if p.merge_touching and len(geoms) > 1:
            geoms, ids = merge_groups(geoms, ids, touching_groups(geoms, p.touch_tolerance_m), p.touch_tolerance_m)
        big = feret_diameters_m(geoms) >= p.min_diameter_m
        if not big.any():
            raise StageError(f"{who}: all {len(geoms)} buildings of {path} are under min_diameter_m = "
                             f"{p.min_diameter_m} m")
        geoms, ids = geoms[big], ids[big]
        grid = scene_grid(scene, who) or grid_from_bounds(tuple(shapely.total_bounds(geoms)), p.gsd_m,
                                                          scene.crs, p.margin_m)
        labels = rasterise(geoms, grid, p.all_touched)
        if p.align_to_dsm:
            geoms, labels = self._align(scene, grid, geoms, labels, obs)
        present = np.bincount(labels[labels >= 0], minlength=len(geoms)) > 0
        if not present.any():
            raise StageError(f"{who}: none of the {len(fp)} buildings of {path} (≥ {p.min_diameter_m} m) "
                             f"falls on the scene grid")
        labels = relabel(labels, present)
        geoms, ids = geoms[present], ids[present]
        if obs.wants_debug:
            obs.debug("mask", DebugImage(labels >= 0, "mask"))
            obs.debug("segments_coloured", DebugImage(colour_segments(labels), "rgb"))
        dsm = dsm_on_grid(scene, who, grid) if p.ground_from_dsm else None
        if obs.wants_debug and dsm is not None:
            obs.debug("dsm", DebugImage(np.where(dsm[1], dsm[0], np.nan), "depth"))
        return build_segments(labels, ids, grid, who, polygons=tuple(geoms),
                              dsm=None if dsm is None else dsm[0], dsm_valid=None if dsm is None else dsm[1],
                              ring_inner_m=p.ring_inner_m, ring_outer_m=p.ring_outer_m)

    def _align(self, scene: Scene, grid: Grid, geoms: np.ndarray, labels: np.ndarray,
               obs: Any) -> tuple[np.ndarray, np.ndarray]:
        from toolkit.overview.align import dsm_building_evidence, footprint_shifts, shift_geometries

        p = self.params
        need(scene, "dsm", f"{self.key()} with align_to_dsm")
        z, valid = dsm_on_grid(scene, self.key(), grid)
        evidence = dsm_building_evidence(z, valid, grid)
        shifts = footprint_shifts(labels, len(geoms), evidence, round(p.align_search_m / grid.gsd_m))
        moved = shifts.any(axis=1)
        if obs.wants_debug:
            obs.debug("dsm_evidence", DebugImage(evidence, "mask"))
        if not moved.any():
            return geoms, labels
        obs.warn(f"align_to_dsm moved {int(moved.sum())} of {len(geoms)} footprints "
                 f"(median {np.median(np.hypot(*shifts[moved].T)) * grid.gsd_m:.2f} m)")
        geoms = shift_geometries(geoms, shifts, grid)
        return geoms, rasterise(geoms, grid, p.all_touched)

    def _source_path(self, scene: Scene) -> Path:
        source = self.params.source
        if source == "auto":
            if not (scene.has("footprints") or scene.has("osm")):
                raise SceneError(f"{self.key()} needs overview.footprints or overview.osm, which "
                                 f"{scene.root / 'scene.yaml'} does not name")
            source = "geojson" if scene.has("footprints") else "osm"
        return need(scene, "footprints" if source == "geojson" else "osm", self.key())
