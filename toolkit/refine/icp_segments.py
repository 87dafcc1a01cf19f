"""The per-segment steps of refine.icp: seed by the match and the ground step, ICP, keep or discard.

``IcpTargets.of`` gathers what every segment is registered against (the over-view cloud when used,
else the over-view segments' outlines), ``register_segment`` places one segment into ``IcpFits``
(the per-segment columns ``toolkit.refine.finish.finish`` composes and checks).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from toolkit.capture import StreetCapture
from toolkit.refine.ground3d import GroundParams, GroundResult, HeightGrid, ground_step
from toolkit.refine.icp import (CloudIndex, IcpParams, IcpResult, accepted, file_normals, icp_cloud, icp_outline,
                                outline_points, voxel_thin)
from toolkit.refine.segments import SegmentPoints
from toolkit.refine.transforms import compose_eq5
from toolkit.types import Matches, OverviewSegments, Scene, StreetSegments


def uses_cloud(scene: Scene, target: str) -> bool:
    """Whether ``target`` registers against the over-view cloud: cloud, or auto and the scene has one."""
    return target == "cloud" or (target == "auto" and scene.has("overview_cloud"))


def overview_cloud(xyz: np.ndarray, path: Path) -> CloudIndex:
    """The over-view cloud ``xyz`` (read from ``path``) indexed, with the file's normals."""
    return CloudIndex(xyz, normals=file_normals(path, len(xyz)))


@dataclass(frozen=True)
class IcpTargets:
    """The street segments' points and what they are registered against."""

    overview: OverviewSegments
    cloud: CloudIndex | None
    pts: SegmentPoints
    heights: Any                 # toolkit.refine.ground3d.height_source
    boxes: list                  # bounding slices of the over-view segments (None: no pixel)

    @classmethod
    def of(cls, street: StreetSegments, overview: OverviewSegments, capture: StreetCapture, cloud: CloudIndex | None,
           heights: HeightGrid | None):
        boxes = ndimage.find_objects(np.asarray(overview.label_image) + 1, max_label=len(overview))
        return cls(overview, cloud, SegmentPoints(street, capture), heights, boxes)


@dataclass
class IcpFits:
    """Per-segment results: 2D transform, tilt, height, ground centre, validity, cost, confidence."""

    T2d: np.ndarray
    R_z: np.ndarray
    t_z: np.ndarray
    centres: np.ndarray
    valid: np.ndarray
    cost: np.ndarray
    conf: np.ndarray
    override: dict[int, np.ndarray] = field(default_factory=dict)   # levelled → scene transforms (cloud ICP)

    @classmethod
    def empty(cls, S: int) -> IcpFits:
        return cls(np.repeat(np.eye(3)[None], S, axis=0), np.repeat(np.eye(3)[None], S, axis=0), np.full(S, np.nan),
                   np.zeros((S, 3)), np.zeros(S, bool), np.ones(S), np.zeros(S))

    def columns(self) -> tuple[np.ndarray, ...]:
        """T2d, R_z, t_z, centres, valid, cost, confidence (the order of ``finish``)."""
        return self.T2d, self.R_z, self.t_z, self.centres, self.valid, self.cost, self.conf

    def place(self, i: int, T2d: np.ndarray, g: GroundResult) -> None:
        self.T2d[i], self.R_z[i], self.t_z[i], self.centres[i] = T2d, g.R_z, g.t_z, g.centre


def register_segment(t: IcpTargets, fits: IcpFits, i: int, matches: Matches, ip: IcpParams,
                     gp: GroundParams) -> bool | None:
    """Place segment i (seed, then ICP): None when it is not registered (no usable match or footprint),
    else whether the ICP result was kept (False: discarded, the seed kept)."""
    o = int(matches.segment_match[i])
    if o < 0 or o >= len(t.overview) or t.boxes[o] is None:
        return None
    seed = np.asarray(matches.T2d[i], np.float64)
    ground, gnormals = t.pts.ground(i)
    on, oh = t.overview.ground_normal[o], float(t.overview.ground_height[o])
    g0 = ground_step(ground, gnormals, seed, t.heights, on, oh, gp)
    fp = t.pts.footprint(i, ip.voxel_m, ip.max_points, g0.R_z, g0.centre)
    if len(fp) < 10:
        return None
    fits.valid[i], fits.conf[i] = True, float(matches.confidence[i])
    fits.place(i, seed, g0)
    if t.cloud is not None:
        res, T_lev = cloud_step(i, t.pts, seed, g0, t.cloud, ip)
    else:
        res, T_new = outline_step(fp, seed, t.overview, o, t.boxes[o], ip)
    if res is None or not accepted(res, ip):
        return False
    if t.cloud is not None:
        fits.override[i] = T_lev
    else:
        fits.place(i, T_new, ground_step(ground, gnormals, T_new, t.heights, on, oh, gp))
    fits.cost[i], fits.conf[i] = res.rmse_m, fits.conf[i] * res.fitness
    return True


def cloud_step(i: int, pts: SegmentPoints, seed: np.ndarray, g0: GroundResult, cloud: CloudIndex,
               ip: IcpParams) -> tuple[IcpResult | None, np.ndarray | None]:
    """ICP result and the corrected levelled → scene transform of segment i."""
    f = pts.facade(i)
    g, _ = pts.ground(i)
    src_lev = voxel_thin(np.concatenate([f, g]), ip.voxel_m, ip.max_points)
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


def outline_step(fp: np.ndarray, seed: np.ndarray, overview: OverviewSegments, o: int, box,
                 ip: IcpParams) -> tuple[IcpResult, np.ndarray]:
    """ICP result and the corrected 2D transform of a footprint onto over-view segment o's outline."""
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
