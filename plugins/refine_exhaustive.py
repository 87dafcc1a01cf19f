"""refine.exhaustive — the paper's fine registration (§3.3.2, Eq. 5), one street segment at a time.

For every matched segment:
1. 3D tilt: the segment's street ground normal (ground normals within [15°] of vertical,
   median-filtered) is rotated onto the over-view ground normal around it (a plane fitted to the
   DSM / over-view cloud heights under the street ground points; level when neither exists).
2. 2D: exhaustive search of rotation within ±[10°] at [1°] and of every one-pixel offset that keeps
   the footprint inside the over-view segment's window (its bounding box plus a margin), on the
   chamfer distance to the over-view segment's outline; then sub-pixel refinement
   (``toolkit.refine.search2d``). A small penalty per metre of shift keeps the match's position
   where the outline cannot fix it (a single straight wall slides along itself at equal cost).
3. Height: t_z = robust difference between over-view and street ground heights (10–60 % slice).
4. Eq. 5: T = [[R2d, 0], [0, 1]]·R_Z, t = [t2d | t_z] (R_Z about the segment's ground centre),
   composed with the levelling so that T maps the INPUT street frame to the scene CRS.
Then a segment whose transform disagrees strongly with its neighbours' is rejected
(``consistency``, ``toolkit.refine.consistency``) and left to the warp to carry with its neighbours; with the route
position of each segment (from the COLMAP model, ``toolkit.refine.route``) neighbours are those
near in space AND along the route, and a run of wrong matches is outvoted along the route.
Beyond the paper: segments left without a match (or whose match was rejected) are placed by their
registered neighbours and searched against every over-view outline around them
(``toolkit.refine.propagate``); they must pass the same inlier and consistency tests. Then every
segment is searched once more, seeded by its neighbours (``neighbour_passes``): along a single
straight wall the outline cannot place a segment, its neighbours can.
Finally (``joint.window_m`` > 0, route-aware), each segment's 2D transform is re-estimated by
registering together the footprints of all segments captured within that distance along the route
(``toolkit.refine.joint``): the per-building errors of the over-view outlines (OSM digitising
offsets, label-map edges) average out over several buildings, and other buildings' corners fix the
position along straight walls. A segment with no other in its window keeps its own transform (a
re-fit would be its own search again, without the shift penalty). With ``rotation_window_m`` > 0,
each segment's rotation is then the mean of its route neighbours' (``toolkit.refine.rotation``),
turned about its own footprint centre: a compact façade fixes its rotation weakly, and the ground
it carries far from it follows that error.
Before the neighbour passes, each segment gets a scale (``scale``, ``toolkit.refine.scale``): the
ratio of its registered to its input distance from the segments captured near it along the route,
within 1 ± ``scale.max_deviation``; the later passes search its footprint at that scale, so the
transforms are similarities (monocular SfM drifts slowly in scale, which rigid segments cannot follow).
"""

from __future__ import annotations

from pydantic import Field

from toolkit.capture import StreetCapture
from toolkit.params import GroupedParams, group
from toolkit.refine.finish import ConsistencyParams, warn_rejected
from toolkit.refine.ground3d import GroundParams, height_source
from toolkit.refine.joint import JointConfig
from toolkit.refine.passes import (Placement, Refinement, checked, finished, matched_items, neighbour_pass,
                                   propagate, register, route_pass, set_scales)
from toolkit.refine.scale import ScaleConfig
from toolkit.refine.search2d import SearchParams
from toolkit.scene import overview_heights
from toolkit.stage import Stage, StageParams
from toolkit.threads import single_threaded_blas
from toolkit.types import Matches, OverviewSegments, Scene, SegmentTransforms, StreetSegments


class ExhaustiveParams(GroupedParams):
    search: SearchParams = group(SearchParams, "the exhaustive 2D rotation/offset search and its sub-pixel step")
    footprint_cell_m: float = Field(0.25, gt=0, description="façade points are thinned to one per cell of this size "
                                                            "before the search (metres)")
    max_footprint_points: int = Field(4000, ge=10, description="at most this many footprint points per segment")
    ground: GroundParams = group(GroundParams, "the 3D tilt (ground normals) and height step")
    min_inlier_ratio: float = Field(0.2, ge=0, le=1, description="a segment whose footprint has a smaller inlier "
                                                                 "share after the search is rejected")
    consistency: ConsistencyParams = group(ConsistencyParams, "reject segments disagreeing with their neighbours")
    route_aware: bool = Field(True, description="find neighbours by position and by position along the route (from "
                                                "COLMAP), so another pass's segments are not neighbours")
    propagate: bool = Field(True, description="also register unmatched segments, seeded by registered neighbours' "
                                              "transforms, against every outline near them")
    propagated_confidence: float = Field(0.5, ge=0, le=1, description="confidence factor of a segment registered "
                                                                      "by propagation (times its inlier share)")
    neighbour_passes: int = Field(1, ge=0, le=5, description="extra passes re-searching every registered segment "
                                                             "from its neighbours' blended transforms (count; 0: the paper's one)")
    prior_k: int = Field(8, ge=1, description="neighbours blended into that seed (count; weights 1/log d)")
    joint: JointConfig = group(JointConfig, "the joint pass: each segment re-fitted with its route neighbours")
    rotation_window_m: float = Field(0.0, ge=0, description="set each rotation to the weighted mean rotation of "
                                                            "segments within this route distance (m; route-aware only; 0: off)")
    scale: ScaleConfig = Field(default_factory=ScaleConfig,
                               description="per-segment scale from the route neighbours (route-aware only)")


class Exhaustive(Stage):
    """Paper §3.3.2: exhaustive 2D rotation/offset search + 3D ground normal and height step (Eq. 5)."""

    kind = "refine"
    name = "exhaustive"
    Params = ExhaustiveParams

    @classmethod
    def scene_needs(cls, params: StageParams) -> tuple[str, ...]:
        return ("street_cloud",)

    def __call__(self, matches: Matches, street: StreetSegments, overview: OverviewSegments, scene: Scene,
                 capture: StreetCapture, obs, graphs=None) -> SegmentTransforms:
        p: ExhaustiveParams = self.params  # type: ignore[assignment]
        with single_threaded_blas():
            heights = height_source(overview_heights(scene, "refine"), overview)
            r = Refinement.of(street, overview, capture, graphs, obs, heights=heights, search=p.search,
                              ground=p.ground, consistency=p.consistency, route_aware=p.route_aware,
                              footprint_cell_m=p.footprint_cell_m, max_footprint_points=p.max_footprint_points,
                              min_inlier_ratio=p.min_inlier_ratio)
            # 1. the matched segments: tilt, exhaustive 2D search, height; then the consistency check
            register(r, matched_items(r, matches))
            placed = checked(r, r.fits.valid)
            warn_rejected(street, r.fits.valid, placed.valid, obs)
            # 2. segments without a surviving match, from their registered neighbours
            if p.propagate:
                placed = propagate(r, placed, p.consistency.k, p.propagated_confidence)
            # 3. scales along the route, then every segment re-searched from its neighbours' seeds
            scaled = p.scale.max_deviation > 0 and r.routed()
            if scaled:
                set_scales(r, placed, p.scale)
            for _ in range(p.neighbour_passes):
                placed = neighbour_pass(r, placed, p.prior_k)
            if scaled and p.neighbour_passes:
                set_scales(r, placed, p.scale)     # again, from the better placed centres
            # 4. joint re-fit and rotation smoothing along the route
            if (p.joint.window_m > 0 or p.rotation_window_m > 0) and r.routed():
                placed = Placement(route_pass(r, placed.valid, p.joint, p.rotation_window_m), placed.valid)
            return finished(r, scene, placed)
