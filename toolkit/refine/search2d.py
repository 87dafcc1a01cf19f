"""Exhaustive 2D registration of a street segment's façade footprint onto one over-view segment.

Paper §3.3.2: rotations within ±[10°] at [1°] and every one-pixel offset inside the over-view
segment's window, keeping the least chamfer cost. The cost of one transform is the mean, over the
street footprint points, of the (truncated) distance to the over-view segment's outline.

Exact and fast: for each rotation the points are splatted (bilinear weights) into a small kernel
image; the chamfer cost of *every* integer offset is then one cross-correlation of the distance
map with that kernel (FFT). Integer shifts keep each point's sub-pixel phase, so this equals
evaluating the bilinearly interpolated distance map at each offset — the full grid, no coarse step.
The optimum is then refined below one pixel: a parabola through the neighbouring grid costs, then a
few Gauss-Newton steps on the signed distance (point-to-outline least squares, inliers only).

The outline is the edge of the segment's pixel mask (between inside and outside pixel centres), so
there is no half-pixel inward bias from using boundary-pixel centres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.signal import fftconvolve

from toolkit.refine.transforms import rigid2d
from toolkit.types import Grid


@dataclass(frozen=True)
class SearchParams:
    rotation_range_deg: float = 10.0
    rotation_step_deg: float = 1.0
    margin_m: float = 5.0
    truncate_m: float = 3.0
    inlier_m: float = 1.0
    shift_penalty: float = 0.03
    subpixel: bool = True


@dataclass(frozen=True)
class SearchResult:
    T2d: np.ndarray          # (3,3) levelled street xy → scene xy
    cost_m: float            # mean truncated outline distance at T2d
    seed_cost_m: float       # same at the seed transform
    inlier_ratio: float      # share of points within inlier_m of the outline
    shift_m: float           # how far the footprint centre moved from the seed
    rotation_deg: float      # rotation relative to the seed


class OutlineField:
    """Signed distance (metres, + outside) to one segment's mask edge, on a window of the grid."""

    def __init__(self, grid: Grid, mask_window: np.ndarray, row0: int, col0: int) -> None:
        gsd = grid.gsd_m
        inside = mask_window.astype(bool)
        d_out = ndimage.distance_transform_edt(~inside)
        d_in = ndimage.distance_transform_edt(inside)
        self.sdf = np.where(inside, -(d_in - 0.5), d_out - 0.5) * gsd
        self.grid, self.row0, self.col0 = grid, row0, col0
        a, b, _, d, e, _ = grid.transform
        # world gradient = J^-T (d/dcol, d/drow), J maps (dcol, drow) → (dx, dy)
        jinv_t = np.linalg.inv(np.array([[a, b], [d, e]])).T
        g_r, g_c = np.gradient(self.sdf)
        self.grad_x = jinv_t[0, 0] * g_c + jinv_t[0, 1] * g_r
        self.grad_y = jinv_t[1, 0] * g_c + jinv_t[1, 1] * g_r

    def to_window(self, xy: np.ndarray) -> np.ndarray:
        rc = self.grid.world_to_pixel(xy)
        rc[:, 0] -= self.row0
        rc[:, 1] -= self.col0
        return rc

    def sample(self, xy: np.ndarray, field: np.ndarray | None = None, outside: float = np.nan) -> np.ndarray:
        arr = self.sdf if field is None else field
        rc = self.to_window(xy)
        return _bilinear(arr, rc, outside)


def _bilinear(arr: np.ndarray, rc: np.ndarray, outside: float) -> np.ndarray:
    h, w = arr.shape
    r0 = np.floor(rc[:, 0]).astype(np.int64)
    c0 = np.floor(rc[:, 1]).astype(np.int64)
    fr, fc = rc[:, 0] - r0, rc[:, 1] - c0
    ok = (r0 >= 0) & (c0 >= 0) & (r0 < h - 1) & (c0 < w - 1)
    out = np.full(len(rc), outside, dtype=np.float64)
    r, c, fr, fc = r0[ok], c0[ok], fr[ok], fc[ok]
    out[ok] = (arr[r, c] * (1 - fr) * (1 - fc) + arr[r, c + 1] * (1 - fr) * fc
               + arr[r + 1, c] * fr * (1 - fc) + arr[r + 1, c + 1] * fr * fc)
    return out


def _splat(rc: np.ndarray) -> tuple[np.ndarray, int, int]:
    """Bilinear splat of fractional (row, col) into a kernel; returns kernel and its top-left."""
    base_r, base_c = int(np.floor(rc[:, 0].min())), int(np.floor(rc[:, 1].min()))
    r = rc[:, 0] - base_r
    c = rc[:, 1] - base_c
    r0, c0 = np.floor(r).astype(np.int64), np.floor(c).astype(np.int64)
    fr, fc = r - r0, c - c0
    h, w = int(r0.max()) + 2, int(c0.max()) + 2
    k = np.zeros(h * w)
    for dr, dc, wt in ((0, 0, (1 - fr) * (1 - fc)), (0, 1, (1 - fr) * fc), (1, 0, fr * (1 - fc)), (1, 1, fr * fc)):
        k += np.bincount((r0 + dr) * w + (c0 + dc), weights=wt, minlength=h * w)
    return k.reshape(h, w), base_r, base_c


def _correlate_valid(sub: np.ndarray, k: np.ndarray, max_direct_offsets: int = 121) -> np.ndarray:
    """out[i, j] = Σ_uv sub[i+u, j+v]·k[u, v] over the valid offsets (i, j): gathered directly when
    there are few offsets (the joint pass searches ±4 px with a large kernel: ~2× faster than an
    FFT there), else by FFT."""
    n_r, n_c = sub.shape[0] - k.shape[0] + 1, sub.shape[1] - k.shape[1] + 1
    if n_r * n_c > max_direct_offsets:
        return fftconvolve(sub, k[::-1, ::-1], mode="valid")
    nz_r, nz_c = np.nonzero(k)
    off_r, off_c = np.divmod(np.arange(n_r * n_c), n_c)
    idx = (off_r * sub.shape[1] + off_c)[:, None] + (nz_r * sub.shape[1] + nz_c)[None, :]
    return (sub.ravel()[idx] @ k[nz_r, nz_c]).reshape(n_r, n_c)


def _parabola(cm: float, c0: float, cp: float) -> float:
    den = cm - 2 * c0 + cp
    if den <= 1e-12:
        return 0.0
    return float(np.clip(0.5 * (cm - cp) / den, -0.5, 0.5))


def search_segment(street_xy: np.ndarray, T_seed: np.ndarray, grid: Grid, label_image: np.ndarray,
                   seg: int | None, bbox: tuple[slice, slice], p: SearchParams) -> SearchResult:
    """Best 2D rigid transform of ``street_xy`` (levelled) onto over-view segment ``seg``.

    ``bbox``: the (row, col) slices of the window the footprint centre may move in (before the
    margin); ``seg = None`` takes the outline of every over-view segment in the window.
    """
    gsd = grid.gsd_m
    seed_xy = street_xy @ T_seed[:2, :2].T + T_seed[:2, 2]
    centre = seed_xy.mean(axis=0)
    n_rot = round(p.rotation_range_deg / p.rotation_step_deg)
    angles = np.radians(np.arange(-n_rot, n_rot + 1) * p.rotation_step_deg)
    margin = int(np.ceil(p.margin_m / gsd))
    c_rc = grid.world_to_pixel(centre[None])[0]
    rs, cs = bbox
    dr0 = int(np.floor(min(0.0, rs.start - margin - c_rc[0])))
    dr1 = int(np.ceil(max(0.0, rs.stop - 1 + margin - c_rc[0])))
    dc0 = int(np.floor(min(0.0, cs.start - margin - c_rc[1])))
    dc1 = int(np.ceil(max(0.0, cs.stop - 1 + margin - c_rc[1])))

    kernels = []
    rel = seed_xy - centre
    for ang in angles:
        c, s = np.cos(ang), np.sin(ang)
        xy = rel @ np.array([[c, s], [-s, c]]) + centre
        kernels.append(_splat(grid.world_to_pixel(xy)))
    win_r0 = min(br for _, br, _ in kernels) + dr0 - 1
    win_c0 = min(bc for _, _, bc in kernels) + dc0 - 1
    win_r1 = max(br + k.shape[0] for k, br, _ in kernels) + dr1 + 1
    win_c1 = max(bc + k.shape[1] for k, _, bc in kernels) + dc1 + 1
    labels = _window(label_image, win_r0, win_c0, win_r1, win_c1, fill=-1)
    mask = labels >= 0 if seg is None else labels == seg
    field = OutlineField(grid, mask, win_r0, win_c0)
    trunc = np.minimum(np.abs(field.sdf), p.truncate_m)

    n = len(street_xy)
    dr = np.arange(dr0, dr1 + 1)[:, None]
    dc = np.arange(dc0, dc1 + 1)[None, :]
    a, b, _, d, e, _ = grid.transform
    shift_m = np.hypot(a * dc + b * dr, d * dc + e * dr)
    costs = np.empty((len(angles), dr1 - dr0 + 1, dc1 - dc0 + 1))
    for i, (k, br, bc) in enumerate(kernels):
        r_lo, c_lo = br + dr0 - win_r0, bc + dc0 - win_c0
        sub = trunc[r_lo:r_lo + (dr1 - dr0) + k.shape[0], c_lo:c_lo + (dc1 - dc0) + k.shape[1]]
        costs[i] = _correlate_valid(sub, k) / n + p.shift_penalty * shift_m
    ki, ri, ci = np.unravel_index(int(np.argmin(costs)), costs.shape)
    ang, off_r, off_c = float(angles[ki]), float(ri + dr0), float(ci + dc0)
    if p.subpixel:
        if 0 < ki < len(angles) - 1:
            ang += _parabola(*costs[ki - 1:ki + 2, ri, ci]) * np.radians(p.rotation_step_deg)
        if 0 < ri < costs.shape[1] - 1:
            off_r += _parabola(*costs[ki, ri - 1:ri + 2, ci])
        if 0 < ci < costs.shape[2] - 1:
            off_c += _parabola(*costs[ki, ri, ci - 1:ci + 2])
    shift = np.array([a * off_c + b * off_r, d * off_c + e * off_r])

    def chamfer(T: np.ndarray) -> np.ndarray:
        xy = street_xy @ T[:2, :2].T + T[:2, 2]
        return np.minimum(np.abs(field.sample(xy, outside=p.truncate_m)), p.truncate_m)

    T_grid = _about(ang, centre, shift) @ T_seed
    T_best = T_grid
    if p.subpixel:
        T_gn = _gauss_newton(street_xy, T_grid, field, p)
        if T_gn is not None and chamfer(T_gn).mean() <= chamfer(T_grid).mean() + 1e-6:
            T_best = T_gn
    d_final = chamfer(T_best)
    moved = (street_xy @ T_best[:2, :2].T + T_best[:2, 2]).mean(axis=0) - centre
    rot = np.degrees(np.arctan2(T_best[1, 0], T_best[0, 0]) - np.arctan2(T_seed[1, 0], T_seed[0, 0]))
    return SearchResult(
        T2d=T_best, cost_m=float(d_final.mean()), seed_cost_m=float(chamfer(T_seed).mean()),
        inlier_ratio=float((d_final < p.inlier_m).mean()), shift_m=float(np.hypot(*moved)),
        rotation_deg=float((rot + 180) % 360 - 180))


def _about(theta: float, centre: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Rotation by theta about ``centre`` followed by ``shift`` (world frame)."""
    R = rigid2d(theta, np.zeros(2))
    R[:2, 2] = centre - R[:2, :2] @ centre + shift
    return R


def _window(arr: np.ndarray, r0: int, c0: int, r1: int, c1: int, fill=False) -> np.ndarray:
    """arr[r0:r1, c0:c1], ``fill`` outside the image."""
    h, w = arr.shape
    out = np.full((r1 - r0, c1 - c0), fill, dtype=arr.dtype)
    rr0, cc0, rr1, cc1 = max(r0, 0), max(c0, 0), min(r1, h), min(c1, w)
    if rr1 > rr0 and cc1 > cc0:
        out[rr0 - r0:rr1 - r0, cc0 - c0:cc1 - c0] = arr[rr0:rr1, cc0:cc1]
    return out


def _gauss_newton(street_xy: np.ndarray, T0: np.ndarray, field: OutlineField, p: SearchParams,
                  iterations: int = 10) -> np.ndarray | None:
    """Point-to-outline least squares on the signed distance (inliers within inlier_m)."""
    T = T0.copy()
    for _ in range(iterations):
        xy = street_xy @ T[:2, :2].T + T[:2, 2]
        s = field.sample(xy)
        ok = np.isfinite(s) & (np.abs(s) < p.inlier_m)
        if ok.sum() < 6:
            return None
        gx, gy = field.sample(xy[ok], field.grad_x), field.sample(xy[ok], field.grad_y)
        c = xy[ok].mean(axis=0)
        rx, ry = xy[ok, 0] - c[0], xy[ok, 1] - c[1]
        J = np.column_stack([gx * -ry + gy * rx, gx, gy])
        H = J.T @ J + 1e-6 * np.eye(3)
        step = -np.linalg.solve(H, J.T @ s[ok])
        if not np.all(np.isfinite(step)):
            return None
        T = _about(step[0], c, step[1:]) @ T
        if abs(step[0]) < 1e-6 and np.hypot(*step[1:]) < 1e-4:
            break
    gsd = field.grid.gsd_m
    c0 = (street_xy @ T0[:2, :2].T + T0[:2, 2]).mean(axis=0)
    c1 = (street_xy @ T[:2, :2].T + T[:2, 2]).mean(axis=0)
    dtheta = np.arctan2(T[1, 0], T[0, 0]) - np.arctan2(T0[1, 0], T0[0, 0])
    if np.hypot(*(c1 - c0)) > 2 * gsd or abs(np.degrees(dtheta)) > 2 * p.rotation_step_deg:
        return None
    return T
