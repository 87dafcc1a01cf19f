"""overview.label_map — building segments from a GeoTIFF class map (Ling & Qin 2022, over-view segments).

Pixels equal to ``building_class`` (no-data pixels excluded) → thin-structure and
small-component cleanup → connected components → segments of at least ``min_diameter_m``.
When the scene has a DSM it gives the terrain around each segment.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import Field

from toolkit.errors import SceneError, StageError
from toolkit.observe import DebugImage
from toolkit.overview.inputs import dsm_on_grid
from toolkit.overview.mask import clean_mask, mask_to_labels
from toolkit.overview.segments import build_segments, colour_segments
from toolkit.scene import load_raster
from toolkit.stage import Stage, StageParams
from toolkit.types import OverviewSegments, Scene


class LabelMap(Stage):
    """Building segments from the building class of a GeoTIFF class map."""

    kind = "overview"
    name = "label_map"

    class Params(StageParams):
        building_class: int = Field(1, description="class value of building pixels")
        band: int = Field(1, ge=1, description="band of the class map holding the classes (1-based index)")
        thin_radius_m: float = Field(1.0, ge=0, description=(
            "radius of the binary opening that removes thin misclassified structures (m)"))
        min_area_m2: float = Field(20.0, ge=0, description="components smaller than this are removed (m²)")
        max_hole_m2: float = Field(50.0, ge=0, description="enclosed holes smaller than this are filled (m²)")
        min_diameter_m: float = Field(5.0, ge=0, description="segments under this maximum Feret diameter are dropped (m)")
        connectivity: Literal[4, 8] = Field(4, description="pixel connectivity of the components")
        ground_from_dsm: bool = Field(True, description="terrain height/normal around segments from the DSM when present")
        ring_inner_m: float = Field(1.0, ge=0, description="ground ring starts this far from any building (m)")
        ring_outer_m: float = Field(6.0, gt=0, description="ground ring ends this far from the segment (m)")

    @classmethod
    def scene_needs(cls, params: StageParams) -> tuple[str, ...]:
        return ("labels",)

    def __call__(self, scene: Scene, obs: Any) -> OverviewSegments:
        p = self.params
        who = self.key()
        raster = load_raster(scene, "labels", who)
        path = scene.files.labels
        if p.band > raster.data.shape[0]:
            raise SceneError(f"{path}: {who} params.band = {p.band} but the file has {raster.data.shape[0]} band(s)")
        classes = raster.data[p.band - 1]
        if classes.dtype.kind == "f" and not np.all(np.isnan(classes) | (classes == np.round(classes))):
            raise SceneError(f"{path}: class map has non-integer values (is it a class map?)")
        grid = raster.grid
        mask = (classes == p.building_class) & ~raster.nodata_mask
        if not mask.any():
            present = np.unique(classes[~raster.nodata_mask])[:10]
            raise StageError(f"{path}: no pixel of building class {p.building_class} "
                             f"(classes present: {', '.join(str(v) for v in present) or 'none'})")
        mask = clean_mask(mask, grid.gsd_m, p.thin_radius_m, p.max_hole_m2)
        labels, n, boundary = mask_to_labels(mask, grid.gsd_m, p.min_area_m2, p.min_diameter_m,
                                             p.connectivity)
        if n == 0:
            raise StageError(f"{path}: no building segment of at least {p.min_diameter_m} m after cleanup")
        if obs.wants_debug:
            obs.debug("labels", DebugImage(classes.astype(np.int32), "segmentation"))
            obs.debug("mask", DebugImage(labels >= 0, "mask"))
            obs.debug("segments_coloured", DebugImage(colour_segments(labels), "rgb"))
        dsm = dsm_on_grid(scene, who, grid) if p.ground_from_dsm else None
        return build_segments(labels, np.arange(1, n + 1), grid, who, boundary=boundary,
                              dsm=None if dsm is None else dsm[0], dsm_valid=None if dsm is None else dsm[1],
                              ring_inner_m=p.ring_inner_m, ring_outer_m=p.ring_outer_m)
