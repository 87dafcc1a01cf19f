"""Per-segment truncated distance maps packed into one flat buffer (an "atlas") for chamfer look-ups.

Each over-view segment gets its own crop around its bounding box holding the distance (in pixels)
to *its* boundary, truncated at ``truncate_px`` and quantised to uint8 (255 = truncated). A street
point that a label maps onto segment p is looked up in p's crop only, so a label is rewarded for
putting each street segment on its own over-view segment, not on whatever building is nearest.

Offsets are searched as flat-index shifts (PERF_NOTES: rotate once, then integer offsets). For that
a point is clipped into the crop's inner area [reach, size-1-reach]; the crop extends
``2*reach + truncate + 2`` pixels beyond the boundary's bounding box, so a clipped point stays at
least ``truncate`` pixels from the boundary under any offset up to ``reach`` and reads 255, which is
what the unclipped point would read.

Coarse search levels read eroded copies (grey erosion, a min filter of radius e): the value at a
coarse offset is then a lower bound of the values within ±e pixels, so a coarse grid of step 2e
does not skip the true optimum.

The directional variant stores ``n_bins`` planes per level: plane b holds
``min_b' (DT_b' + weight·Δangle(b, b'))`` where DT_b' is the distance to boundary pixels whose
tangent falls in orientation bin b' (directional chamfer, Liu et al. 2010).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

SCALE = 255  # quantisation: value = round(min(d, truncate) / truncate * SCALE)


@dataclass(frozen=True)
class CropAtlas:
    """levels[i]: flat uint8 buffer (n_bins planes of plane_size) for erosion radius erosion_px[i].

    origin/size/place: (S,2) int64 (row, col) of each crop's top-left on the over-view grid, its
    size, and its top-left in the packed plane.
    """

    levels: tuple[np.ndarray, ...]
    erosion_px: tuple[int, ...]
    stride: int
    plane_size: int
    n_bins: int
    origin: np.ndarray
    size: np.ndarray
    place: np.ndarray
    reach: int
    truncate_px: float
    inside: np.ndarray | None = None  # flat uint8 (one plane): SCALE inside the crop's segment, else 0

    @property
    def nbytes(self) -> int:
        return sum(b.nbytes for b in self.levels)

    def level(self, erosion: int) -> np.ndarray:
        return self.levels[self.erosion_px.index(erosion)]

    def flat_index(self, rows: np.ndarray, cols: np.ndarray, crop: np.ndarray,
                   bins: np.ndarray | None = None) -> np.ndarray:
        """Integer grid (rows, cols) looked up in crop ``crop`` → flat buffer indices (int64).

        ``crop`` may have fewer dimensions that broadcast against rows/cols (per-point constants
        are then computed once). ``rows``/``cols`` are overwritten (clipped in place)."""
        lo_r, hi_r, sh_r, lo_c, hi_c, sh_c = self.crop_constants(crop)
        np.maximum(rows, lo_r, out=rows)
        np.minimum(rows, hi_r, out=rows)
        np.maximum(cols, lo_c, out=cols)
        np.minimum(cols, hi_c, out=cols)
        rows += sh_r
        rows *= self.stride
        rows += cols
        rows += sh_c
        if bins is not None and self.n_bins > 1:
            rows += bins.astype(np.int64) * self.plane_size
        return rows

    def crop_constants(self, crop: np.ndarray) -> tuple[np.ndarray, ...]:
        """Clip bounds and shifts (grid → packed plane) of each entry of ``crop``."""
        table = self._constants()
        return tuple(np.take(col, crop) for col in table)

    def _constants(self) -> tuple[np.ndarray, ...]:
        cached = self.__dict__.get("_const")
        if cached is None:
            o, s, pl = self.origin, self.size, self.place
            lo, hi, sh = o + self.reach, o + s - 1 - self.reach, pl - o
            cached = tuple(np.ascontiguousarray(a[:, i]) for i in (0, 1) for a in (lo, hi, sh))
            object.__setattr__(self, "_const", cached)
        return cached

    def offset_delta(self, offsets: np.ndarray) -> np.ndarray:
        """(...,2) integer (drow, dcol) → flat shifts."""
        offsets = np.asarray(offsets, dtype=np.int64)
        return offsets[..., 0] * self.stride + offsets[..., 1]


def boundary_tangent_angle(mask: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                           sigma_px: float = 1.5) -> np.ndarray:
    """Tangent angle in [0, π) (pixel frame: atan2(drow, dcol)) of a mask's boundary at given pixels."""
    sm = ndi.gaussian_filter(mask.astype(np.float64), sigma_px)
    g_r = ndi.sobel(sm, axis=0)[rows, cols]
    g_c = ndi.sobel(sm, axis=1)[rows, cols]
    # the gradient is the boundary normal; the tangent is perpendicular to it
    return np.mod(np.arctan2(g_r, g_c) + np.pi / 2, np.pi)


def _directional_planes(mask_b: np.ndarray, angles: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                        n_bins: int, weight_px_per_rad: float, truncate: float) -> np.ndarray:
    shape = mask_b.shape
    bin_of = np.floor(angles / np.pi * n_bins).astype(np.int64) % n_bins
    dts = np.full((n_bins,) + shape, np.inf)
    for b in range(n_bins):
        sel = bin_of == b
        if sel.any():
            m = np.ones(shape, bool)
            m[rows[sel], cols[sel]] = False
            dts[b] = ndi.distance_transform_edt(m)
    centres = (np.arange(n_bins) + 0.5) * np.pi / n_bins
    diff = np.abs(centres[:, None] - centres[None, :])
    diff = np.minimum(diff, np.pi - diff)  # orientations are modulo π
    out = np.empty((n_bins,) + shape)
    for b in range(n_bins):
        out[b] = np.min(dts + weight_px_per_rad * diff[b][:, None, None], axis=0)
    return np.minimum(out, truncate)


def _pack(sizes: np.ndarray, min_width: int) -> tuple[np.ndarray, int, int]:
    """Shelf packing of (n,2) (h, w) rectangles → (n,2) placements, plane height, stride."""
    width = int(max(min_width, sizes[:, 1].max()))
    order = np.argsort(-sizes[:, 0], kind="stable")
    place = np.zeros_like(sizes)
    x = y = shelf_h = 0
    for i in order:  # one iteration per segment
        h, w = sizes[i]
        if x + w > width:
            y, x, shelf_h = y + shelf_h, 0, 0
        place[i] = (y, x)
        x += w
        shelf_h = max(shelf_h, h)
    return place, int(y + shelf_h), width


def build_atlas(label_image: np.ndarray, boundary_px: tuple[np.ndarray, ...], truncate_px: float,
                reach_px: int, erosions: tuple[int, ...] = (0,), n_bins: int = 1,
                orientation_weight_px_per_rad: float = 10.0, with_inside: bool = False) -> CropAtlas:
    """Crops of every segment's truncated boundary distance, at each erosion radius; with_inside
    adds each segment's interior (eroded by one pixel) for free-space tests."""
    n = len(boundary_px)
    truncate = float(truncate_px)
    margin = 2 * reach_px + int(np.ceil(truncate)) + 2
    origin = np.zeros((n, 2), np.int64)
    size = np.zeros((n, 2), np.int64)
    # Beyond truncate_px + 1 of its boundary's bounding box a crop is one plateau (truncate): the
    # distances and erosions are computed on that tight box only (values[p] starts at corner[p] of
    # the crop) and the plateau comes from the plane's fill (≈10× less work, the same bytes).
    pad = int(np.ceil(truncate)) + 1
    values: list[np.ndarray] = []
    corner = np.zeros((n, 2), np.int64)
    for p in range(n):  # one iteration per over-view segment
        b = np.asarray(boundary_px[p], dtype=np.int64).reshape(-1, 2)
        lo = b.min(axis=0) if len(b) else np.zeros(2, np.int64)
        hi = b.max(axis=0) if len(b) else np.zeros(2, np.int64)
        origin[p] = lo - margin
        size[p] = hi - lo + 1 + 2 * margin
        shape = tuple(size[p])
        if not len(b):
            values.append(np.full((n_bins, 0, 0), truncate))
            continue
        rr, cc = b[:, 0] - origin[p, 0], b[:, 1] - origin[p, 1]
        if n_bins > 1:
            mask = _segment_mask(label_image, p, origin[p], shape)
            ang = boundary_tangent_angle(mask, rr, cc)
            values.append(_directional_planes(mask, ang, rr, cc, n_bins,
                                              orientation_weight_px_per_rad, truncate))
        else:
            corner[p] = np.maximum(margin - pad, 0)
            h, w = np.minimum(size[p] - corner[p], hi - lo + 1 + 2 * pad)
            m = np.ones((h, w), bool)
            m[rr - corner[p, 0], cc - corner[p, 1]] = False
            values.append(np.minimum(ndi.distance_transform_edt(m), truncate)[None])
    place, plane_h, stride = _pack(size, min_width=2048)
    plane_size = plane_h * stride
    levels = []
    for e in erosions:
        buf = np.full((n_bins, plane_h, stride), SCALE, np.uint8)
        for p, v in enumerate(values):
            r0, c0 = place[p] + corner[p]
            if e > 0 and v.size:
                v, (r0, c0) = _grow(v, corner[p], size[p], e, truncate), place[p] + np.maximum(corner[p] - e, 0)
                v = ndi.grey_erosion(v, size=(1, 2 * e + 1, 2 * e + 1), mode="nearest")
            q = np.rint(v * (SCALE / truncate)).astype(np.uint8)
            buf[:, r0:r0 + q.shape[1], c0:c0 + q.shape[2]] = q
        levels.append(buf.reshape(-1))
    inside = None
    if with_inside:
        ins = np.zeros((plane_h, stride), np.uint8)
        for p in range(n):
            shape = (int(size[p, 0]), int(size[p, 1]))
            m = ndi.binary_erosion(_segment_mask(label_image, p, origin[p], shape))
            (r0, c0), (h, w) = place[p], size[p]
            ins[r0:r0 + h, c0:c0 + w] = np.where(m, SCALE, 0)
        inside = ins.reshape(-1)
    return CropAtlas(tuple(levels), tuple(int(e) for e in erosions), stride, plane_size, n_bins,
                     origin, size, place, int(reach_px), truncate, inside)


def _grow(v: np.ndarray, corner: np.ndarray, crop: np.ndarray, e: int, truncate: float) -> np.ndarray:
    """The (B,h,w) box ``v`` at ``corner`` of its crop, padded with the plateau by ``e`` on each side
    (within the crop), so that an erosion of radius e sees what it would see on the whole crop."""
    before = np.minimum(corner, e)
    after = np.minimum(crop - corner - np.array(v.shape[1:]), e)
    return np.pad(v, ((0, 0), (before[0], after[0]), (before[1], after[1])), constant_values=truncate)


def _segment_mask(label_image: np.ndarray, p: int, origin: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """label_image == p over a crop that may extend beyond the grid."""
    H, W = label_image.shape
    out = np.zeros(shape, bool)
    r0, c0 = int(origin[0]), int(origin[1])
    rs, cs = max(r0, 0), max(c0, 0)
    re, ce = min(r0 + shape[0], H), min(c0 + shape[1], W)
    if re > rs and ce > cs:
        out[rs - r0:re - r0, cs - c0:ce - c0] = label_image[rs:re, cs:ce] == p
    return out
