"""The 3D step of the fine registration (paper §3.3.2): tilt and height of one street segment.

The street ground normal of a segment (its ground points' normals within [15°] of vertical,
median-filtered) is rotated onto the over-view ground normal around the segment (R_Z); then the
height offset t_z is the robust difference between over-view ground heights and the street ground
heights at the same places. Over-view heights come from the DSM when the scene has one, else from
the terrain model (``overview.dem``, bare earth), else from the over-view cloud (lowest point per
grid cell), else from the over-view segments' ground heights (and a level ground). The robust
difference is the mean of the 10–60 % slice of the sorted differences, as the released code does
for DSM road heights: cars, trees and building edges in the DSM only ever raise it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from pydantic import Field

from toolkit.params import ParamGroup
from toolkit.refine.bilinear import cells_inside, interpolate, world_to_rows_cols
from toolkit.refine.columns import centred, minus_row
from toolkit.refine.transforms import rotation_between, tilt_deg
from toolkit.types import Grid, OverviewSegments, Raster


class GroundParams(ParamGroup):
    """The 3D tilt and height step (``steps.refine.params.ground``; old flat keys: the field names)."""

    flat_prefix: ClassVar[str | None] = ""

    normal_max_angle_deg: float = Field(15.0, gt=0, lt=90, description="ground normals within this angle of vertical define the street ground normal (paper: 15°)")
    min_ground_points: int = Field(30, ge=3, description="fewer ground points than this: no tilt, height from the neighbours")
    max_tilt_deg: float = Field(5.0, ge=0, description="a tilt correction larger than this is distrusted and skipped (degrees)")
    inlier_height_m: float = Field(0.5, gt=0, description="over-view heights within this of the first height offset fit the over-view ground plane (m)")
    min_spread_m: float = Field(1.0, ge=0, description="no fitted ground plane when the points spread less than this across (m, standard deviation)")
    trim_low: float = Field(0.10, ge=0, le=1, description="the height difference is the mean of the slice from this quantile ...")
    trim_high: float = Field(0.60, ge=0, le=1, description="... to this one (robust to cars, kerbs and walls)")


@dataclass(frozen=True)
class GroundResult:
    R_z: np.ndarray        # (3,3) tilt correction in the levelled frame
    t_z: float             # height offset (NaN when unknown)
    centre: np.ndarray     # (3,) levelled point R_z turns about
    tilt_deg: float
    n_ground: int


class HeightGrid:
    """Heights on a raster grid, sampled bilinearly (NaN where unknown)."""

    def __init__(self, heights: np.ndarray, grid: Grid) -> None:
        self.h, self.grid = np.ascontiguousarray(heights, np.float64), grid

    def sample(self, xy: np.ndarray) -> np.ndarray:
        row, col = world_to_rows_cols(self.grid.transform, xy)
        H, W = self.h.shape
        r0, c0, inside = cells_inside(row, col, H, W)
        if inside is None:
            return interpolate(self.h.ravel(), W, row, col, r0, c0)
        out = np.full(len(xy), np.nan)
        out[inside] = interpolate(self.h.ravel(), W, row[inside], col[inside], r0[inside], c0[inside])
        return out


def height_source(heights: Raster | np.ndarray | None, overview: OverviewSegments) -> HeightGrid | None:
    """``heights`` (``toolkit.scene.overview_heights``: the DSM or terrain model raster, or the
    over-view cloud) as a grid: a raster as it is, the cloud rasterised (lowest z per cell) on the
    over-view grid; None without heights."""
    if heights is None:
        return None
    if isinstance(heights, Raster):
        h = heights.data[0].astype(np.float64)
        h[heights.nodata_mask] = np.nan
        return HeightGrid(h, heights.grid)
    pts = heights
    g = overview.grid
    rc = np.floor(g.world_to_pixel(pts[:, :2]) + 0.5).astype(np.int64)
    ok = (rc[:, 0] >= 0) & (rc[:, 1] >= 0) & (rc[:, 0] < g.height) & (rc[:, 1] < g.width)
    h = np.full(g.height * g.width, np.inf)
    np.minimum.at(h, rc[ok, 0] * g.width + rc[ok, 1], pts[ok, 2])
    h[~np.isfinite(h)] = np.nan
    return HeightGrid(h.reshape(g.height, g.width), g)


def trimmed_mean(x: np.ndarray, lo: float, hi: float, scratch: bool = False) -> float:
    """Mean of the [lo, hi) quantile slice of the finite values (a partial sort: only the slice's
    bounds are ordered, its members are the same as a full sort's). ``scratch``: x may be reordered
    in place."""
    finite = np.isfinite(x)
    if finite.all():
        x = x if scratch else x.copy()
    else:
        x = x[finite]
    if len(x) == 0:
        return float("nan")
    a, b = int(np.floor(lo * len(x))), max(int(np.ceil(hi * len(x))), int(np.floor(lo * len(x))) + 1)
    b = min(b, len(x))
    x.partition(sorted({a, b - 1}))
    return float(x[a:b].mean())


@dataclass(frozen=True)
class PreparedGround:
    """What the ground step needs of a segment's ground points independently of its transform."""

    centre: np.ndarray                 # (3,) median ground point (R_Z turns about it)
    street_normal: np.ndarray | None   # levelled street ground normal (None: unknown)
    xy: np.ndarray                     # (G,2) contiguous levelled x, y of the ground points
    relative: np.ndarray               # (G,3) ground points minus the centre
    z: np.ndarray                      # (G,) contiguous levelled heights of the ground points


def prepare_ground(points: np.ndarray, normals: np.ndarray | None, p: GroundParams) -> PreparedGround | None:
    """The transform-independent part of ``ground_step`` (None when too few ground points)."""
    if len(points) < p.min_ground_points:
        return None
    centre = _column_medians(points)
    return PreparedGround(centre, street_ground_normal(points, normals, p), np.ascontiguousarray(points[:, :2]),
                          minus_row(points, centre), np.ascontiguousarray(points[:, 2]))


def _column_medians(points: np.ndarray) -> np.ndarray:
    """``np.median(points, axis=0)``, one contiguous column at a time (the same order statistics)."""
    return np.array([np.median(points[:, j]) for j in range(points.shape[1])])


def street_ground_normal(points: np.ndarray, normals: np.ndarray | None, p: GroundParams) -> np.ndarray | None:
    """Levelled ground normal of a segment: median of near-vertical normals, else a plane fit."""
    if len(points) < p.min_ground_points:
        return None
    cos_max = np.cos(np.radians(p.normal_max_angle_deg))
    if normals is not None:
        up = np.sign(normals[:, 2] + 1e-12)
        n = [normals[:, j] * up for j in range(3)]          # normals turned upwards, column by column
        near_vertical = n[2] >= cos_max
        if np.count_nonzero(near_vertical) >= p.min_ground_points:
            m = np.array([np.median(column[near_vertical]) for column in n])
            return m / np.linalg.norm(m)
    return _plane_normal(points, p)


def _plane_normal(xyz: np.ndarray, p: GroundParams) -> np.ndarray | None:
    """Least-squares plane z = a x + b y + c (None when the points span too little area), from the
    3×3 scatter of the centred points (normal equations; the intercept decouples once centred)."""
    q = centred(xyz)
    S = q.T @ q
    sxx, sxy, syy = S[0, 0], S[0, 1], S[1, 1]
    smallest = 0.5 * (sxx + syy) - np.sqrt(0.25 * (sxx - syy) ** 2 + sxy ** 2)   # of the xy scatter
    if not len(q) > 1 or np.sqrt(max(smallest, 0.0) / (len(q) - 1)) < p.min_spread_m:
        return None
    coef = np.linalg.solve(S[:2, :2], S[:2, 2])
    n = np.array([-coef[0], -coef[1], 1.0])
    n /= np.linalg.norm(n)
    return n if n[2] >= np.cos(np.radians(p.normal_max_angle_deg)) else None


def ground_step(ground: np.ndarray, ground_normals: np.ndarray | None, T2d: np.ndarray,
                heights: HeightGrid | None, overview_normal: np.ndarray, overview_height: float,
                p: GroundParams, prepared: PreparedGround | None = None, with_height: bool = True) -> GroundResult:
    """R_Z and t_z for one segment. ``ground``: (G,3) levelled ground points of the segment.

    ``overview_normal`` / ``overview_height``: the over-view segment's terrain normal and height,
    used when the height source cannot give them at the segment's ground points. ``prepared``:
    ``prepare_ground`` of the same points (computed here when not given; pass it when the segment
    is stepped several times). ``with_height=False``: only the tilt is wanted (t_z is NaN; the over-view
    heights are not even sampled when the segment has no street ground normal).
    """
    if len(ground) < p.min_ground_points:
        return GroundResult(np.eye(3), float("nan"), np.zeros(3), 0.0, len(ground))  # filled later
    if prepared is None:
        prepared = prepare_ground(ground, ground_normals, p)
    centre = prepared.centre
    n_street = prepared.street_normal
    if not with_height and n_street is None:
        return GroundResult(np.eye(3), float("nan"), centre, 0.0, len(ground))
    world_xy = prepared.xy @ np.ascontiguousarray(T2d[:2, :2].T) + T2d[:2, 2]
    h = heights.sample(world_xy) if heights is not None else np.full(len(ground), np.nan)
    dz = h - prepared.z
    t0 = trimmed_mean(dz, p.trim_low, p.trim_high)
    n_over = None
    if np.isfinite(t0):
        dz -= t0
        keep = np.abs(dz, out=dz) < p.inlier_height_m
        n_keep = int(np.count_nonzero(keep))
        if n_keep >= p.min_ground_points:
            xyz = np.empty((n_keep, 3))
            for j, column in enumerate((world_xy[:, 0], world_xy[:, 1], h)):   # 1D compressions: ~3× faster
                xyz[:, j] = column[keep]
            n_over = _plane_normal(xyz, p)
    if n_over is None:
        n_over = np.asarray(overview_normal, np.float64)
    R_z = np.eye(3)
    if n_street is not None:
        R2 = np.eye(3)
        R2[:2, :2] = T2d[:2, :2]
        R_z = rotation_between(n_street, R2.T @ n_over)
        if tilt_deg(R_z) > p.max_tilt_deg:
            R_z = np.eye(3)
    if not with_height:
        return GroundResult(R_z, float("nan"), centre, tilt_deg(R_z), len(ground))
    z_new = prepared.relative @ R_z[2] + centre[2]
    if np.isfinite(t0):
        h -= z_new
        t_z = trimmed_mean(h, p.trim_low, p.trim_high, scratch=True)
    else:
        t_z = float(overview_height - np.median(z_new))  # NaN when the over-view has no height
    return GroundResult(R_z, t_z, centre, tilt_deg(R_z), len(ground))
