"""warp.nearest — every point takes its own segment's transform, no blending (a baseline for Eq. 6).

A point's own segment is its carrier when that segment is valid, else the nearest valid segment
(by distance to its footprint); a camera takes the transform of the segment it observes most
(else the nearest valid one). A point of another pass of the route than its segment is re-anchored on
a segment of its own pass (``toolkit.warp.passes``).
"""

from __future__ import annotations

from pydantic import Field

from toolkit.capture import StreetCapture
from toolkit.stage import Stage, StageParams
from toolkit.types import Registration, Scene, SegmentTransforms, StreetSegments
from toolkit.warp.apply import PassCheck, warp_scene


class Nearest(Stage):
    """Piecewise-rigid warp without blending: each point and camera takes its nearest segment's transform."""

    kind = "warp"
    name = "nearest"

    class Params(StageParams):
        pass_gap_m: float | None = Field(
            200.0, gt=0,
            description="Route distance (m) beyond which a point or camera counts as "
                        "another pass and is re-anchored on its own pass (None: off)")
        pass_sparse_gap_m: float = Field(
            2.0, gt=0, description="Only sparse points within this distance of a street point give it a route "
                                   "position (metres).")

    @classmethod
    def scene_needs(cls, params) -> tuple[str, ...]:
        return ("street_cloud",)

    def __call__(self, transforms: SegmentTransforms, street: StreetSegments, scene: Scene, capture: StreetCapture,
                 obs) -> Registration:
        p = self.params
        return warp_scene(transforms, street, capture, 0, 2.0, passes=PassCheck(p.pass_gap_m, p.pass_sparse_gap_m))
