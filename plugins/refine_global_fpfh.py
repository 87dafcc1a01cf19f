"""refine.global_fpfh — the Open3D peer baseline: FPFH + RANSAC global registration, then ICP.

Registers the whole street cloud rigidly onto the over-view cloud (overview/cloud.ply), the way a
user of an off-the-shelf point cloud library would: voxel downsampling, normals, FPFH features,
RANSAC on feature correspondences, point-to-plane ICP. It ignores the building matches and returns
the same transform for every segment, so the runner, metrics and report apply unchanged. It shows
why the cross-view problem needs a method of its own: street clouds see façades, over-view clouds
see roofs, and their local geometry has little in common. The steps: ``toolkit.refine.fpfh``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field

from plugins.refine_rigid_oracle import uniform_transforms
from toolkit.capture import StreetCapture
from toolkit.refine.fpfh import register_fpfh
from toolkit.scene import load_cloud
from toolkit.stage import Stage, StageParams
from toolkit.types import ConjugateGraphs, Matches, OverviewSegments, Scene, SegmentTransforms, StreetSegments


class GlobalFpfh(Stage):
    """Open3D FPFH + RANSAC + ICP, whole cloud, rigid (peer baseline; ignores matches)."""

    kind = "refine"
    name = "global_fpfh"

    class Params(StageParams):
        voxel_m: float = Field(1.0, gt=0, description="voxel size of the downsampling of both clouds (m)")
        normal_radius_m: float = Field(2.0, gt=0, description="radius of the normal estimation (m)")
        feature_radius_m: float = Field(5.0, gt=0, description="radius of the FPFH features (m)")
        max_keypoints: int = Field(5000, ge=3, description="street voxels whose features are matched (count; a "
                                                           "deterministic subsample bounding the matching cost)")
        ransac_distance_m: float = Field(1.5, gt=0, description="RANSAC inlier distance (m)")
        ransac_iterations: int = Field(100_000, ge=1, description="RANSAC iteration cap")
        ransac_confidence: float = Field(0.999, gt=0, lt=1, description="RANSAC stopping confidence")
        ransac_restarts: int = Field(3, ge=1, description="independent RANSAC runs, seeds seed, seed+1, … (count); "
                                                          "the one with the best ICP fitness is kept")
        icp_distance_m: float = Field(2.0, gt=0, description="ICP correspondence distance (m)")
        icp_iterations: int = Field(50, ge=0, description="ICP iteration cap (0: RANSAC only)")
        use_levelling: bool = Field(False, description="start from the street stage's levelled frame (gives "
                                    "RANSAC the up direction); off = the plain Open3D pipeline")
        seed: int = Field(0, description="Open3D random seed (RANSAC)")

    @classmethod
    def scene_needs(cls, params: StageParams) -> tuple[str, ...]:
        return ("street_cloud", "overview_cloud")

    def __call__(self, matches: Matches, street: StreetSegments, overview: OverviewSegments, scene: Scene,
                 capture: StreetCapture, obs: Any, graphs: ConjugateGraphs | None = None) -> SegmentTransforms:
        p = self.params
        src = capture.points
        dst = load_cloud(scene, "overview_cloud", who="refine.global_fpfh")
        pre = street.levelling if p.use_levelling else np.eye(4)
        T, fitness, rmse = register_fpfh(src @ pre[:3, :3].T + pre[:3, 3], dst, p)
        T = T @ pre
        obs.debug("fitness", fitness)
        obs.debug("inlier_rmse_m", rmse)
        if fitness == 0.0:
            obs.warn("FPFH + RANSAC found no consistent transform; returning its best guess")
        return uniform_transforms(T, street, None, confidence=fitness)
