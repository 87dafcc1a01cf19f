"""Vectorised chamfer pose search of street point sets on a ``CropAtlas``.

A *pair* is (street edge, label): the edge's two street segments, each looked up in its own
candidate segment's crop. Points are stored per segment relative to the segment centre and padded
by repeating the first point (whose repeated look-ups are subtracted exactly). A pose is
(θ, integer pixel offset): pixel = round(A·R(θ)·(x - mid) + pivot) + offset, where A is the
world→pixel linear map, mid the street centre-line midpoint and pivot its pixel position.
Rotations are applied once per pose angle; offsets are flat-index shifts (PERF_NOTES).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree

from toolkit.matching.atlas import SCALE, CropAtlas
from toolkit.matching.config import MatchingConfig
from toolkit.threads import map_in_order


class ChamferConfig(MatchingConfig):
    """The truncated chamfer the data term scores poses with (distance maps: ``toolkit.matching.atlas``)."""

    truncate_px: float = Field(5.0, gt=0, description="chamfer distances are truncated here (px; released code: 5 px threshold)")
    directional: bool = Field(False, description="directional chamfer: add an orientation channel (distance + weight·|Δangle|)")
    orientation_bins: int = Field(8, ge=2, le=32, description="orientation bins over [0, π) when directional (count)")
    orientation_weight_px_per_rad: float = Field(
        10.0, ge=0, description="directional chamfer weight (px per radian; released code: DT + 10·|Δangle|)")


# --- street points ------------------------------------------------------------------------------
def subsample_segment(xy: np.ndarray, cell_m: float, max_points: int) -> np.ndarray:
    """Even subsample of a façade footprint: one point per occupied cell, then evenly spaced
    along the principal axis up to ``max_points``. Deterministic."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(xy) == 0:
        return xy
    keys = np.floor((xy - xy.min(axis=0)) / cell_m).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    counts = np.bincount(inverse.ravel())
    cells = np.zeros((len(first), 2))
    np.add.at(cells, inverse.ravel(), xy)
    cells /= counts[:, None]
    centred = cells - cells.mean(axis=0)
    if len(cells) > 1:
        _, _, vt = np.linalg.svd(centred, full_matrices=False)
        order = np.argsort(centred @ vt[0], kind="stable")
        cells = cells[order]
    if len(cells) > max_points:
        cells = cells[even_indices(len(cells), max_points)]
    return cells


def even_indices(n: int, m: int) -> np.ndarray:
    """m evenly spaced indices in 0..n-1 (all of them when m ≥ n)."""
    if m >= n:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, m)).astype(np.int64))


def point_directions(xy: np.ndarray, k: int = 8) -> np.ndarray:
    """Local line direction (angle in [0, π), street frame) of each point by PCA of its k neighbours."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(xy) < 2:
        return np.zeros(len(xy))
    kk = min(k, len(xy))
    _, idx = cKDTree(xy).query(xy, k=kk)
    nb = xy[idx.reshape(len(xy), kk)]
    d = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", d, d)
    # principal direction of a 2x2 symmetric matrix in closed form
    ang = 0.5 * np.arctan2(2 * cov[:, 0, 1], cov[:, 0, 0] - cov[:, 1, 1])
    return np.mod(ang, np.pi)


@dataclass(frozen=True)
class SegmentPoints:
    """Street points per segment relative to its centre, padded to n by repeating the first point.

    xy: (S,n,2) float32; n_pad: (S,) padding count (its look-ups are subtracted exactly);
    angle: (S,n) float32 local direction (street frame) or None; centre: (S,2) float64;
    mid: (E,2) float64 midpoint of each street edge's centre line; edges: (E,2).
    """

    xy: np.ndarray
    n_pad: np.ndarray
    angle: np.ndarray | None
    centre: np.ndarray
    mid: np.ndarray
    edges: np.ndarray

    @property
    def n_real(self) -> np.ndarray:
        return self.xy.shape[1] - self.n_pad


def segment_points(seg_points: list[np.ndarray], seg_angles: list[np.ndarray] | None, centres: np.ndarray,
                   edges: np.ndarray) -> SegmentPoints:
    S = len(seg_points)
    n = int(max(1, max((len(x) for x in seg_points), default=1)))
    xy = np.zeros((S, n, 2), np.float32)
    angle = np.zeros((S, n), np.float32) if seg_angles is not None else None
    n_pad = np.full(S, n, np.int64)
    for i, pts in enumerate(seg_points):  # one iteration per street segment
        m = len(pts)
        if m == 0:
            continue
        rel = pts - centres[i]
        xy[i, :m] = rel
        xy[i, m:] = rel[0]
        n_pad[i] = n - m
        if angle is not None:
            angle[i, :m] = seg_angles[i]
            angle[i, m:] = seg_angles[i][0]
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    mid = (centres[edges[:, 0]] + centres[edges[:, 1]]) / 2 if len(edges) else np.zeros((0, 2))
    return SegmentPoints(xy, n_pad, angle, np.asarray(centres, dtype=np.float64), mid, edges)


# --- pose search --------------------------------------------------------------------------------
@dataclass(frozen=True)
class Pairs:
    """Candidate pairs: edge (P,), crops (P,2) over-view segments of (j, k), theta (P,) base angle,
    pivot_px (P,2) base pixel (row, col) of the midpoint, offset (P,2) int base pixel offset,
    window_px (P,) allowed |offset| (Euclidean) or None."""

    edge: np.ndarray
    crops: np.ndarray
    theta: np.ndarray
    pivot_px: np.ndarray
    offset: np.ndarray
    window_px: np.ndarray | None = None

    def take(self, idx: np.ndarray) -> Pairs:
        return Pairs(self.edge[idx], self.crops[idx], self.theta[idx], self.pivot_px[idx],
                     self.offset[idx], None if self.window_px is None else self.window_px[idx])


def search(atlas: CropAtlas, erosion: int, A: np.ndarray, pts: SegmentPoints, pairs: Pairs,
           d_theta: np.ndarray, d_off: np.ndarray, max_elems: int = 4_000_000,
           probes: SegmentPoints | None = None, probe_weight: float = 0.0, workers: int = 1
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best pose per pair over the grid (θ + d_theta) × (offset + d_off).

    Returns cost (P,) in [0, 1] (mean truncated distance / truncation), theta (P,), offset (P,2).
    With ``probes`` (free-space points on the observer's side of each façade, same centres) the
    cost is (1 - w)·chamfer + w·(share of probes inside their own candidate segment), w =
    ``probe_weight``, for pairs that have probes. Batches run in up to ``workers`` threads, at most
    the thread budget (``toolkit.threads``).
    """
    use_probes = probes is not None and probe_weight > 0 and atlas.inside is not None
    buf = atlas.level(erosion)
    d_theta = np.asarray(d_theta, dtype=np.float64).reshape(-1)
    d_off = np.asarray(d_off, dtype=np.int64).reshape(-1, 2)
    P, n = len(pairs.edge), pts.xy.shape[1]
    R, O = len(d_theta), len(d_off)
    cost = np.empty(P)
    best_theta = np.empty(P)
    best_off = np.empty((P, 2), np.int64)
    A32 = A.astype(np.float32)
    step = max(1, max_elems // (R * n * O))

    def batch(s: int) -> None:  # writes its own slice of the outputs
        sl = slice(s, min(P, s + step))
        b = sl.stop - sl.start
        th = pairs.theta[sl, None] + d_theta[None, :]              # (b,R)
        c, sn = np.cos(th), np.sin(th)
        # A·R(θ) per pose, formed before touching the points
        m00, m01 = A[0, 0] * c + A[0, 1] * sn, A[0, 1] * c - A[0, 0] * sn
        m10, m11 = A[1, 0] * c + A[1, 1] * sn, A[1, 1] * c - A[1, 0] * sn
        offs = pairs.offset[sl, None, :] + d_off[None]              # (b,O,2)
        delta = atlas.offset_delta(offs)[:, None, None, :]          # (b,1,1,O)
        sums = np.zeros((b, R, O), np.int64)
        n_real = np.zeros(b, np.int64)
        p_sums = np.zeros((b, R, O), np.int64)
        p_real = np.zeros(b, np.int64)
        mid = pts.mid[pairs.edge[sl]]
        for side in (0, 1):
            seg = pts.edges[pairs.edge[sl], side]
            # segment centre relative to the edge midpoint, through the pose, plus the pivot
            rel = pts.centre[seg] - mid
            br = pairs.pivot_px[sl, 0, None] + m00 * rel[:, :1] + m01 * rel[:, 1:]
            bc = pairs.pivot_px[sl, 1, None] + m10 * rel[:, :1] + m11 * rel[:, 1:]
            crop = pairs.crops[sl, side][:, None, None]
            if use_probes:
                P_ = probes.xy[seg]
                flat = atlas.flat_index(_affine_round(m00, m01, P_[:, None, :, 0], P_[:, None, :, 1], br),
                                        _affine_round(m10, m11, P_[:, None, :, 0], P_[:, None, :, 1], bc), crop)
                _add_lookups(p_sums, atlas.inside, flat, delta, probes.n_pad[seg])
                p_real += probes.n_real[seg]
            X = pts.xy[seg]                                          # (b,n,2) float32
            x, y = X[:, None, :, 0], X[:, None, :, 1]
            rows = _affine_round(m00, m01, x, y, br)
            cols = _affine_round(m10, m11, x, y, bc)
            bins = None
            if atlas.n_bins > 1 and pts.angle is not None:
                bins = _orientation_bins(atlas, pts.angle[seg], th, A32)
            _add_lookups(sums, buf, atlas.flat_index(rows, cols, crop, bins), delta, pts.n_pad[seg])
            n_real += pts.n_real[seg]
        val = sums.astype(np.float64) / (np.maximum(n_real, 1) * SCALE)[:, None, None]
        if use_probes:
            w = np.where(p_real > 0, probe_weight, 0.0)[:, None, None]
            val = (1 - w) * val + w * p_sums / (np.maximum(p_real, 1) * SCALE)[:, None, None]
        if pairs.window_px is not None:
            outside = np.hypot(offs[..., 0], offs[..., 1]) > pairs.window_px[sl, None] + 1e-9
            val = np.where(outside[:, None, :], np.inf, val)
        flat_best = np.argmin(val.reshape(b, -1), axis=1)
        r_i, o_i = np.divmod(flat_best, O)
        cost[sl] = val.reshape(b, -1)[np.arange(b), flat_best]
        best_theta[sl] = th[np.arange(b), r_i]
        best_off[sl] = offs[np.arange(b), o_i]

    for _ in map_in_order(batch, range(0, P, step), workers):
        pass
    return cost, best_theta, best_off


def _add_lookups(sums: np.ndarray, buf: np.ndarray, flat: np.ndarray, delta: np.ndarray, n_pad: np.ndarray) -> None:
    """sums (b,R,O) += the look-ups of ``buf`` at flat (b,R,n) + delta (b,1,1,O), summed over the points;
    padding repeats the first point: its repeated look-ups are removed exactly."""
    vals = buf[flat[..., None] + delta]                        # (b,R,n,O) uint8
    sums += vals.sum(axis=2, dtype=np.int64)
    sums -= n_pad[:, None, None] * vals[:, :, 0, :].astype(np.int64)


def _orientation_bins(atlas: CropAtlas, angle: np.ndarray, th: np.ndarray, A32: np.ndarray) -> np.ndarray:
    """(b,R,n) directional plane of each point: its street-frame angle (b,n) turned by the poses th (b,R)."""
    a = angle[:, None, :] + th[..., None].astype(np.float32)
    ca, sa = np.cos(a), np.sin(a)
    pix_ang = np.arctan2(A32[0, 0] * ca + A32[0, 1] * sa, A32[1, 0] * ca + A32[1, 1] * sa)
    return np.floor(np.mod(pix_ang, np.pi) / np.pi * atlas.n_bins).astype(np.int64) % atlas.n_bins


def _affine_round(m0: np.ndarray, m1: np.ndarray, x: np.ndarray, y: np.ndarray, b: np.ndarray) -> np.ndarray:
    """round(m0·x + m1·y + b) as int64; m0, m1, b: (b,R) per pose, x, y: (b,1,n) float32."""
    v = m0[..., None].astype(np.float32) * x
    v += m1[..., None].astype(np.float32) * y
    v += b[..., None].astype(np.float32)
    np.rint(v, out=v)
    return v.astype(np.int64)


def grid_offsets(radius: int, step: int) -> np.ndarray:
    """(O,2) integer offsets on a square grid of ``step`` covering [-radius, radius]²."""
    k = int(np.ceil(radius / step)) if step > 0 else 0
    v = np.arange(-k, k + 1) * step
    rr, cc = np.meshgrid(v, v, indexing="ij")
    return np.stack([rr.ravel(), cc.ravel()], axis=1)


def ranges(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Concatenation of arange(s, s + n) for each (s, n), vectorised."""
    lengths = np.asarray(lengths, dtype=np.int64)
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    ends = np.cumsum(lengths)
    out = np.ones(total, np.int64)
    nz = lengths > 0
    first = np.concatenate([[0], ends[:-1]])[nz]
    st = np.asarray(starts, dtype=np.int64)[nz]
    out[first[0]] = st[0]
    if len(first) > 1:
        prev_end = (st + lengths[nz] - 1)[:-1]
        out[first[1:]] = st[1:] - prev_end
    return np.cumsum(out)
