"""refine.icp — per-segment Open3D ICP seeded by the match transform (an alternative to the paper's search).

Seed: the match's 2D transform plus the paper's 3D ground step (tilt onto the over-view ground
normal, height from DSM / over-view cloud heights; ``toolkit.refine.ground3d``). Then, per segment:
- ``cloud`` (scene has overview/cloud.ply): ICP of the segment's façade and ground points onto
  the over-view cloud around them (point-to-plane when the cloud has normals, else point-to-point);
- ``outline``: point-to-point ICP of the façade footprint onto the over-view segment's outline,
  kept as a rotation about z and a horizontal shift, then the height step again.
An ICP result that fits too few points or moves too far from the seed is discarded (the seed is
kept). Neighbour consistency as in refine.exhaustive. The steps: ``toolkit.refine.icp_segments``.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from toolkit.capture import StreetCapture
from toolkit.params import GroupedParams, group
from toolkit.refine.finish import ConsistencyParams, finish
from toolkit.refine.ground3d import GroundParams, height_source
from toolkit.refine.icp import IcpParams
from toolkit.refine.icp_segments import IcpFits, IcpTargets, overview_cloud, register_segment, uses_cloud
from toolkit.scene import load_cloud, overview_heights
from toolkit.stage import Stage
from toolkit.threads import single_threaded_blas
from toolkit.types import Matches, OverviewSegments, Scene, SegmentTransforms, StreetSegments


class IcpRefineParams(GroupedParams):
    target: Literal["auto", "cloud", "outline"] = Field(
        "auto", description="ICP target: over-view cloud, over-view segment outline, or auto (cloud when the scene has one).")
    icp: IcpParams = group(IcpParams, "the ICP schedule, its source points and the acceptance of its result")
    ground: GroundParams = group(GroundParams, "the 3D tilt (ground normals) and height step of the seed")
    consistency: ConsistencyParams = group(ConsistencyParams, "reject segments disagreeing with their neighbours")


class IcpRefine(Stage):
    """Open3D ICP per segment against the over-view cloud or the segment outline, seeded by the match."""

    kind = "refine"
    name = "icp"
    Params = IcpRefineParams

    @classmethod
    def scene_needs(cls, params) -> tuple[str, ...]:
        return ("street_cloud", "overview_cloud") if params.target == "cloud" else ("street_cloud",)

    def __call__(self, matches: Matches, street: StreetSegments, overview: OverviewSegments, scene: Scene,
                 capture: StreetCapture, obs, graphs=None) -> SegmentTransforms:
        p: IcpRefineParams = self.params  # type: ignore[assignment]
        with single_threaded_blas():
            cloud = None
            if uses_cloud(scene, p.target):
                cloud = overview_cloud(load_cloud(scene, "overview_cloud", "refine.icp"), scene.files.overview_cloud)
            heights = height_source(overview_heights(scene, "refine"), overview)
            targets = IcpTargets.of(street, overview, capture, cloud, heights)
            fits = IcpFits.empty(len(street))
            discarded = 0
            for i in obs.progress(range(len(street)), total=len(street), desc="icp segments"):
                discarded += (register_segment(targets, fits, i, matches, p.icp, p.ground) is False)
            if discarded:
                obs.warn(f"ICP result discarded for {discarded} segment(s) (poor fit or too far from the match): "
                         "seed kept")
            return finish(street, *fits.columns(), p.consistency, graphs, obs, fits.override)
