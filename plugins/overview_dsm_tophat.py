"""overview.dsm_tophat — building segments from a DSM and a multispectral ortho (Ling & Qin 2022, over-view segments).

White top-hat of the DSM → height threshold → minus vegetation (NDVI) and shadow (shadow
index) → half-height edges → thin-structure and small-component cleanup → connected components
→ segments whose maximum Feret diameter reaches ``min_diameter_m`` and whose outline is a wall
(median DSM slope ≥ ``wall_slope_min``: a 3 m wall blurred over 1 m is still ~2 m/m, dunes and
embankments narrower than the top-hat stay under 0.7).

A fixed height threshold puts the edge of a blurred DSM where the blur falls to that height:
outside the wall by a distance that grows with the building's height, and across the 1–2 m
gaps between neighbours, which merges them. Keeping only pixels at least half as high as the
highest candidate nearby puts edges at half height (the wall, for a symmetric blur) and cuts
those gaps. The cost: a low wing within ``edge_radius_m`` of a part more than twice as tall loses
that strip.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import Field

from toolkit.errors import StageError
from toolkit.observe import DebugImage
from toolkit.overview.inputs import check_ortho_bands, load_dsm, load_ortho
from toolkit.overview.mask import clean_mask, mask_to_labels
from toolkit.overview.segments import build_segments, colour_segments, relabel
from toolkit.overview.tophat import (
    boundary_slopes,
    brightness_reference,
    fill_nodata_low,
    half_height_edges,
    ndvi,
    shadow_index,
    white_tophat,
)
from toolkit.stage import Stage, StageParams
from toolkit.types import OverviewSegments, Scene


class DsmTophat(Stage):
    """Building segments from a DSM white top-hat, minus vegetation (NDVI) and shadow."""

    kind = "overview"
    name = "dsm_tophat"

    class Params(StageParams):
        tophat_radius_m: float = Field(40.0, gt=0, description=(
            "half-size of the top-hat's flat structuring element; must "
            "exceed every building's inscribed half-width (m)"))
        footprint: Literal["square", "disk"] = Field("square", description=(
            "structuring element: square (separable, time independent of the radius) or disk (time grows with it)"))
        height_min_m: float = Field(2.5, gt=0, description="minimum top-hat height of a building pixel")
        edge_fraction: float = Field(0.5, ge=0, lt=1, description=(
            "a building pixel needs this share of the highest top-hat within edge_radius_m (0-1; 0 disables)"))
        edge_radius_m: float = Field(2.0, gt=0, description="neighbourhood of that local maximum (m)")
        step_fraction: float = Field(1.0, ge=0, description=(
            "keep pixels cut by edge_fraction with at least this share "
            "of the lowest roof nearby (unitless; 0 disables)"))
        wall_slope_min: float = Field(0.8, ge=0, description=(
            "segments whose outline's median DSM slope is below this are terrain, not buildings (m/m; 0 disables)"))
        ndvi_max: float = Field(0.3, description="pixels with NDVI above this are vegetation and removed")
        shadow_index_max: float | None = Field(None, description=(
            "pixels darker than this shadow index (0 bright .. 1 black) are removed; None keeps them"))
        use_ortho: bool = Field(True, description="use the ortho for NDVI/shadow (False: DSM only)")
        bands: tuple[str, ...] | None = Field(None, description=(
            "ortho band roles in file order, e.g. [red, green, blue, nir]; "
            "overrides the band descriptions (None: read them)"))
        thin_radius_m: float = Field(1.0, ge=0, description=(
            "radius of the binary opening that removes walls, fences and branches (m)"))
        min_area_m2: float = Field(20.0, ge=0, description="components smaller than this are removed (m²)")
        max_hole_m2: float = Field(50.0, ge=0, description="enclosed holes smaller than this are filled (m²)")
        min_diameter_m: float = Field(5.0, ge=0, description="segments under this maximum Feret diameter are dropped (m)")
        connectivity: Literal[4, 8] = Field(4, description="pixel connectivity of the components")
        ring_inner_m: float = Field(1.0, ge=0, description="ground ring starts this far from any building (m)")
        ring_outer_m: float = Field(6.0, gt=0, description="ground ring ends this far from the segment (m)")

    @classmethod
    def scene_needs(cls, params: StageParams) -> tuple[str, ...]:
        return ("dsm", "ortho") if getattr(params, "use_ortho", True) else ("dsm",)

    def check_scene(self, scene: Scene) -> None:
        if self.params.use_ortho:
            check_ortho_bands(scene, self.key(), self.params.bands, ("red", "nir"))

    def __call__(self, scene: Scene, obs: Any) -> OverviewSegments:
        p = self.params
        who = self.key()
        z, valid, grid = load_dsm(scene, who)
        if not valid.any():
            raise StageError(f"{scene.files.dsm}: DSM has no valid pixel")
        gsd = grid.gsd_m
        radius_px = max(1, round(p.tophat_radius_m / gsd))
        z_filled = fill_nodata_low(z, valid)
        tophat = white_tophat(z_filled, radius_px, p.footprint)
        mask = (tophat >= p.height_min_m) & valid
        if obs.wants_debug:
            obs.debug("dsm", DebugImage(np.where(valid, z, np.nan), "depth"))
            obs.debug("tophat", DebugImage(np.where(valid, tophat, np.nan), "depth"))
        if p.use_ortho:
            mask = self._remove_vegetation_and_shadow(scene, grid, mask, obs)
        if p.edge_fraction > 0:
            mask = half_height_edges(tophat, mask, p.edge_fraction, max(1, round(p.edge_radius_m / gsd)),
                                     p.step_fraction)
        mask = clean_mask(mask, gsd, p.thin_radius_m, p.max_hole_m2)
        labels, n, boundary = mask_to_labels(mask, gsd, p.min_area_m2, p.min_diameter_m, p.connectivity)
        if p.wall_slope_min > 0 and n:
            walls = boundary_slopes(z_filled, boundary, gsd) >= p.wall_slope_min
            labels, n = relabel(labels, walls), int(walls.sum())
            boundary = tuple(b for b, k in zip(boundary, walls) if k)
        if n == 0:
            raise StageError(f"{who}: no building found in {scene.files.dsm} (top-hat ≥ {p.height_min_m} m, "
                             f"NDVI ≤ {p.ndvi_max}, diameter ≥ {p.min_diameter_m} m)")
        if obs.wants_debug:
            obs.debug("mask", DebugImage(labels >= 0, "mask"))
            obs.debug("segments_coloured", DebugImage(colour_segments(labels), "rgb"))
        return build_segments(labels, np.arange(1, n + 1), grid, who, boundary=boundary, dsm=z, dsm_valid=valid,
                              ring_inner_m=p.ring_inner_m, ring_outer_m=p.ring_outer_m)

    def _remove_vegetation_and_shadow(self, scene: Scene, grid: Any, mask: np.ndarray, obs: Any) -> np.ndarray:
        """Drop NDVI > ndvi_max and (optionally) shadow pixels from the candidates. Indices are
        computed on the candidate pixels only (all pixels when the viewer wants the masks)."""
        p = self.params
        bands, ortho_valid = load_ortho(scene, self.key(), p.bands, grid, ("red", "nir"))
        where = slice(None) if obs.wants_debug else np.nonzero(mask)
        red, nir = bands["red"][where], bands["nir"][where]
        drop = (ndvi(red, nir) > p.ndvi_max) & ortho_valid[where]
        if obs.wants_debug:
            obs.debug("ndvi_mask", DebugImage(drop, "mask"))
        if p.shadow_index_max is not None:
            darkness = shadow_index({k: b[where] for k, b in bands.items()}, brightness_reference(bands, ortho_valid))
            shadow = (darkness > p.shadow_index_max) & ortho_valid[where]
            if obs.wants_debug:
                obs.debug("shadow_mask", DebugImage(shadow, "mask"))
            drop |= shadow
        out = mask.copy()
        out[where] &= ~drop
        return out
