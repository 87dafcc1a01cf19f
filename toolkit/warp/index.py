"""Footprints of the valid segments and each one's blending neighbours (``toolkit.warp.blend``).

Speed: the neighbour search is batched: one centre query for all segments, one transform-agreement
check for all pairs, and one footprint query per neighbour segment for all the segments that list it
(instead of one KD-tree query per (segment, neighbour) pair: ~3,000 calls on campus). The nearest
segment of many points is settled per cell where the cell allows a single answer (``nearest``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from toolkit.arrays import dense_rank
from toolkit.errors import StageError
from toolkit.refine.consistency import gap_matrix
from toolkit.refine.segments import input_anchors, thin_xy
from toolkit.threads import query_workers
from toolkit.types import SegmentTransforms, StreetSegments
from toolkit.warp.cells import cell_grid_keys


def footprint_gaps(owner: np.ndarray, other: np.ndarray, fp_xy: np.ndarray, fp_start: np.ndarray,
                   trees: dict[int, cKDTree]) -> np.ndarray:
    """(P,) least distance from footprint ``owner[p]`` to footprint ``other[p]``.

    ``fp_xy``: the footprints of all segments concatenated, segment s at rows
    ``fp_start[s]:fp_start[s + 1]``; ``trees``: a KD-tree over each footprint.
    """
    gap = np.empty(len(owner))
    by_other = np.argsort(other, kind="stable")
    bounds = np.flatnonzero(np.diff(other[by_other])) + 1
    for pairs in np.split(by_other, bounds) if len(owner) else []:
        size = fp_start[owner[pairs] + 1] - fp_start[owner[pairs]]
        first = np.cumsum(size) - size
        rows = np.repeat(fp_start[owner[pairs]] - first, size) + np.arange(int(size.sum()))
        d = trees[int(other[pairs[0]])].query(fp_xy[rows], workers=query_workers(len(rows)))[0]
        gap[pairs] = np.minimum.reduceat(d, first)
    return gap


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
              agree_tol_m: float = np.inf, agree_ratio: float = 0.0, max_gap_m: float = np.inf,
              route_s: np.ndarray | None = None, route_gap_m: float = np.inf) -> SegmentIndex:
        """Neighbours: the k valid segments nearest (footprint to footprint, at most ``max_gap_m``
        apart) among the 3k nearest by centre whose transform agrees with the segment's own (gap at
        both centres ≤ agree_tol_m + agree_ratio·d) and, given ``route_s`` ((S,) route position per
        segment, NaN: unknown, never excluded), that were captured within ``route_gap_m`` of it along
        the route: after a loop the street frame puts segments of another pass next to it, drifted
        away (a few metres: the transform check alone lets those within its tolerance through)."""
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
        fp_size = np.zeros(len(street) + 1, np.int64)
        fp_size[valid + 1] = [len(fps[int(i)]) for i in valid]
        fp_start = np.cumsum(fp_size)          # all_xy rows of segment s: fp_start[s]:fp_start[s + 1]

        cent = np.asarray(street.centroids, np.float64).reshape(-1, 2)[valid]
        n_near = min(3 * k + 1, len(valid))
        near = valid[cKDTree(cent).query(cent, k=n_near)[1].reshape(len(valid), n_near)]
        not_self = near != valid[:, None]
        owner, other = np.repeat(valid, n_near)[not_self.ravel()], near[not_self]
        if route_s is not None and np.isfinite(route_gap_m) and len(owner):
            s = np.asarray(route_s, np.float64)
            with np.errstate(invalid="ignore"):
                same_pass = ~(np.abs(s[owner] - s[other]) > route_gap_m)       # NaN: unknown, kept
            owner, other = owner[same_pass], other[same_pass]
        if np.isfinite(agree_tol_m) and len(owner):
            anchors = input_anchors(street)
            disagree = gap_matrix(np.asarray(transforms.T, np.float64), anchors, np.column_stack([owner, other]))
            dist = np.linalg.norm(anchors[other] - anchors[owner], axis=1)
            agree = disagree <= agree_tol_m + agree_ratio * dist
            owner, other = owner[agree], other[agree]
        gap = footprint_gaps(owner, other, all_xy, fp_start, trees)
        start = np.searchsorted(owner, valid)
        end = np.searchsorted(owner, valid, side="right")
        neighbours = {}
        for i, lo, hi in zip(valid, start, end):
            order = np.argsort(gap[lo:hi], kind="stable")[:k]
            neighbours[int(i)] = other[lo:hi][order][gap[lo:hi][order] <= max_gap_m]
        return cls(valid, trees, cKDTree(all_xy), all_seg, neighbours)

    @classmethod
    def from_arrays(cls, valid: np.ndarray, footprint_xy: np.ndarray, footprint_segment: np.ndarray,
                    neighbours: np.ndarray) -> SegmentIndex:
        """The index stored by ``to_arrays`` (``toolkit.warp.store``), footprints and neighbours as built."""
        valid = np.asarray(valid, np.int64)
        footprint_segment = np.asarray(footprint_segment, np.int64)
        trees = {int(i): cKDTree(footprint_xy[footprint_segment == i]) for i in valid}
        listed = {int(i): row[row >= 0].astype(np.int64) for i, row in zip(valid, np.asarray(neighbours))}
        return cls(valid, trees, cKDTree(footprint_xy), footprint_segment, listed)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """valid (V,), footprint_xy (F,2) and footprint_segment (F,) in valid order, neighbours (V, K)
        −1 padded: all ``from_arrays`` needs."""
        width = max((len(n) for n in self.neighbours.values()), default=0)
        table = np.full((len(self.valid), width), -1, np.int64)
        for row, i in enumerate(self.valid):
            listed = self.neighbours[int(i)]
            table[row, :len(listed)] = listed
        return {"valid": np.asarray(self.valid, np.int64), "footprint_xy": np.asarray(self.all_tree.data),
                "footprint_segment": np.asarray(self.all_seg, np.int64), "neighbours": table}

    def nearest(self, xy: np.ndarray, cell_m: float = 1.0) -> np.ndarray:
        """(N,) segment of the footprint point nearest to each point: ``all_seg[all_tree.query(xy)[1]]``.

        Many points (e.g. 0.2–0.6 M without a valid carrier on campus) are first grouped into
        ``cell_m`` cells: the footprint point nearest to any point of a cell is within d₀ + the cell's
        diagonal of its centre (d₀: the centre's nearest distance), so when all the footprint points
        that near belong to one segment, it is every point's answer. Only the points of the other
        cells (20–25 % on campus) are queried one by one (0.11 → 0.05 s, 0.28 → 0.11 s CPU).
        """
        xy = np.asarray(xy, np.float64)
        if len(xy) < 10_000:
            return self.all_seg[self.all_tree.query(xy, workers=query_workers(len(xy)))[1]]
        key, lo, nx, ny = cell_grid_keys(xy, cell_m)
        occupied, cell = dense_rank(key, nx * ny)
        centres = (np.column_stack([occupied // ny + lo[0], occupied % ny + lo[1]]) + 0.5) * cell_m
        d0, nearest_to_centre = self.all_tree.query(centres, workers=query_workers(len(centres)))
        # slack for float rounding (distances, cell assignment): near-ties between segments stay unsure
        reach = (d0 + cell_m * np.sqrt(2.0)) * (1 + 1e-9) + 1e-9
        near = self.all_tree.query_ball_point(centres, reach, workers=query_workers(len(centres)))
        size = np.fromiter(map(len, near), np.int64, len(near))
        seg = self.all_seg[np.concatenate(near).astype(np.int64)]
        first = np.cumsum(size) - size
        sure = np.minimum.reduceat(seg, first) == np.maximum.reduceat(seg, first)
        out = self.all_seg[nearest_to_centre][cell]
        unsure = ~sure[cell]
        out[unsure] = self.all_seg[self.all_tree.query(xy[unsure], workers=query_workers(int(unsure.sum())))[1]]
        return out

    def anchors(self, xy: np.ndarray, carrier: np.ndarray, valid_mask: np.ndarray) -> np.ndarray:
        carrier = np.asarray(carrier, np.int64)
        valid_mask = np.asarray(valid_mask, bool)
        if len(carrier) and carrier.min() >= -1 and carrier.max() < len(valid_mask):
            orphan = ~np.append(valid_mask, False)[carrier]        # −1 (no carrier) reads the False
        else:
            ok = (carrier >= 0) & (carrier < len(valid_mask))
            ok[ok] = valid_mask[carrier[ok]]
            orphan = ~ok
        out = carrier.copy()
        if orphan.any():
            out[orphan] = self.nearest(xy[orphan])
        return out

    def candidates(self, anchor: int, k: int) -> np.ndarray:
        return np.concatenate([[anchor], self.neighbours[anchor][:k]]).astype(np.int64)

    def footprints(self, segments: np.ndarray) -> list[np.ndarray]:
        """The (thinned) footprint xy of each of the given valid segments."""
        return [self.trees[int(j)].data for j in segments]

    @functools.cached_property
    def _extents(self) -> dict[int, tuple[float, np.ndarray]]:
        return {j: (float(np.linalg.norm(t.data.max(axis=0) - t.data.min(axis=0))), t.data.mean(axis=0))
                for j, t in self.trees.items()}

    def extents(self, segments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(size (n,): bounding-box diagonal of each thinned footprint, m; centre (n,2): its mean xy)
        of the given valid segments, computed once per segment."""
        e = [self._extents[int(j)] for j in segments]
        return np.array([size for size, _ in e]), np.array([centre for _, centre in e]).reshape(-1, 2)

    def distances(self, cand: np.ndarray, xy: np.ndarray) -> np.ndarray:
        w = query_workers(len(xy))
        return np.column_stack([self.trees[int(j)].query(xy, workers=w)[0] for j in cand])
