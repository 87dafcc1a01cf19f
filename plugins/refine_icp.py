"""refine.icp — per-segment Open3D ICP seeded by the match transform (an alternative to the paper's search).

Seed: the match's 2D transform plus the paper's 3D ground step (tilt onto the over-view ground
normal, height from DSM / over-view cloud heights; ``toolkit.refine.ground3d``). Then, per segment:
- ``cloud`` (scene has overview/cloud.ply): ICP of the segment's façade and ground points onto
  the over-view cloud around them (point-to-plane when the cloud has normals, else point-to-point);
- ``outline``: point-to-point ICP of the façade footprint onto the over-view segment's outline,
  kept as a rotation about z and a horizontal shift, then the height step again.
An ICP result that fits too few points or moves too far from the seed is discarded (the seed is
kept). Neighbour consistency as in refine.exhaustive.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field
from scipy import ndimage

from toolkit.refine.blas import single_threaded_blas
from toolkit.refine.finish import ConsistencyParams, finish
from toolkit.refine.ground3d import GroundParams, ground_step, height_source
from toolkit.refine.icp import CloudIndex, IcpParams, icp_cloud, icp_outline, outline_points
from toolkit.refine.segments import SegmentPoints
from toolkit.refine.transforms import compose_eq5
from toolkit.stage import Stage, StageParams
from toolkit.types import Matches, OverviewSegments, Scene, SegmentTransforms, StreetSegments


class IcpRefine(Stage):
    """Open3D ICP per segment against the over-view cloud or the segment outline, seeded by the match."""

    kind = "refine"
    name = "icp"

    class Params(StageParams):
        target: Literal["auto", "cloud", "outline"] = Field(
            "auto", description="ICP target: over-view cloud, over-view segment outline, or auto (cloud when the scene has one).")
        distances_m: tuple[float, ...] = Field((6.0, 3.0, 1.5, 0.75), min_length=1, description="Correspondence distances, coarse to fine (metres).")
        iterations: int = Field(30, ge=1, description="ICP iterations per distance.")
        voxel_m: float = Field(0.3, gt=0, description="Source points are thinned to one per voxel of this size (metres).")
        max_points: int = Field(20000, ge=100, description="At most this many source points per segment.")
        min_fitness: float = Field(0.3, ge=0, le=1, description="ICP results matching a smaller share of source points are discarded (seed kept).")
        max_correction_m: float = Field(10.0, gt=0, description="ICP results moving the segment centre farther than this are discarded (metres).")
        max_correction_deg: float = Field(10.0, gt=0, description="ICP results rotating more than this are discarded (degrees).")
        normal_max_angle_deg: float = Field(15.0, gt=0, lt=90, description="Ground normals within this angle of vertical define the street ground normal (degrees).")
        min_ground_points: int = Field(30, ge=3, description="Fewer ground points than this: no tilt, height from the neighbours.")
        check_consistency: bool = Field(True, description="Reject segments whose transform disagrees with their neighbours'.")
        neighbours_k: int = Field(4, ge=1, description="Neighbours compared in the consistency check (count).")
        consistency_tol_m: float = Field(3.0, gt=0, description="Allowed gap between neighbouring transforms at their centres (metres) ...")
        consistency_tol_ratio: float = Field(0.05, ge=0, description="... plus this fraction of the distance between the segments.")

    @classmethod
    def scene_needs(cls, params) -> tuple[str, ...]:
        return ("street_cloud", "overview_cloud") if params.target == "cloud" else ("street_cloud",)

    def __call__(self, matches: Matches, street: StreetSegments, overview: OverviewSegments, scene: Scene,
                 obs, graphs=None) -> SegmentTransforms:
        with single_threaded_blas():
            return self._run(matches, street, overview, scene, obs, graphs)

    def _run(self, matches: Matches, street: StreetSegments, overview: OverviewSegments, scene: Scene,
             obs, graphs=None) -> SegmentTransforms:
        from toolkit.scene import load_points

        p = self.params
        ip = IcpParams(tuple(p.distances_m), p.iterations, p.voxel_m, p.max_points)
        gp = GroundParams(normal_max_angle_deg=p.normal_max_angle_deg, min_ground_points=p.min_ground_points)
        use_cloud = p.target == "cloud" or (p.target == "auto" and scene.has("overview_cloud"))
        cloud = None
        if use_cloud:
            xyz = load_points(scene, "overview_cloud", "refine.icp")
            cloud = CloudIndex(xyz, normals=_file_normals(scene.files.overview_cloud, len(xyz)))
        S = len(street)
        pts = SegmentPoints(street, scene)
        heights = height_source(scene, overview)
        boxes = ndimage.find_objects(np.asarray(overview.label_image) + 1, max_label=len(overview))
        T2d = np.repeat(np.eye(3)[None], S, axis=0)
        R_z = np.repeat(np.eye(3)[None], S, axis=0)
        t_z, centres = np.full(S, np.nan), np.zeros((S, 3))
        valid, cost, conf = np.zeros(S, bool), np.ones(S), np.zeros(S)
        override: dict[int, np.ndarray] = {}
        discarded = 0
        for i in obs.progress(range(S), total=S, desc="icp segments"):
            o = int(matches.segment_match[i])
            if o < 0 or o >= len(overview) or boxes[o] is None:
                continue
            seed = np.asarray(matches.T2d[i], np.float64)
            ground, gnormals = pts.ground(i)
            on, oh = overview.ground_normal[o], float(overview.ground_height[o])
            g0 = ground_step(ground, gnormals, seed, heights, on, oh, gp)
            fp = pts.footprint(i, p.voxel_m, p.max_points, g0.R_z, g0.centre)
            if len(fp) < 10:
                continue
            valid[i], conf[i] = True, float(matches.confidence[i])
            T2d[i], R_z[i], t_z[i], centres[i] = seed, g0.R_z, g0.t_z, g0.centre
            if cloud is not None:
                res, T_lev = self._cloud_step(i, pts, seed, g0, cloud, ip)
                if res is not None and self._accept(res):
                    override[i] = T_lev
                    cost[i], conf[i] = res.rmse_m, conf[i] * res.fitness
                else:
                    discarded += 1
            else:
                res, T_new = self._outline_step(fp, seed, overview, o, boxes[o], ip)
                if res is not None and self._accept(res):
                    g1 = ground_step(ground, gnormals, T_new, heights, on, oh, gp)
                    T2d[i], R_z[i], t_z[i], centres[i] = T_new, g1.R_z, g1.t_z, g1.centre
                    cost[i], conf[i] = res.rmse_m, conf[i] * res.fitness
                else:
                    discarded += 1
        if discarded:
            obs.warn(f"ICP result discarded for {discarded} segment(s) (poor fit or too far from the match): seed kept")
        return finish(street, T2d, R_z, t_z, centres, valid, cost, conf,
                      ConsistencyParams(p.check_consistency, p.neighbours_k, p.consistency_tol_m,
                                        p.consistency_tol_ratio), graphs, obs, override)

    def _accept(self, res) -> bool:
        p = self.params
        ang = np.degrees(np.arccos(np.clip((np.trace(res.delta[:3, :3]) - 1) / 2, -1, 1)))
        return res.fitness >= p.min_fitness and ang <= p.max_correction_deg and \
            np.linalg.norm(res.delta[:3, 3]) <= p.max_correction_m + 1e-9

    def _cloud_step(self, i, pts: SegmentPoints, seed, g0, cloud: CloudIndex, ip: IcpParams):
        """ICP result and the corrected levelled → scene transform of segment i."""
        f = pts.facade(i)
        g, _ = pts.ground(i)
        src_lev = np.concatenate([f, g])
        src_lev = _voxel(src_lev, ip.voxel_m, ip.max_points)
        T_seed = compose_eq5(seed, g0.R_z, 0.0 if np.isnan(g0.t_z) else g0.t_z, g0.centre)
        src = src_lev @ T_seed[:3, :3].T + T_seed[:3, 3]
        origin = src.mean(axis=0)
        pad = max(ip.distances_m) + 2.0
        tgt, tgt_n = cloud.crop(src[:, :2].min(axis=0) - pad, src[:, :2].max(axis=0) + pad)
        if len(tgt) < 50:
            return None, None
        res = icp_cloud(src - origin, tgt - origin, ip, tgt_n)
        L = np.eye(4)
        L[:3, 3] = -origin
        return res, np.linalg.inv(L) @ res.delta @ L @ T_seed

    def _outline_step(self, fp, seed, overview: OverviewSegments, o: int, box, ip: IcpParams):
        rs, cs = box
        r0, c0 = max(rs.start - 1, 0), max(cs.start - 1, 0)
        win = np.asarray(overview.label_image)[r0:rs.stop + 1, c0:cs.stop + 1] == o
        outline = outline_points(overview.grid, win)
        outline += overview.grid.pixel_to_world(np.array([r0]), np.array([c0]))[0] \
            - overview.grid.pixel_to_world(np.array([0]), np.array([0]))[0]
        src = fp @ seed[:2, :2].T + seed[:2, 2]
        origin = src.mean(axis=0)
        res = icp_outline(src - origin, outline - origin, ip)
        L = np.eye(3)
        L[:2, 2] = -origin
        D = np.eye(3)
        D[:2, :2], D[:2, 2] = res.delta[:2, :2], res.delta[:2, 3]
        return res, np.linalg.inv(L) @ D @ L @ seed


def _voxel(xyz: np.ndarray, voxel: float, max_points: int) -> np.ndarray:
    key = np.floor(xyz / voxel).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    out = xyz[np.sort(first)]
    if len(out) > max_points:
        out = out[np.linspace(0, len(out) - 1, max_points).astype(np.int64)]
    return out


def _file_normals(path, n: int) -> np.ndarray | None:
    """Per-point normals stored in the over-view cloud file (PLY nx, ny, nz), else None."""
    from toolkit.open3d_import import open3d
    o3d = open3d()

    if path is None or path.suffix.lower() != ".ply":
        return None
    pc = o3d.io.read_point_cloud(str(path))
    if not pc.has_normals() or len(pc.normals) != n:
        return None
    return np.asarray(pc.normals, dtype=np.float64)
