"""Per-segment street points for the refine stages: façade and ground points in the levelled frame.

Points are grouped once (one argsort per grouping), so taking a segment's points is a slice.
Façade points are those labelled with the segment; ground points are ground points (label -1)
whose carrier is the segment. The footprint used for 2D registration is the façade points
projected to z = 0 and thinned to one point per ``cell_m`` cell (an even density, so long, densely
scanned walls do not outweigh the rest).
"""

from __future__ import annotations

import numpy as np

from toolkit.capture import StreetCapture
from toolkit.errors import StageError
from toolkit.refine.columns import minus_row
from toolkit.types import StreetSegments


class SegmentPoints:
    def __init__(self, street: StreetSegments, capture: StreetCapture) -> None:
        pts = capture.points
        labels = np.asarray(street.point_labels)
        if len(labels) != len(pts):
            raise StageError(f"street segments label {len(labels)} points but {capture.cloud_path} "
                             f"holds {len(pts)}")
        # levelled lazily, per segment: only the façade and ground points are ever used
        self._points, self._normals = pts, street.normals
        self._rotation_t = np.ascontiguousarray(street.up_rotation.T)
        carrier = np.asarray(street.carrier)
        # one stable sort for both groupings: façade points by label (groups 0..S-1), ground points
        # by carrier (groups S..2S-1); each group lists its points in input order, as two sorts would
        S = len(street)
        ground_key = np.where((labels == -1) & (carrier >= 0), carrier + S, -1)
        groups = _groups(np.where((labels >= 0) & (labels < S), labels, ground_key), 2 * S)
        self._facade, self._ground = groups[:S], groups[S:]
        self.street = street
        self._ground_cache: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}
        self._facade_cache: dict[int, np.ndarray] = {}
        self._footprint_cache: dict[tuple[int, float, int], np.ndarray] = {}
        self.scale, self.pivots = np.ones(S), np.zeros((S, 3))

    def set_scales(self, scale: np.ndarray, pivots: np.ndarray) -> None:
        """From now on segment i's points are scaled by scale[i] about pivots[i] (levelled frame)."""
        self.scale, self.pivots = np.asarray(scale, np.float64), np.asarray(pivots, np.float64)
        self._ground_cache.clear()
        self._facade_cache.clear()
        self._footprint_cache.clear()

    def _scaled(self, i: int, lev: np.ndarray) -> np.ndarray:
        s = self.scale[i]
        return lev if s == 1.0 else self.pivots[i] + s * (lev - self.pivots[i])

    def facade_counts(self) -> np.ndarray:
        """(S,) number of façade points per segment."""
        return np.array([len(g) for g in self._facade], np.int64)

    def facade(self, i: int) -> np.ndarray:
        """(F,3) levelled façade points of segment i (cached: do not modify)."""
        if i not in self._facade_cache:
            self._facade_cache[i] = self._scaled(i, self.street.level(self._points[self._facade[i]]))
        return self._facade_cache[i]

    def ground(self, i: int) -> tuple[np.ndarray, np.ndarray | None]:
        """(G,3) levelled ground points of segment i and their normals (cached: do not modify)."""
        if i not in self._ground_cache:
            idx = self._ground[i]
            normals = None
            if self._normals is not None:
                normals = np.asarray(self._normals[idx], np.float64) @ self._rotation_t
            self._ground_cache[i] = (self._scaled(i, self.street.level(self._points[idx])), normals)
        return self._ground_cache[i]

    def footprint(self, i: int, cell_m: float, max_points: int, R_z: np.ndarray | None = None,
                  centre: np.ndarray | None = None) -> np.ndarray:
        """(B,2) thinned footprint of segment i, after an optional tilt R_z about ``centre`` (the
        untilted one is cached: do not modify it)."""
        key = (i, cell_m, max_points)
        if R_z is None and key in self._footprint_cache:
            return self._footprint_cache[key]
        f = self.facade(i)
        if len(f) == 0:
            return np.asarray(self.street.boundary_xy[i], np.float64).reshape(-1, 2)
        if R_z is not None:
            # (f - centre) @ R_z.T + centre, its x and y only (the same values)
            turned = minus_row(f, centre) @ R_z.T
            return thin_columns(turned[:, 0] + centre[0], turned[:, 1] + centre[1], cell_m, max_points)
        self._footprint_cache[key] = thin_xy(f[:, :2], cell_m, max_points)
        return self._footprint_cache[key]


def thin_xy(xy: np.ndarray, cell_m: float, max_points: int) -> np.ndarray:
    """One point (the cell mean) per occupied cell; deterministic stride when still too many."""
    if len(xy) == 0:
        return np.zeros((0, 2))
    return thin_columns(xy[:, 0], xy[:, 1], cell_m, max_points)


def thin_columns(x: np.ndarray, y: np.ndarray, cell_m: float, max_points: int) -> np.ndarray:
    """``thin_xy`` of the points (x, y) given as two columns (column-wise: min and division per
    column, ~3× faster than over rows of two)."""
    if len(x) == 0:
        return np.zeros((0, 2))
    cx = np.floor(x / cell_m).astype(np.int64)
    cx -= cx.min()
    cy = np.floor(y / cell_m).astype(np.int64)
    cy -= cy.min()
    # one int64 key per cell, x-major: the same cell order as a row-wise unique, ~10× faster
    key = cx * (int(cy.max()) + 1) + cy
    n_keys = int(key.max()) + 1
    if n_keys <= 8 * len(key) + 65536:      # dense key range: counting instead of sorting, same result
        counts = np.bincount(key, minlength=n_keys)
        occupied = np.flatnonzero(counts)
        rank = np.zeros(n_keys, np.int64)
        rank[occupied] = np.arange(len(occupied))
        inv, counts = rank[key], counts[occupied]
    else:
        _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    out = np.empty((len(counts), 2))
    for j, column in enumerate((x, y)):
        np.divide(np.bincount(inv, weights=column, minlength=len(counts)), counts, out=out[:, j])
    if len(out) > max_points:
        out = out[np.linspace(0, len(out) - 1, max_points).astype(np.int64)]
    return out


def _groups(keys: np.ndarray, n_groups: int) -> list[np.ndarray]:
    if n_groups < np.iinfo(np.int16).max:
        keys = keys.astype(np.int16)        # numpy's stable sort of 16-bit keys is a radix sort (~5× faster)
    order = np.argsort(keys, kind="stable")
    bounds = np.searchsorted(keys[order], np.arange(n_groups + 1))
    return [order[bounds[g]:bounds[g + 1]] for g in range(n_groups)]


def input_anchors(street: StreetSegments) -> np.ndarray:
    """(S,3) segment centres in the INPUT street frame (levelled centroid at its ground height)."""
    c = np.asarray(street.centroids, np.float64).reshape(-1, 2)
    z = np.nan_to_num(np.asarray(street.ground_z, np.float64), nan=0.0)
    lev = np.column_stack([c, z])
    return lev @ street.up_rotation + street.origin
