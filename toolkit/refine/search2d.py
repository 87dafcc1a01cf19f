"""Exhaustive 2D registration of a street segment's façade footprint onto one over-view segment.

Paper §3.3.2: rotations within ±[10°] at [1°] and every one-pixel offset inside the over-view
segment's window, keeping the least chamfer cost. The cost of one transform is the mean, over the
street footprint points, of the (truncated) distance to the over-view segment's outline.

Exact and fast: for each rotation the points are splatted (bilinear weights) into a small kernel
image; the chamfer cost of *every* integer offset is then one cross-correlation of the distance
map with that kernel (FFT). Integer shifts keep each point's sub-pixel phase, so this equals
evaluating the bilinearly interpolated distance map at each offset — the full grid, no coarse step.
All rotations are splatted into one kernel frame and correlated together: one batched FFT sharing
the distance map's transform (per-segment searches, thousands of offsets), or, for the joint pass's
few offsets and large footprints, one gather of the map under every kernel entry used by any
rotation and one matrix product (campus, DSM: the refine stage's correlations 3.2 s → 1.1 s CPU).
Searches against every outline (``seg = None``) cut their distance map from one field per over-view
(``AllOutlines``) instead of two distance transforms each; a search against one segment's outline
computes its own, with distances clamped beyond what is ever read (the truncation plus the reach of
a bilinear sample and of a central difference): exact wherever read, ~1.5× cheaper.
The optimum is then refined below one pixel: a parabola through the neighbouring grid costs, then a
few Gauss-Newton steps on the signed distance (point-to-outline least squares, inliers only;
``toolkit.refine.subpixel``), stepped together for all the searches of a pass (``search_segments``).

The outline is the edge of the segment's pixel mask (between inside and outside pixel centres), so
there is no half-pixel inward bias from using boundary-pixel centres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy import ndimage
from numpy.lib.stride_tricks import sliding_window_view
from scipy.fft import fft, ifft, irfft, next_fast_len, rfft, rfft2

from pydantic import Field

from toolkit.params import ParamGroup
from toolkit.refine.bilinear import cells_inside, interpolate, interpolate_planes, rows_cols, world_to_rows_cols
from toolkit.refine.columns import column_means
from toolkit.refine.subpixel import gauss_newton_many, rotation_about
from toolkit.types import Grid


class SearchParams(ParamGroup):
    """The exhaustive 2D search (``steps.refine.params.search``; old flat keys: the field names)."""

    flat_prefix: ClassVar[str | None] = ""

    rotation_range_deg: float = Field(10.0, ge=0, le=45, description="rotation searched either side of the match (paper: 10°)")
    rotation_step_deg: float = Field(1.0, gt=0, le=10, description="rotation step of the search (paper: 1°)")
    margin_m: float = Field(5.0, ge=0, description="offsets keep the footprint centre within the over-view segment's box grown by this (m)")
    truncate_m: float = Field(3.0, gt=0, description="chamfer distances are truncated at this (m): parts missing from the over-view do not dominate")
    inlier_m: float = Field(1.0, gt=0, description="footprint points closer than this to the outline are inliers (m; sub-pixel step, inlier ratio)")
    shift_penalty: float = Field(0.03, ge=0, description="cost per metre of shift from the match (m of chamfer per m), a tie-breaker along straight walls")
    subpixel: bool = Field(True, description="refine the grid optimum below one pixel (parabola + Gauss-Newton on the signed distance)")


@dataclass(frozen=True)
class SearchResult:
    T2d: np.ndarray          # (3,3) levelled street xy → scene xy
    cost_m: float            # mean truncated outline distance at T2d
    seed_cost_m: float       # same at the seed transform
    inlier_ratio: float      # share of points within inlier_m of the outline
    shift_m: float           # how far the footprint centre moved from the seed
    rotation_deg: float      # rotation relative to the seed


class OutlineField:
    """Signed distance (metres, + outside) to one segment's mask edge, on a window of the grid.

    ``clamp_px``: distances are exact up to this many pixels, clamped beyond (``_clamped_edt``): enough
    when only distances up to the truncation, plus the reach of a bilinear sample and of a central
    difference, are ever read (``search_segment``); None: exact everywhere.
    """

    def __init__(self, grid: Grid, mask_window: np.ndarray, row0: int, col0: int, clamp_px: int | None = None) -> None:
        mask = mask_window.astype(bool)
        if mask.all() or not mask.any():        # no edge in the window: scipy's transform, as ever
            clamp_px = None
        planes = _signed_distance_and_gradient(grid, mask, clamp_px)
        self._set(grid, planes, row0, col0, 0, 0, mask_window.shape)

    def _set(self, grid: Grid, planes: np.ndarray, row0: int, col0: int, at_row: int, at_col: int,
             shape: tuple[int, int], trunc: np.ndarray | None = None) -> None:
        """``planes``: (3,H,W) signed distance, d/dx, d/dy on a raster holding the window (grid rows
        row0…, cols col0…, ``shape``) at its row ``at_row``, col ``at_col`` (no copy of the window)."""
        self.grid, self.row0, self.col0 = grid, row0, col0
        h, w = shape
        self.raster = planes                                  # shared by every window cut from it
        self._flat = planes.reshape(3, -1)
        self._width = planes.shape[2]
        self.raster_origin = self._origin = at_row * self._width + at_col   # flat index, window's top-left
        window = (slice(at_row, at_row + h), slice(at_col, at_col + w))
        self.sdf, self.grad_x, self.grad_y = planes[0][window], planes[1][window], planes[2][window]
        self._trunc = trunc

    def truncated(self, truncate_m: float) -> np.ndarray:
        """min(|signed distance|, truncate_m) on the window."""
        if self._trunc is None:
            return np.minimum(np.abs(self.sdf), truncate_m)
        return self._trunc

    def _locate(self, xy: np.ndarray):
        h, w = self.sdf.shape
        row, col = world_to_rows_cols(self.grid.transform, xy, self.row0, self.col0)
        r0, c0, inside = cells_inside(row, col, h, w)
        return row, col, r0, c0, inside

    def sample_with_gradient(self, xy: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
        """(inside (N,) bool or None when all are, (M,3) signed distance, d/dx, d/dy at the M points
        inside the window)."""
        row, col, r0, c0, inside = self._locate(xy)
        if inside is not None:
            row, col, r0, c0 = row[inside], col[inside], r0[inside], c0[inside]
        return inside, interpolate_planes(self._flat, self._width, row, col, r0, c0, self._origin)

    def sample_truncated(self, xy: np.ndarray, truncate_m: float) -> np.ndarray:
        """min(|signed distance|, truncate_m) at xy (truncate_m outside the window)."""
        row, col, r0, c0, inside = self._locate(xy)
        sdf = self._flat[0]
        if inside is None:
            out = interpolate(sdf, self._width, row, col, r0, c0, self._origin)
        else:
            out = np.full(len(xy), float(truncate_m))
            out[inside] = interpolate(sdf, self._width, row[inside], col[inside], r0[inside], c0[inside], self._origin)
        np.abs(out, out=out)
        return np.minimum(out, truncate_m, out=out)


def _signed_distance_and_gradient(grid: Grid, inside: np.ndarray, clamp_px: int | None = None) -> np.ndarray:
    """(3,h,w) signed distance to the edge of the ``inside`` mask (metres, + outside; the edge runs
    between inside and outside pixel centres) and its world gradient (d/dx, d/dy).

    ``clamp_px``: distances are only needed up to this many pixels (exact up to it, somewhere in
    (clamp_px, clamp_px + 1] beyond): a separable pass over ±clamp_px rows instead of scipy's exact
    transform (~3× faster on a whole over-view grid).
    """
    if clamp_px is None:
        d_out = ndimage.distance_transform_edt(~inside)
        d_in = ndimage.distance_transform_edt(inside)
    else:
        d_out, d_in = _clamped_edt(inside, clamp_px), _clamped_edt(~inside, clamp_px)
    out = np.empty((3,) + inside.shape)
    out[0] = np.where(inside, -(d_in - 0.5), d_out - 0.5) * grid.gsd_m
    a, b, _, d, e, _ = grid.transform
    # world gradient = J^-T (d/dcol, d/drow), J maps (dcol, drow) → (dx, dy)
    jinv_t = np.linalg.inv(np.array([[a, b], [d, e]])).T
    g_r, g_c = np.gradient(out[0])
    out[1] = jinv_t[0, 0] * g_c + jinv_t[0, 1] * g_r
    out[2] = jinv_t[1, 0] * g_c + jinv_t[1, 1] * g_r
    return out


def _clamped_edt(features: np.ndarray, clamp_px: int) -> np.ndarray:
    """Euclidean distance (pixels) from every pixel to the nearest True pixel of ``features`` where it
    is at most ``clamp_px`` (equal to scipy's ``distance_transform_edt(~features)`` there), a value in
    (clamp_px, clamp_px + 1] elsewhere. Separable: exact distances along rows, then the minimum of
    g(r + dy)² + dy² over |dy| ≤ clamp_px (a nearer feature cannot be more rows away)."""
    h, w = features.shape
    far = clamp_px + 1
    cols = np.arange(w, dtype=np.int32)
    left = np.maximum.accumulate(np.where(features, cols, np.int32(-2 * far - w)), axis=1)
    right = np.minimum.accumulate(np.where(features, cols, np.int32(2 * far + 2 * w))[:, ::-1], axis=1)[:, ::-1]
    g = np.minimum(np.minimum(cols - left, right - cols), far)
    g2 = g * g
    if far * far + clamp_px * clamp_px <= np.iinfo(np.int16).max:
        g2 = g2.astype(np.int16)         # the same whole numbers in half the memory traffic
    d2 = g2.copy()
    for dy in range(1, min(clamp_px, h - 1) + 1):
        np.minimum(d2[dy:], g2[:-dy] + dy * dy, out=d2[dy:])
        np.minimum(d2[:-dy], g2[dy:] + dy * dy, out=d2[:-dy])
    return np.sqrt(np.minimum(d2, far * far).astype(np.float64))


class AllOutlines:
    """The outline field of every over-view segment together (``seg = None`` searches), computed
    once per tile of the grid, when a search window first touches it, and cut to each window
    (instead of two distance transforms per search: the joint pass alone runs ~130 searches on
    windows of ~250² pixels; on campus the windows touch ~20 % of the grid).

    Only distances up to the truncation plus the reach of a bilinear sample and of a central
    difference are ever used, so a tile is computed with a halo of that many pixels and its
    distances clamped beyond: exactly the whole-grid field where it matters.

    A window cut from it holds the distance to the nearest outline anywhere in the image; one
    computed on the window alone only sees outlines inside the window, so the two differ within
    ``truncate_m`` of the window's edge when an outline lies just outside it (the cut is the true
    distance there). Windows reaching beyond the image are computed on their own as before.
    """

    def __init__(self, grid: Grid, label_image: np.ndarray, truncate_m: float, tile_px: int = 128) -> None:
        self.grid, self.labels, self.truncate_m = grid, np.asarray(label_image), truncate_m
        self.TILE = tile_px
        h, w = self.labels.shape
        self._clamp = int(np.ceil(truncate_m / grid.gsd_m)) + 3
        self._done = np.zeros((-(-h // self.TILE), -(-w // self.TILE)), bool)
        self._planes: np.ndarray | None = None         # (3,h,w), filled tile by tile
        self._trunc: np.ndarray | None = None

    def field(self, r0: int, c0: int, r1: int, c1: int, truncate_m: float) -> OutlineField | None:
        """The field on rows r0:r1, cols c0:c1 (None when the window leaves the image or the
        truncation differs)."""
        h, w = self.labels.shape
        if r0 < 0 or c0 < 0 or r1 > h or c1 > w or r1 <= r0 or c1 <= c0 or truncate_m != self.truncate_m:
            return None
        if self._planes is None:
            self._planes, self._trunc = np.empty((3, h, w)), np.empty((h, w))
        t = self.TILE
        for ti in range(r0 // t, (r1 - 1) // t + 1):
            for tj in range(c0 // t, (c1 - 1) // t + 1):
                if not self._done[ti, tj]:
                    self._compute_tile(ti, tj)
        f = OutlineField.__new__(OutlineField)
        f._set(self.grid, self._planes, r0, c0, r0, c0, (r1 - r0, c1 - c0), self._trunc[r0:r1, c0:c1])
        return f

    def _compute_tile(self, ti: int, tj: int) -> None:
        h, w = self.labels.shape
        t, halo = self.TILE, self._clamp + 2
        R0, C0 = ti * t, tj * t
        R1, C1 = min(R0 + t, h), min(C0 + t, w)
        a0, b0, a1, b1 = max(R0 - halo, 0), max(C0 - halo, 0), min(R1 + halo, h), min(C1 + halo, w)
        tile = _signed_distance_and_gradient(self.grid, self.labels[a0:a1, b0:b1] >= 0, self._clamp)
        core = tile[:, R0 - a0:R1 - a0, C0 - b0:C1 - b0]
        self._planes[:, R0:R1, C0:C1] = core
        self._trunc[R0:R1, C0:C1] = np.minimum(np.abs(core[0]), self.truncate_m)
        self._done[ti, tj] = True


def _splat_stack(rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, int, int]:
    """Bilinear splats of A sets of N fractional (row, col) ((A,N) each) into one kernel frame:
    (A,KH,KW) kernels and the frame's top-left pixel (row, col), shared by every set."""
    base_r, base_c = int(np.floor(rows.min())), int(np.floor(cols.min()))
    r = rows - base_r
    c = cols - base_c
    r0, c0 = np.floor(r).astype(np.int64), np.floor(c).astype(np.int64)
    fr, fc = r - r0, c - c0
    A = rows.shape[0]
    h, w = int(r0.max()) + 2, int(c0.max()) + 2
    at = (np.arange(A, dtype=np.int64) * (h * w))[:, None] + r0 * w + c0
    keys = np.empty((4,) + at.shape, np.int64)      # corner-major, as np.stack of the four: bincount sums in this order
    weights = np.empty((4,) + at.shape)
    gr, gc = 1 - fr, 1 - fc
    for corner, (offset, wr, wc) in enumerate(((0, gr, gc), (1, gr, fc), (w, fr, gc), (w + 1, fr, fc))):
        np.add(at, offset, out=keys[corner])
        np.multiply(wr, wc, out=weights[corner])
    k = np.bincount(keys.ravel(), weights=weights.ravel(), minlength=A * h * w)
    return k.reshape(A, h, w), base_r, base_c


def _correlate_valid(sub: np.ndarray, k: np.ndarray, max_direct_offsets: int = 121) -> np.ndarray:
    """out[a, i, j] = Σ_uv sub[i+u, j+v]·k[a, u, v] over the valid offsets (i, j), for a stack of
    kernels k (A,KH,KW): gathered directly when there are few offsets (the joint pass searches ±4 px
    with a large kernel), else by one batched FFT (the transform of ``sub`` is shared by all
    kernels; a circular correlation of ``sub``'s size leaves the valid offsets unwrapped)."""
    A, KH, KW = k.shape
    n_r, n_c = sub.shape[0] - KH + 1, sub.shape[1] - KW + 1
    if n_r * n_c > max_direct_offsets:
        P, Q = next_fast_len(sub.shape[0], False), next_fast_len(sub.shape[1], True)
        # pruned 2D transforms: the kernels' rows beyond KH are zero (row transforms of KH rows
        # only), and only the n_r valid output rows are transformed back along the rows
        # (in place where scipy can: the same transforms, fewer large temporaries)
        spec = fft(rfft(k[:, ::-1, ::-1], n=Q, axis=2), n=P, axis=1, overwrite_x=True)
        spec *= rfft2(sub, s=(P, Q))
        rows = ifft(spec, axis=1, overwrite_x=True)[:, KH - 1:KH - 1 + n_r]
        return irfft(rows, n=Q, axis=2, overwrite_x=True)[:, :, KW - 1:KW - 1 + n_c]
    kernels = k.reshape(A, KH * KW)
    used = np.flatnonzero((kernels != 0).any(axis=0))      # entries of any rotation (they overlap a lot)
    u, v = np.divmod(used, KW)
    blocks = sliding_window_view(sub, (n_r, n_c))[u, v].reshape(len(used), n_r * n_c)   # sub under each entry
    return (kernels[:, used] @ blocks).reshape(A, n_r, n_c)


def _parabola(cm: float, c0: float, cp: float) -> float:
    den = cm - 2 * c0 + cp
    if den <= 1e-12:
        return 0.0
    return float(np.clip(0.5 * (cm - cp) / den, -0.5, 0.5))


@dataclass
class _GridFit:
    """A search after its grid stage: the grid optimum, awaiting the sub-pixel step."""

    street_xy: np.ndarray
    T_seed: np.ndarray
    T_grid: np.ndarray
    centre: np.ndarray
    field: OutlineField
    p: SearchParams


def search_segment(street_xy: np.ndarray, T_seed: np.ndarray, grid: Grid, label_image: np.ndarray,
                   seg: int | None, bbox: tuple[slice, slice], p: SearchParams,
                   outlines: AllOutlines | None = None, with_seed_cost: bool = True) -> SearchResult:
    """Best 2D rigid transform of ``street_xy`` (levelled) onto over-view segment ``seg``.

    ``bbox``: the (row, col) slices of the window the footprint centre may move in (before the
    margin); ``seg = None`` takes the outline of every over-view segment in the window (cut from
    ``outlines`` when given: one field for all such searches on the same over-view).
    ``with_seed_cost=False``: ``seed_cost_m`` is not evaluated (NaN).
    """
    return search_segments([(street_xy, T_seed, seg, bbox)], grid, label_image, p, outlines, with_seed_cost)[0]


def search_segments(problems: list[tuple[np.ndarray, np.ndarray, int | None, tuple[slice, slice]]], grid: Grid,
                    label_image: np.ndarray, p: SearchParams, outlines: AllOutlines | None = None,
                    with_seed_cost: bool = True) -> list[SearchResult]:
    """``search_segment`` of independent problems (street_xy, T_seed, seg, bbox), their sub-pixel
    steps run together (``toolkit.refine.subpixel``): the same results as one at a time."""
    fits = [_grid_stage(xy, T_seed, grid, label_image, seg, bbox, p, outlines) for xy, T_seed, seg, bbox in problems]
    refined: list[np.ndarray | None] = [None] * len(fits)
    if p.subpixel:
        refined = gauss_newton_many([(f.street_xy, f.T_grid, f.field, f.p) for f in fits])
    return [_result(f, T_gn, with_seed_cost) for f, T_gn in zip(fits, refined)]


def _grid_stage(street_xy: np.ndarray, T_seed: np.ndarray, grid: Grid, label_image: np.ndarray,
                seg: int | None, bbox: tuple[slice, slice], p: SearchParams, outlines: AllOutlines | None) -> _GridFit:
    """Every rotation and one-pixel offset (one batched correlation), then a parabola through the
    neighbouring grid costs."""
    gsd = grid.gsd_m
    seed_xy = street_xy @ T_seed[:2, :2].T + T_seed[:2, 2]
    centre = column_means(seed_xy)
    n_rot = round(p.rotation_range_deg / p.rotation_step_deg)
    angles = np.radians(np.arange(-n_rot, n_rot + 1) * p.rotation_step_deg)
    margin = int(np.ceil(p.margin_m / gsd))
    c_rc = grid.world_to_pixel(centre[None])[0]
    rs, cs = bbox
    dr0 = int(np.floor(min(0.0, rs.start - margin - c_rc[0])))
    dr1 = int(np.ceil(max(0.0, rs.stop - 1 + margin - c_rc[0])))
    dc0 = int(np.floor(min(0.0, cs.start - margin - c_rc[1])))
    dc1 = int(np.ceil(max(0.0, cs.stop - 1 + margin - c_rc[1])))

    rel_x, rel_y = seed_xy[:, 0] - centre[0], seed_xy[:, 1] - centre[1]
    cos, sin = np.cos(angles)[:, None], np.sin(angles)[:, None]
    rows, cols = rows_cols(grid.transform, (rel_x * cos - rel_y * sin) + centre[0],
                           (rel_x * sin + rel_y * cos) + centre[1])
    kernels, k_r0, k_c0 = _splat_stack(rows, cols)       # (A,KH,KW), one frame for all rotations
    KH, KW = kernels.shape[1:]
    win_r0, win_c0 = k_r0 + dr0 - 1, k_c0 + dc0 - 1
    win_r1, win_c1 = k_r0 + KH + dr1 + 1, k_c0 + KW + dc1 + 1
    field = None
    if seg is None and outlines is not None:
        field = outlines.field(win_r0, win_c0, win_r1, win_c1, p.truncate_m)
    if field is None:
        labels = _window(label_image, win_r0, win_c0, win_r1, win_c1, fill=-1)
        # distances beyond the truncation (or the inlier band, if wider) plus a bilinear sample's and
        # a central difference's reach are never read: exact up to there is the exact field
        clamp_px = int(np.ceil(max(p.truncate_m, p.inlier_m) / gsd)) + 3
        field = OutlineField(grid, labels >= 0 if seg is None else labels == seg, win_r0, win_c0, clamp_px)
    trunc = field.truncated(p.truncate_m)

    n = len(street_xy)
    dr = np.arange(dr0, dr1 + 1)[:, None]
    dc = np.arange(dc0, dc1 + 1)[None, :]
    a, b, _, d, e, _ = grid.transform
    shift_m = np.hypot(a * dc + b * dr, d * dc + e * dr)
    sub = trunc[1:1 + (dr1 - dr0) + KH, 1:1 + (dc1 - dc0) + KW]
    costs = _correlate_valid(sub, kernels) / n + p.shift_penalty * shift_m
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

    return _GridFit(street_xy, T_seed, rotation_about(ang, centre, shift) @ T_seed, centre, field, p)


def _result(fit: _GridFit, T_gn: np.ndarray | None, with_seed_cost: bool) -> SearchResult:
    """The grid or the refined transform, whichever fits better, and its figures."""
    street_xy, T_seed, field, p = fit.street_xy, fit.T_seed, fit.field, fit.p

    def chamfer(T: np.ndarray) -> np.ndarray:
        return field.sample_truncated(street_xy @ T[:2, :2].T + T[:2, 2], p.truncate_m)

    T_best, d_final = fit.T_grid, chamfer(fit.T_grid)
    if T_gn is not None:
        d_gn = chamfer(T_gn)
        if d_gn.mean() <= d_final.mean() + 1e-6:
            T_best, d_final = T_gn, d_gn
    moved = column_means(street_xy @ T_best[:2, :2].T + T_best[:2, 2]) - fit.centre
    rot = np.degrees(np.arctan2(T_best[1, 0], T_best[0, 0]) - np.arctan2(T_seed[1, 0], T_seed[0, 0]))
    return SearchResult(
        T2d=T_best, cost_m=float(d_final.mean()),
        seed_cost_m=float(chamfer(T_seed).mean()) if with_seed_cost else float("nan"),
        inlier_ratio=float((d_final < p.inlier_m).mean()), shift_m=float(np.hypot(*moved)),
        rotation_deg=float((rot + 180) % 360 - 180))


def _window(arr: np.ndarray, r0: int, c0: int, r1: int, c1: int, fill=False) -> np.ndarray:
    """arr[r0:r1, c0:c1], ``fill`` outside the image."""
    h, w = arr.shape
    out = np.full((r1 - r0, c1 - c0), fill, dtype=arr.dtype)
    rr0, cc0, rr1, cc1 = max(r0, 0), max(c0, 0), min(r1, h), min(c1, w)
    if rr1 > rr0 and cc1 > cc0:
        out[rr0 - r0:rr1 - r0, cc0 - c0:cc1 - c0] = arr[rr0:rr1, cc0:cc1]
    return out
