"""warp.inverse_log — paper Eq. 6: distance-weighted blending of the segment transforms.

Every street point and every camera pose is moved by the weighted average of the transforms of its
segment and that segment's K nearest valid neighbours (``neighbours_k`` for points,
``camera_neighbours_k`` for cameras), ``w = 1/log(d)`` with d the horizontal
distance to each segment's footprint, clamped to ``min_distance_m`` because log(d) ≤ 0 for
d ≤ 1 m. Rotations are averaged as quaternions (principal eigenvector), translations about the
point itself (``toolkit.warp.blend``). Points without a valid carrier segment are anchored on the
nearest valid segment: every input point is moved, in input order. A camera is anchored on the
segment it observes most (``toolkit.warp.apply``). Neighbours whose transform disagrees with the
anchor's, or captured farther than ``pass_gap_m`` from it along the route (another pass of the route
after a loop), are left out of the blend, and a point captured on
another pass of the route than its segment is re-anchored on a segment of its own pass
(``toolkit.warp.passes``). The weights are evaluated once per ``weight_cell_m`` cell (speed).
Distances may be measured from the point's nearest segment (``relative_distance``), and each camera
carries the spread of the transforms blended at it (``Registration.camera_spread_m``: the bundle
adjustment holds uncertainly placed cameras more loosely).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

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
            description="Valid neighbouring segments blended into each street point with its own segment (the paper's "
                        "graph uses K = 4). Held-out campus seeds 5-10 x 3 over-view sources (18 runs, 10 m clamp), "
                        "K = 4/6/8/10, means: 3D p95 1.089/1.030/1.040/1.038 m (runs above 1.5 m: 3/2/2/4), border p95 "
                        "1.271/1.162/1.151/1.146 m, 3D mean 0.514/0.507/0.521/0.527 m, horizontal median "
                        "0.308/0.310/0.322/0.333 m (DSM alone: 0.159/0.171/0.195/0.219 m, its p95 "
                        "0.999/0.897/0.915/0.898 m).")
        camera_neighbours_k: int = Field(
            4, ge=0, le=64,
            description="Valid neighbouring segments blended into each camera pose with its anchor segment (0: the "
                        "anchor's transform alone). The bundle adjustment holds the cameras near these poses. Held-out "
                        "campus seeds 5-10 x 3 sources (18 runs, neighbours_k 6), 2/3/4: camera-centre median after "
                        "BA 0.308/0.308/0.309 m, mean 0.366/0.364/0.362 m; K = 6 for the cameras too had given a "
                        "median of 0.326 m and left one run's cameras worse than warped.")
        min_distance_m: float = Field(
            10.0, gt=1.0,
            description="Distances are clamped to at least this (metres, > 1 since log d ≤ 0 for d ≤ 1 m): every "
                        "segment within 10 m of a point weighs 1/log 10 = 0.43, one 25 m away 0.31, 100 m away "
                        "0.22. A small clamp lets a point's own façade outweigh every neighbour near it (1/log 1.5 = "
                        "2.5), close to warp.nearest there. Held-out campus seeds 5-10 x 3 sources (18 runs "
                        "with BA), 1.5/6/10 m: horizontal median 0.312/0.308/0.308 m, 3D mean 0.521/0.513/0.513 m, 3D p95 "
                        "1.164/1.096/1.089 m, border p95 1.310/1.283/1.271 m, camera median after BA "
                        "0.308/0.308/0.309 m; without BA, 2-25 m: a plateau from 6 to 15 m.")
        relative_distance: bool = Field(
            False, description="Measure distances from the segment nearest to the point (d − d_nearest, then "
                               "clamped): unchanged on a footprint, but a point far from every footprint (ground, "
                               "the street at a camera) is blended mostly from its nearest segments instead of "
                               "nearly equally from all K + 1 (1/log d barely falls off: 0.27 at 40 m, 0.21 at "
                               "120 m). Off (default): the paper's absolute d. Held-out campus seeds 5-7: lower "
                               "3D mean error in 3 of 4 runs but higher p95 error at segment borders in 3 of 4.")
        max_neighbour_gap_m: float | None = Field(
            None, gt=0, description="Neighbours farther than this from the segment (footprint to footprint, metres) "
                                    "are not blended (None: the K nearest at any distance).")
        neighbour_gap_m: float = Field(
            3.0, gt=0, description="A neighbour blends in only if its transform and the segment's own put both "
                                   "segments' centres within this distance (metres) ...")
        neighbour_gap_ratio: float = Field(
            0.05, ge=0, description="... plus this fraction of their distance (keeps segments of another pass of "
                                    "the route, placed nearby by the drift, out of the blend).")
        weight_cell_m: float = Field(
            0.5, gt=0, le=5.0,
            description="The weights of a point are those of the centre of its horizontal cell of this size (metres): "
                        "one set of footprint distances and one blended transform per cell instead of per point "
                        "(campus, 3.5 M points: 0.5 m moves points by < 0.03 m at the 99th percentile vs exact "
                        "per-point weights; the footprints are themselves thinned to 1 m).")
        pass_gap_m: float | None = Field(
            200.0, gt=0,
            description="A point captured farther than this along the route (metres travelled by the cameras "
                        "observing the sparse point next to it) from its segment is on another pass of the route "
                        "(loop start/end, revisits) and is re-anchored on the nearest segment of its own pass; "
                        "a segment blends no neighbour of another pass; "
                        "a camera takes no vote from segments of another pass when choosing the segment it is "
                        "anchored on (campus seed 0, DSM: 3 end-of-loop cameras 15.8 m off, reprojection RMS of "
                        "the warped model 218 → 2.2 px, bundle adjustment 86 → 14 iterations). None: off; needs "
                        "the COLMAP model. See toolkit.warp.passes.")
        pass_sparse_gap_m: float = Field(
            2.0, gt=0, description="Only sparse points within this distance of a street point give it a route "
                                   "position (metres); points without one keep their segment.")

    @classmethod
    def scene_needs(cls, params) -> tuple[str, ...]:
        return ("street_cloud",)

    def __call__(self, transforms: SegmentTransforms, street: StreetSegments, scene: Scene, obs) -> Registration:
        p = self.params
        return warp_scene(transforms, street, scene, p.neighbours_k, p.min_distance_m, p.neighbour_gap_m,
                          p.neighbour_gap_ratio, np.inf if p.max_neighbour_gap_m is None else p.max_neighbour_gap_m,
                          p.weight_cell_m, PassCheck(p.pass_gap_m, p.pass_sparse_gap_m),
                          relative=p.relative_distance, camera_k=p.camera_neighbours_k)
