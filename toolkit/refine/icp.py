"""Per-segment ICP (Open3D) for refine.icp: against the over-view cloud, or the segment's outline.

Over-view cloud: the segment's façade and ground points (seed-placed in the scene, about a local
origin) are registered onto the cloud cropped around them: point-to-plane when the cloud file
carries normals, else point-to-point. Outline: the thinned footprint (z = 0) is registered point-to-point onto the
edge of the over-view segment's pixel mask (midpoints between inside and outside pixel centres);
the result is projected to a rotation about z plus a horizontal shift.
Both use a coarse-to-fine schedule of correspondence distances.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from pydantic import Field

from toolkit.params import ParamGroup
from toolkit.types import Grid


class IcpParams(ParamGroup):
    """The ICP schedule, its source points and the acceptance of its result (``steps.refine.params.icp``;
    old flat keys: the field names)."""

    flat_prefix: ClassVar[str | None] = ""

    distances_m: tuple[float, ...] = Field((6.0, 3.0, 1.5, 0.75), min_length=1, description="Correspondence distances, coarse to fine (metres).")
    iterations: int = Field(30, ge=1, description="ICP iterations per distance.")
    voxel_m: float = Field(0.3, gt=0, description="Source points are thinned to one per voxel of this size (metres).")
    max_points: int = Field(20000, ge=100, description="At most this many source points per segment.")
    min_fitness: float = Field(0.3, ge=0, le=1, description="ICP results matching a smaller share of source points are discarded (seed kept).")
    max_correction_m: float = Field(10.0, gt=0, description="ICP results moving the segment centre farther than this are discarded (metres).")
    max_correction_deg: float = Field(10.0, gt=0, description="ICP results rotating more than this are discarded (degrees).")


@dataclass(frozen=True)
class IcpResult:
    delta: np.ndarray      # (4,4) correction in the local scene frame (applied after the seed)
    fitness: float
    rmse_m: float


class CloudIndex:
    """Coarse cell index over a large cloud, for fast box crops."""

    def __init__(self, xyz: np.ndarray, cell_m: float = 25.0, normals: np.ndarray | None = None) -> None:
        self.xyz, self.cell, self.normals = xyz, cell_m, normals
        key = np.floor(xyz[:, :2] / cell_m).astype(np.int64)
        self.k0 = key.min(axis=0)
        key -= self.k0
        self.ny = int(key[:, 1].max()) + 1
        flat = key[:, 0] * self.ny + key[:, 1]
        self.order = np.argsort(flat, kind="stable")
        self.sorted = flat[self.order]

    def crop(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Points (and normals, when known) inside the box lo..hi (x, y)."""
        a = np.floor(lo / self.cell).astype(np.int64) - self.k0
        b = np.floor(hi / self.cell).astype(np.int64) - self.k0
        parts = []
        for cx in range(max(a[0], 0), b[0] + 1):
            y0, y1 = max(a[1], 0), min(b[1], self.ny - 1)
            if y1 < y0:
                continue
            s = np.searchsorted(self.sorted, cx * self.ny + y0)
            e = np.searchsorted(self.sorted, cx * self.ny + y1, side="right")
            parts.append(self.order[s:e])
        idx = np.concatenate(parts) if parts else np.zeros(0, np.int64)
        p = self.xyz[idx]
        keep = (p[:, 0] >= lo[0]) & (p[:, 0] <= hi[0]) & (p[:, 1] >= lo[1]) & (p[:, 1] <= hi[1])
        return p[keep], None if self.normals is None else self.normals[idx[keep]]


def accepted(res: IcpResult, p: IcpParams) -> bool:
    """Whether an ICP result fits enough points and stays near its seed (else the seed is kept)."""
    ang = np.degrees(np.arccos(np.clip((np.trace(res.delta[:3, :3]) - 1) / 2, -1, 1)))
    return res.fitness >= p.min_fitness and ang <= p.max_correction_deg and \
        np.linalg.norm(res.delta[:3, 3]) <= p.max_correction_m + 1e-9


def voxel_thin(xyz: np.ndarray, voxel: float, max_points: int) -> np.ndarray:
    """The first point in each occupied voxel (input order), then at most ``max_points`` evenly spread."""
    key = np.floor(xyz / voxel).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    out = xyz[np.sort(first)]
    if len(out) > max_points:
        out = out[np.linspace(0, len(out) - 1, max_points).astype(np.int64)]
    return out


def file_normals(path, n: int) -> np.ndarray | None:
    """Per-point normals stored in the over-view cloud file (PLY nx, ny, nz), else None."""
    from toolkit.open3d_import import open3d
    o3d = open3d()

    if path is None or path.suffix.lower() != ".ply":
        return None
    pc = o3d.io.read_point_cloud(str(path))
    if not pc.has_normals() or len(pc.normals) != n:
        return None
    return np.asarray(pc.normals, dtype=np.float64)


def outline_points(grid: Grid, mask: np.ndarray) -> np.ndarray:
    """(M,2) world points on the edge of a pixel mask (midpoints of inside/outside pixel pairs)."""
    pts = []
    for dr, dc in ((0, 1), (1, 0)):
        a = mask[:mask.shape[0] - dr, :mask.shape[1] - dc]
        b = mask[dr:, dc:]
        r, c = np.nonzero(a != b)
        pts.append(grid.pixel_to_world(r + dr / 2.0, c + dc / 2.0))
    return np.concatenate(pts)


def _pcd(xyz: np.ndarray):
    from toolkit.open3d_import import open3d
    o3d = open3d()

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.ascontiguousarray(xyz, dtype=np.float64))
    return pc


def icp_cloud(source: np.ndarray, target: np.ndarray, p: IcpParams,
              target_normals: np.ndarray | None = None) -> IcpResult:
    """ICP of local-frame source onto local-frame target (both (N,3)): point-to-plane when the
    target comes with normals, else point-to-point (normals estimated on a 2.5D over-view cloud
    leave sliding directions unconstrained and the point-to-plane solve can run away)."""
    from toolkit.open3d_import import open3d
    o3d = open3d()

    reg = o3d.pipelines.registration
    tgt = _pcd(target)
    if target_normals is not None:
        tgt.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(target_normals, dtype=np.float64))
        method = reg.TransformationEstimationPointToPlane()
    else:
        method = reg.TransformationEstimationPointToPoint()
    src = _pcd(source)
    T = np.eye(4)
    res = None
    for d in p.distances_m:
        res = reg.registration_icp(src, tgt, d, T, method, reg.ICPConvergenceCriteria(max_iteration=p.iterations))
        T = np.asarray(res.transformation)
    return IcpResult(T, float(res.fitness), float(res.inlier_rmse))


def icp_outline(source_xy: np.ndarray, outline_xy: np.ndarray, p: IcpParams) -> IcpResult:
    """Point-to-point ICP in the plane; the result is kept as a yaw plus a horizontal shift."""
    from toolkit.open3d_import import open3d
    o3d = open3d()

    reg = o3d.pipelines.registration
    src = _pcd(np.column_stack([source_xy, np.zeros(len(source_xy))]))
    tgt = _pcd(np.column_stack([outline_xy, np.zeros(len(outline_xy))]))
    T = np.eye(4)
    res = None
    for d in p.distances_m:
        res = reg.registration_icp(src, tgt, d, T, reg.TransformationEstimationPointToPoint(),
                                   reg.ICPConvergenceCriteria(max_iteration=p.iterations))
        T = _yaw_only(np.asarray(res.transformation))
    return IcpResult(T, float(res.fitness), float(res.inlier_rmse))


def _yaw_only(T: np.ndarray) -> np.ndarray:
    yaw = np.arctan2(T[1, 0] - T[0, 1], T[0, 0] + T[1, 1])
    out = np.eye(4)
    out[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    out[:2, 3] = T[:2, 3]
    return out
