"""street.region_growing: building façade segments of the street cloud (Ling & Qin 2022, street-view segments).

The steps (``RegionGrowing._segment``) live in ``toolkit/street``: levelling (``frame.py``), Morton
order and voxels (``order.py``), normals, the vertical (``vertical.py``), the façade rule (``facade.py``),
segments (``segments.py``: growing, terrace split, merge, size filter, absorption), association and
output. Helpers own their parameter groups; old flat keys still work (``split_window_m`` → ``split.window_m``).

Why a voxel default: at full resolution the k = 20 neighbourhoods of the 0.13 m-spaced synthetic
campus cloud span ~0.3 m, too little against its 3-10 cm MVS noise; normals scatter, growing
fragments walls and the façade recall drops to 0.34 (0.90 at 0.3 m). The reduction also keeps
the stage within 3x the cloud's memory; ``voxel_m: 0`` analyses every point.
"""

from __future__ import annotations

import contextlib
import logging
from typing import Any

import numpy as np
from pydantic import Field

from toolkit.capture import StreetCapture
from toolkit.stage import Stage, StageParams
from toolkit.street.absorb import AbsorbConfig
from toolkit.street.associate import associate
from toolkit.street.clock import StepClock
from toolkit.street.facade import FacadeConfig, MultiscaleConfig, find_facade
from toolkit.street.frame import levelling, local_origin, pre_levelling, valid_points
from toolkit.street.growing import GrowingConfig
from toolkit.street.merge import MergeConfig
from toolkit.street.normals import open3d_normals, orient_upwards
from toolkit.street.order import prepare
from toolkit.street.outline import BoundaryConfig
from toolkit.street.output import debug_views, street_segments
from toolkit.street.params import GroupedParams, group
from toolkit.street.segments import facade_segments
from toolkit.street.split import SplitConfig
from toolkit.street.vertical import VerticalConfig
from toolkit.threads import single_threaded_blas
from toolkit.types import Scene, StreetSegments

log = logging.getLogger("crossview.street")
WHO = "steps.street (street.region_growing)"


class RegionGrowingParams(GroupedParams):
    knn: int = Field(20, ge=3, le=200, description="neighbours for PCA normals and the façade neighbour test")
    multiscale: MultiscaleConfig = group(MultiscaleConfig, "the façade rule voted over several k")
    facade: FacadeConfig = group(FacadeConfig, "façade points: steep normals with steep neighbours")
    ground_angle_deg: float = Field(15.0, gt=0, lt=90, description="ground: normal within this of vertical (degrees)")
    growing: GrowingConfig = group(GrowingConfig, "region growing: façade kNN graph, smoothness, bends")
    split: SplitConfig = group(SplitConfig, "terrace split: cut rows of houses where the façade top steps")
    merge: MergeConfig = group(MergeConfig, "merge walls meeting at a corner and pieces of one wall")
    min_diameter_m: float = Field(5.0, ge=0, description="drop segments narrower than this horizontally (m)")
    min_height_m: float = Field(
        2.5, ge=0, description="drop segments whose points span less than this vertically (cars, fences)")
    min_points: int = Field(30, ge=1, description="drop segments with fewer analysis points")
    absorb: AbsorbConfig = group(AbsorbConfig, "leftover façade points joining an adjacent segment")
    association_radius_m: float = Field(
        50.0, gt=0, description="points farther than this (2D) from every segment get carrier -1")
    voxel_m: float = Field(0.3, ge=0, description="voxel size of the analysis cloud (0 = every point); "
                                                  "labels are carried back to every input point")
    vertical: VerticalConfig = group(VerticalConfig, "the vertical from the sphere histogram of the normals")
    boundary: BoundaryConfig = group(BoundaryConfig, "boundary points: façade points thinned per segment")
    keep_normals: bool = Field(True, description="return per-point normals (N,3) float32")
    seed: int = Field(0, description="seed of the random subsampling")


class RegionGrowing(Stage):
    """Street-view building segments by normals, vertical histogram and region growing.

    Output (``StreetSegments``): ``origin`` the median of the cloud; ``up_rotation`` levels it
    (minimal rotation, so the levelled yaw follows the input's); ``point_labels`` segment index /
    -1 ground / -2 other, in input order (points of one voxel share their voxel's label);
    ``carrier`` the segment every point moves with (-1 beyond ``association_radius_m``);
    ``boundary_xy`` façade points in the levelled frame at z = 0, one per ``boundary.cell_m`` cell,
    at most ``boundary.max_points``; ``normals`` upward-oriented unit normals in the input frame
    (the voxel's), or None with ``keep_normals: false``.

    Bad inputs: an empty or all non-finite cloud, fewer points than knn + 1, all points on a line,
    or normals with no dominant orientation (support below ``vertical.min_support``) raise
    ``StageError`` (one line). Non-finite rows are ignored with a warning (label -2, carrier -1, NaN
    normal). A cloud with no façade segment (e.g. only ground) gives an empty result and a warning.
    """

    kind = "street"
    name = "region_growing"
    Params = RegionGrowingParams

    @classmethod
    def scene_needs(cls, params: StageParams) -> tuple[str, ...]:
        return ("street_cloud",)

    def __call__(self, scene: Scene, capture: StreetCapture, obs: Any) -> StreetSegments:
        return self.segment(capture.points, obs)

    def segment(self, points: np.ndarray, obs: Any) -> StreetSegments:
        """Segment an (N,3) cloud given as an array (the scene-free entry point); seconds per step go to
        ``obs`` (``timings/<step>``). BLAS threads gain nothing on (N,3) @ (3,3) and lose ~25x under load."""
        with single_threaded_blas(), contextlib.closing(StepClock(obs, "street")) as clock:
            return self._segment(points, obs, clock)

    def _segment(self, points: np.ndarray, obs: Any, clock: StepClock) -> StreetSegments:
        p: RegionGrowingParams = self.params  # type: ignore[assignment]
        # 1. finite points, local origin; Morton order and voxels on a grid levelled by a coarse pass
        pts, finite = valid_points(points, obs, WHO)
        scales = p.multiscale.scales(p.knn)
        origin = local_origin(pts, max(scales + [p.knn]), p.seed, WHO)
        pre = pre_levelling(pts, origin, p.voxel_m, p.knn, p.vertical, p.seed, WHO)
        cloud = prepare(pts, origin, p.voxel_m, WHO, rotation=pre if p.voxel_m > 0 else None)
        del pts
        clock.lap("order")
        # 2. PCA normals at every scale the façade rule votes over
        normals = open3d_normals(cloud.points, p.knn)
        per_scale = [normals if k == p.knn else open3d_normals(cloud.points, k) for k in scales]
        clock.lap("normals")
        # 3. the vertical and the rotation levelling the analysis frame
        level = levelling(cloud.points, normals, pre, p.vertical, p.seed, obs, WHO)
        clock.lap("vertical")
        # 4. façade points (and their neighbour graph)
        facade = find_facade(cloud.points, per_scale, p.knn, level.up, p.facade, p.multiscale,
                             graph_k=min(p.growing.graph_knn, p.knn))
        del per_scale
        clock.lap("facade")
        # 5. façade segments: grow, split terraces, merge, drop the small, absorb leftovers
        segments = facade_segments(cloud.points, normals, facade, level.rotation, growing=p.growing, split=p.split,
                                   merge=p.merge, absorb=p.absorb, min_diameter_m=p.min_diameter_m,
                                   min_height_m=p.min_height_m, min_points=p.min_points)
        del facade
        clock.lap("growing")
        # 6. ground, and the segment every point moves with
        orient_upwards(normals, level.rotation[2])
        association = associate(cloud.points, normals, level.rotation, segments, p.ground_angle_deg,
                                p.association_radius_m)
        clock.lap("associate")
        # 7. the output, in input order
        if segments.count == 0:
            obs.warn(f"no façade segment found (none ≥ min_diameter_m={p.min_diameter_m}, "
                     f"min_height_m={p.min_height_m}); street segments are empty")
        if obs.wants_debug:
            debug_views(obs, cloud.points, level.rotation, association.labels, p.seed)
        n_analysed, inverse = len(cloud.points), cloud.inverse
        del cloud  # the outputs below are the stage's largest arrays
        normals = normals @ pre.astype(np.float32) if p.keep_normals else None  # back to the input frame
        out = street_segments(origin, level.rotation @ pre, inverse, finite, segments, association, normals, p.boundary)
        clock.lap("output")
        log.debug("street.region_growing: %d points (%d analysed), %d segments; %s",
                  len(points), n_analysed, segments.count, clock)
        return out
