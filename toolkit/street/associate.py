"""What every point moves with: the nearest façade segment within a horizontal radius (Ling & Qin 2022),
and the per-segment ground statistics later stages use (median height, median normal)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from toolkit.threads import thread_budget

if TYPE_CHECKING:
    from toolkit.street.segments import FacadeSegments

GROUND_STATS_POINTS = 500_000  # per-segment ground medians from at most about this many points


@dataclass(frozen=True)
class Association:
    """Per analysis point: labels (M,) int32 segment / -1 ground / -2 other, carrier (M,) int32 the
    segment it moves with (-1: none); per segment: ground_z (S,) and ground_normal (S,3), levelled."""

    labels: np.ndarray
    carrier: np.ndarray
    ground_z: np.ndarray
    ground_normal: np.ndarray


def decimate_xy(xy: np.ndarray, labels: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """One representative (the first, in input order) per (label, 2D cell): keeps KD-trees small."""
    cells = np.floor(xy / cell_m).astype(np.int64)
    cells -= cells.min(axis=0) if len(cells) else 0
    width = int(cells[:, 1].max()) + 1 if len(cells) else 1
    key = (labels.astype(np.int64) * (int(cells[:, 0].max()) + 1 if len(cells) else 1) + cells[:, 0]) * width + cells[:, 1]
    _, first = np.unique(key, return_index=True)
    return xy[first], labels[first]


def nearest_segment(points: np.ndarray, to_xy: np.ndarray, seg_xy: np.ndarray, seg_labels: np.ndarray,
                    radius_m: float, cell_m: float = 0.5, chunk: int = 1 << 20,
                    skip: np.ndarray | None = None) -> np.ndarray:
    """(M,) int32 label of the nearest segment point within ``radius_m`` in 2D, -1 when none.

    points: (M,3); to_xy: (2,3) rows of the levelling rotation giving horizontal coordinates;
    seg_xy, seg_labels: the segments' points, decimated to one per (label, ``cell_m`` cell);
    skip: optional (M,) bool, rows whose answer the caller does not need (not searched, left -1).
    """
    out = np.full(len(points), -1, dtype=np.int32)
    if len(seg_xy) == 0 or len(points) == 0:
        return out
    rep_xy, rep_lab = decimate_xy(seg_xy, seg_labels, cell_m)
    tree = cKDTree(rep_xy)
    for s in range(0, len(points), chunk):
        xy = points[s:s + chunk] @ to_xy.T  # whole chunks: the same products as without ``skip``
        rows = np.arange(len(xy)) if skip is None else np.flatnonzero(~skip[s:s + chunk])
        dist, idx = tree.query(xy[rows], k=1, distance_upper_bound=radius_m, workers=thread_budget())
        hit = np.isfinite(dist)
        out[s + rows[hit]] = rep_lab[idx[hit]]
    return out


def sort_within_groups(values: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """``values`` ordered by (group, value), as ``values[np.lexsort((values, groups))]``.

    Without zeros and NaNs, values that compare equal have equal bits, so an unstable sort by value
    followed by a stable sort by group gives the same array; two quick sorts replace the merge
    sorts of lexsort (~4x faster). Small group numbers are sorted as int16 (radix sort).
    """
    floating = np.issubdtype(values.dtype, np.floating)
    if floating and ((values == 0).any() or np.isnan(values).any()):  # ±0 and NaNs: keep lexsort's order
        return values[np.lexsort((values, groups))]
    by_value = np.argsort(values)
    key = groups[by_value]
    if len(key) and key.min() >= 0 and key.max() <= np.iinfo(np.int16).max:
        key = key.astype(np.int16)
    return values[by_value[np.argsort(key, kind="stable")]]


def group_quantile(values: np.ndarray, groups: np.ndarray, n: int, q: float) -> np.ndarray:
    """(n,) ``q`` quantile (linear between order statistics) of ``values`` per group 0..n-1
    (groups < 0 ignored); NaN for empty groups."""
    keep = groups >= 0
    v, g = values[keep], groups[keep]
    v = sort_within_groups(v, g)
    counts = np.bincount(g, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    out = np.full(n, np.nan)
    has = counts > 0
    pos = q * (counts[has] - 1)
    lo = np.floor(pos).astype(np.int64)
    frac = pos - lo
    hi = np.minimum(lo + 1, counts[has] - 1)
    out[has] = (1 - frac) * v[starts[has] + lo] + frac * v[starts[has] + hi]
    return out


def group_median(values: np.ndarray, groups: np.ndarray, n: int) -> np.ndarray:
    """(n,) median of ``values`` per group 0..n-1 (groups < 0 ignored); NaN for empty groups."""
    return group_quantile(values, groups, n, 0.5)


def ground_statistics(z: np.ndarray, normals_up: np.ndarray, carrier: np.ndarray,
                      n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per segment: median height (n,) and unit median normal (n,3) of its ground points.

    z: (G,) levelled heights; normals_up: (G,3) levelled normals oriented upwards; carrier: (G,).
    Segments without ground points get NaN and (0, 0, 1).
    """
    ground_z = group_median(z, carrier, n)
    normal = np.stack([group_median(normals_up[:, i], carrier, n) for i in range(3)], axis=1)
    norm = np.linalg.norm(normal, axis=1)
    bad = ~np.isfinite(norm) | (norm < 1e-6)
    normal[bad] = (0.0, 0.0, 1.0)
    normal[~bad] /= norm[~bad, None]
    return ground_z, normal


def associate(points: np.ndarray, normals_up: np.ndarray, rotation: np.ndarray, segments: FacadeSegments,
              ground_angle_deg: float, radius_m: float) -> Association:
    """Labels, carriers and ground statistics of the analysis cloud ``points`` (M,3) with upward
    ``normals_up`` (M,3) float32: ground within ``ground_angle_deg`` of vertical, every point carried
    by the nearest segment within ``radius_m`` (2D); ``rotation`` levels the analysis frame."""
    seg_idx, seg_lab = segments.index, segments.labels
    ground = normals_up @ rotation[2].astype(np.float32) > np.cos(np.radians(ground_angle_deg))
    labels = np.full(len(points), -2, dtype=np.int32)
    labels[ground] = -1
    labels[seg_idx] = seg_lab
    is_seg_point = np.zeros(len(points), dtype=bool)
    is_seg_point[seg_idx] = True  # they carry themselves: no search
    carrier = nearest_segment(points, rotation[:2], segments.xy, seg_lab, radius_m, skip=is_seg_point)
    carrier[seg_idx] = seg_lab
    del is_seg_point
    g_idx = np.flatnonzero(ground)[::max(1, int(ground.sum()) // GROUND_STATS_POINTS)]
    ground_z, ground_normal = ground_statistics(points[g_idx] @ rotation[2],
                                                normals_up[g_idx] @ rotation.T.astype(np.float32),
                                                carrier[g_idx], segments.count)
    return Association(labels, carrier, ground_z, ground_normal)
