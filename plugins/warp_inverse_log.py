"""warp.inverse_log — paper Eq. 6: distance-weighted blending of the segment transforms.

Every street point and every camera pose is moved by the weighted average of the transforms of its
segment and that segment's K nearest valid neighbours (``neighbours_k`` for points,
``camera_neighbours_k`` for cameras), ``w = 1/log(d)`` with d the horizontal
distance to each segment's footprint, clamped to ``min_distance_m`` because log(d) ≤ 0 for
d ≤ 1 m; a camera's weights are also multiplied by size / (size + arm) of each footprint
(``camera_lever_arm``: a small fragment's rotation error is large at a camera far from it).
Rotations are averaged as quaternions (principal eigenvector), translations about the point
itself (``toolkit.warp.blend``). Points without a valid carrier segment are anchored on the
nearest valid segment: every input point is moved, in input order. A camera is anchored on the
segment it observes most (``toolkit.warp.apply``). Neighbours whose transform disagrees with the
anchor's, or captured farther than ``pass_gap_m`` from it along the route (another pass of the route
after a loop), are left out of the blend, and a point captured on
another pass of the route than its segment is re-anchored on a segment of its own pass
(``toolkit.warp.passes``). The weights are evaluated once per ``weight_cell_m`` cell (speed).
Distances may be measured from the point's nearest segment (``relative_distance``), and each camera
carries the spread of the transforms blended at it (``Registration.camera_spread_m``: the bundle
adjustment holds uncertainly placed cameras more loosely). Cameras that see no registered façade
follow the street trajectory between those that do (``bridge_min_observations``,
``toolkit.warp.bridge``, docs/camera_bridge.md).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from toolkit.capture import StreetCapture
from toolkit.stage import Stage, StageParams
from toolkit.types import Registration, Scene, SegmentTransforms, StreetSegments
from toolkit.warp.apply import PassCheck, warp_scene


class InverseLog(Stage):
    """Paper Eq. 6: blend each point's and camera's segment transform with its neighbours', w = 1/log d."""

    kind = "warp"
    name = "inverse_log"

    class Params(StageParams):
        neighbours_k: int = Field(
            6, ge=1, le=64,
            description="Neighbouring segments blended into each street point with "
                        "its own segment (count; the paper's graph uses 4)")
        camera_neighbours_k: int = Field(
            4, ge=0, le=64,
            description="Neighbouring segments blended into each camera pose with its "
                        "anchor segment (count; 0: the anchor's transform alone)")
        camera_lever_arm: bool = Field(
            True, description="Also weigh each transform blended at a camera by its footprint's size over that "
                              "size plus the camera's distance from the footprint's centre (off: 1/log d alone)")
        min_distance_m: float = Field(
            10.0, gt=1.0,
            description="Lower clamp on the distance d in the 1/log d blending weight "
                        "(m, > 1): segments closer than this weigh alike")
        relative_distance: bool = Field(
            False, description="Measure d from the point's nearest segment (d − d_nearest, "
                               "then clamped) instead of the paper's absolute d")
        max_neighbour_gap_m: float | None = Field(
            None, gt=0, description="Neighbours farther than this from the segment, footprint to "
                                    "footprint, are not blended (m; None: any distance)")
        neighbour_gap_m: float = Field(
            3.0, gt=0, description="Blend a neighbour only if both transforms agree on the two "
                                   "centres within this (m) + neighbour_gap_ratio × distance")
        neighbour_gap_ratio: float = Field(
            0.05, ge=0, description="Share of the centres' distance added to "
                                    "neighbour_gap_m in that agreement check (unitless)")
        weight_cell_m: float = Field(
            0.5, gt=0, le=5.0,
            description="Blending weights are computed once per horizontal cell of this size, at its centre (m)")
        pass_gap_m: float | None = Field(
            200.0, gt=0,
            description="Route distance (m) beyond which a point, neighbour or camera "
                        "vote is on another pass (None: off; needs COLMAP)")
        pass_sparse_gap_m: float = Field(
            10.0, gt=0, description="Only sparse points within this distance of a "
                                    "street point give it a route position (m)")

        bridge_min_observations: int = Field(
            10, ge=0, description="A camera observing fewer registered façade points than this follows the "
                                 "street trajectory between those that do, not the blend (count; 0: off)")
        bridge_min_gap_m: float = Field(
            100.0, ge=0, description="Only stretches of the route at least this long between such cameras are bridged (m)")

    @classmethod
    def scene_needs(cls, params) -> tuple[str, ...]:
        return ("street_cloud",)

    def __call__(self, transforms: SegmentTransforms, street: StreetSegments, scene: Scene, capture: StreetCapture,
                 obs) -> Registration:
        p = self.params
        return warp_scene(transforms, street, capture, p.neighbours_k, p.min_distance_m, p.neighbour_gap_m,
                          p.neighbour_gap_ratio, np.inf if p.max_neighbour_gap_m is None else p.max_neighbour_gap_m,
                          p.weight_cell_m, PassCheck(p.pass_gap_m, p.pass_sparse_gap_m),
                          relative=p.relative_distance, camera_k=p.camera_neighbours_k,
                          bridge_min_observations=p.bridge_min_observations,
                          bridge_min_gap_m=p.bridge_min_gap_m, camera_lever=p.camera_lever_arm)
