"""Distance-weighted blending of segment transforms (paper Eq. 6), vectorised over points in chunks.

Every point has an *anchor* segment: its carrier when that segment is valid, else the nearest
valid segment (by distance to its footprint). It is moved by the weighted average of the
transforms of its anchor and the anchor's K nearest valid neighbours, with ``w_j = 1/log(d_j)``,
``d_j`` the horizontal distance from the point to segment j's footprint. ``log(d) ≤ 0`` for
``d ≤ 1 m``, so d is clamped to ``d_min > 1 m`` (the weight of a point's own segment is then
``1/log(d_min)``; see the stage parameters for the default).

Averaging transforms: each transform is expressed about the point itself (the local origin), so
the blended translation is ``Σ w_j T_j(p) / Σ w_j`` — independent of where the frames' origins are
(scene coordinates are large UTM numbers) — and the blended rotation is the weighted quaternion
mean (Markley et al. 2007: the principal eigenvector of ``Σ w q qᵀ``), never a matrix average.
Positions only need the first; camera orientations use the second.

Speed: the weights of a point are evaluated at the centre of its (anchor, ``cell_m`` cell) — one
set of footprint distances and one blended affine map ``A p + b`` per cell, then applied to the
points in chunks (bounded memory). On campus (3.5 M points, 171 segments, K = 16) this took the
point blend from 15–26 s (per-point KD queries against 17 footprints) to a few seconds, moving
points by < 0.03 m at the 99th percentile (max 0.19 m) at 0.5 m cells.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from toolkit.errors import StageError
from toolkit.refine.blas import workers_for
from toolkit.refine.consistency import gap_matrix
from toolkit.refine.segments import input_anchors, thin_xy
from toolkit.types import SegmentTransforms, StreetSegments


def inverse_log_weights(d: np.ndarray, d_min: float) -> np.ndarray:
    """w = 1/log(max(d, d_min)); requires d_min > 1 m."""
    if not d_min > 1.0:
        raise ValueError(f"d_min must exceed 1 m, got {d_min}")
    return 1.0 / np.log(np.maximum(d, d_min))


def quaternions(R: np.ndarray) -> np.ndarray:
    """(...,3,3) → (...,4) unit quaternions (w, x, y, z)."""
    from scipy.spatial.transform import Rotation

    shape = R.shape[:-2]
    xyzw = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1).reshape(shape + (4,))


def average_rotations(R: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted rotation mean: R (M,K,3,3), w (M,K) → (M,3,3) (principal eigenvector of Σ w q qᵀ)."""
    from scipy.spatial.transform import Rotation

    q = quaternions(R)                                   # (M,K,4)
    M = np.einsum("mk,mki,mkj->mij", w, q, q)
    _, vec = np.linalg.eigh(M)
    qm = vec[..., -1]                                    # (M,4) w,x,y,z
    return Rotation.from_quat(np.concatenate([qm[:, 1:], qm[:, :1]], axis=1)).as_matrix()


@dataclass
class SegmentIndex:
    """Footprints of the valid segments (levelled xy) for point-to-segment distances."""

    valid: np.ndarray            # (V,) indices of valid segments
    trees: dict[int, cKDTree]
    all_tree: cKDTree
    all_seg: np.ndarray
    neighbours: dict[int, np.ndarray]

    @classmethod
    def build(cls, street: StreetSegments, transforms: SegmentTransforms, k: int, cell_m: float = 1.0,
              agree_tol_m: float = np.inf, agree_ratio: float = 0.0, max_gap_m: float = np.inf) -> SegmentIndex:
        """Neighbours: the k valid segments nearest (footprint to footprint, at most ``max_gap_m``
        apart) among those whose transform agrees with the segment's own (gap at both centres ≤
        agree_tol_m + agree_ratio·d): after a loop the street frame puts segments of another pass
        next to it, drifted away."""
        valid = np.flatnonzero(np.asarray(transforms.valid, bool))
        if len(valid) == 0:
            raise StageError("warp: no valid segment transform (refine registered nothing)")
        fps = {}
        for i in valid:
            b = np.asarray(street.boundary_xy[i], np.float64).reshape(-1, 2)
            if len(b) == 0:
                b = np.asarray(street.centroids[i], np.float64).reshape(1, 2)
            fps[int(i)] = thin_xy(b, cell_m, 100_000)
        trees = {i: cKDTree(f) for i, f in fps.items()}
        all_xy = np.concatenate([fps[int(i)] for i in valid])
        all_seg = np.concatenate([np.full(len(fps[int(i)]), int(i)) for i in valid])
        neighbours = {}
        cent = np.asarray(street.centroids, np.float64).reshape(-1, 2)[valid]
        ctree = cKDTree(cent)
        anchors = input_anchors(street)
        T = np.asarray(transforms.T, np.float64)
        for row, i in enumerate(valid):
            pre = valid[np.atleast_1d(ctree.query(cent[row], k=min(3 * k + 1, len(valid)))[1])]
            pre = pre[pre != i]
            if np.isfinite(agree_tol_m) and len(pre):
                disagree = gap_matrix(T, anchors, np.column_stack([np.full(len(pre), i), pre]))
                dist = np.linalg.norm(anchors[pre] - anchors[i], axis=1)
                pre = pre[disagree <= agree_tol_m + agree_ratio * dist]
            gap = np.array([trees[int(j)].query(fps[int(i)])[0].min() for j in pre])
            order = np.argsort(gap, kind="stable")[:k]
            neighbours[int(i)] = pre[order][gap[order] <= max_gap_m]
        return cls(valid, trees, cKDTree(all_xy), all_seg, neighbours)

    def nearest(self, xy: np.ndarray) -> np.ndarray:
        _, idx = self.all_tree.query(xy, workers=workers_for(len(xy)))
        return self.all_seg[idx]

    def anchors(self, xy: np.ndarray, carrier: np.ndarray, valid_mask: np.ndarray) -> np.ndarray:
        carrier = np.asarray(carrier, np.int64)
        ok = (carrier >= 0) & (carrier < len(valid_mask))
        ok[ok] = valid_mask[carrier[ok]]
        out = carrier.copy()
        if (~ok).any():
            out[~ok] = self.nearest(xy[~ok])
        return out

    def candidates(self, anchor: int, k: int) -> np.ndarray:
        return np.concatenate([[anchor], self.neighbours[anchor][:k]]).astype(np.int64)

    def distances(self, cand: np.ndarray, xy: np.ndarray) -> np.ndarray:
        w = workers_for(len(xy))
        return np.column_stack([self.trees[int(j)].query(xy, workers=w)[0] for j in cand])


def cell_keys(xy: np.ndarray, anchors: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(U,) unique (anchor, xy cell) pairs as (anchor, cell centre xy) and each point's row in them.

    Returns (rows (N,), table (U,3): anchor, centre x, centre y). Cells are ``cell_m`` squares of the
    levelled xy plane; rows are sorted by anchor, then cell (deterministic).

    Speed: points are grouped by anchor with a radix sort, then each anchor's cells are counted on
    its own small dense key range (the same rows as a ``np.unique`` of (anchor, cell) keys, whose
    sort of 3.5 M int64 keys took ~0.4 s).
    """
    cell = np.floor(xy / cell_m).astype(np.int64)
    anchors = np.asarray(anchors, np.int64)
    if len(anchors) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    small = anchors.min() >= 0 and anchors.max() < np.iinfo(np.int16).max
    order = np.argsort(anchors.astype(np.int16) if small else anchors, kind="stable")
    sorted_anchor = anchors[order]
    bounds = np.flatnonzero(np.diff(sorted_anchor)) + 1
    rows = np.empty(len(anchors), np.int64)
    tables = []
    n_rows = 0
    for lo, hi in zip(np.concatenate([[0], bounds]), np.concatenate([bounds, [len(order)]])):
        idx = order[lo:hi]
        c = cell[idx]
        c_min = c.min(axis=0)
        c -= c_min
        ny = int(c[:, 1].max()) + 1
        key = c[:, 0] * ny + c[:, 1]
        n_keys = int(key.max()) + 1
        if n_keys <= 8 * len(key) + 65536:
            occupied = np.flatnonzero(np.bincount(key, minlength=n_keys))
            rank = np.zeros(n_keys, np.int64)
            rank[occupied] = np.arange(len(occupied))
            local = rank[key]
        else:
            occupied, local = np.unique(key, return_inverse=True)
        rows[idx] = n_rows + local.ravel()
        kx, ky = np.divmod(occupied, ny)
        tables.append(np.column_stack([np.full(len(occupied), float(sorted_anchor[lo])),
                                       (kx + c_min[0] + 0.5) * cell_m, (ky + c_min[1] + 0.5) * cell_m]))
        n_rows += len(occupied)
    return rows, np.concatenate(tables)


def blended_affine(table: np.ndarray, T: np.ndarray, index: SegmentIndex, k: int, d_min: float,
                   origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per (anchor, cell) row: (U,3,3) A and (U,3) b with Σ_j w_j (R_j p + t_j − origin) / Σ_j w_j = A p + b.

    Weights are those of the cell centre: the distances to the footprints (themselves thinned to
    1 m cells) are evaluated once per cell instead of once per point.
    """
    U = len(table)
    A = np.empty((U, 3, 3))
    b = np.empty((U, 3))
    anchor = table[:, 0].astype(np.int64)
    bounds = np.flatnonzero(np.diff(anchor)) + 1
    for lo, hi in zip(np.concatenate([[0], bounds]), np.concatenate([bounds, [U]])):
        cand = index.candidates(int(anchor[lo]), k)
        if len(cand) == 1:
            A[lo:hi], b[lo:hi] = T[cand[0], :3, :3], T[cand[0], :3, 3] - origin
            continue
        w = inverse_log_weights(index.distances(cand, table[lo:hi, 1:]), d_min)
        w /= w.sum(axis=1, keepdims=True)
        A[lo:hi] = np.einsum("uk,kab->uab", w, T[cand, :3, :3])
        b[lo:hi] = w @ (T[cand, :3, 3] - origin)
    return A, b


def blend_points(points: np.ndarray, xy: np.ndarray, anchors: np.ndarray, T: np.ndarray, index: SegmentIndex,
                 k: int, d_min: float, cell_m: float = 0.5, chunk: int = 1_000_000) -> np.ndarray:
    """Σ_j w_j T_j(p) / Σ_j w_j over each point's anchor and its k neighbours (k = 0: no blending).

    The weights of a point are those of the centre of its ``cell_m`` cell (per anchor), so the
    blend is one affine map per cell, applied to the points in chunks (bounded memory).
    """
    out = np.empty((len(points), 3), dtype=np.float64)
    if len(points) == 0:
        return out
    origin = T[index.valid, :3, 3].mean(axis=0)
    if k == 0:                       # no blending: every point takes its anchor's transform
        rows, A, b = np.asarray(anchors, np.int64), T[:, :3, :3], T[:, :3, 3] - origin
    else:
        rows, table = cell_keys(xy, np.asarray(anchors, np.int64), cell_m)
        A, b = blended_affine(table, T, index, k, d_min, origin)
    for s in range(0, len(points), chunk):
        r = rows[s:s + chunk]
        p = np.asarray(points[s:s + chunk], np.float64)
        out[s:s + chunk] = np.einsum("nab,nb->na", A[r], p) + b[r] + origin
    return out


def blend_rigid(points: np.ndarray, xy: np.ndarray, anchors: np.ndarray, T: np.ndarray, index: SegmentIndex,
                k: int, d_min: float) -> tuple[np.ndarray, np.ndarray]:
    """Blended rigid transform at a few points (cameras): (M,3) new positions, (M,3,3) rotations."""
    M = len(points)
    K = k + 1
    cand = np.zeros((M, K), np.int64)
    w = np.zeros((M, K))
    anchors = np.asarray(anchors, np.int64)
    order = np.argsort(anchors, kind="stable")
    for grp in np.split(order, np.flatnonzero(np.diff(anchors[order])) + 1):
        if len(grp) == 0:
            continue
        c = index.candidates(int(anchors[grp[0]]), k)
        cand[grp, :len(c)] = c
        cand[grp, len(c):] = c[0]
        w[grp, :len(c)] = inverse_log_weights(index.distances(c, xy[grp]), d_min) if len(c) > 1 else 1.0
    w /= w.sum(axis=1, keepdims=True)
    origin = T[index.valid, :3, 3].mean(axis=0)
    moved = np.einsum("mkab,mb->mka", T[cand, :3, :3], points) + (T[cand, :3, 3] - origin)
    pos = np.einsum("mk,mka->ma", w, moved) + origin
    return pos, average_rotations(T[cand, :3, :3], w)
