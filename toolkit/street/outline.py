"""Per-segment 2D summaries of façade points in the levelled frame: order, size, boundary points."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from toolkit.street.params import StreetConfig

N_DIRECTIONS = 32  # diameter as the largest width over 32 directions: under 0.5 % short


class BoundaryConfig(StreetConfig):
    """Boundary points of each segment (keyword arguments of ``boundary_points``)."""

    cell_m: float = Field(0.25, gt=0, description="one mean point per cell of this size (m)")
    max_points: int = Field(2000, ge=10, description="boundary points kept per segment at most")


def relabel_by_size(labels: np.ndarray) -> np.ndarray:
    """Labels ≥ 0 renumbered 0..S-1 by decreasing size (ties: smaller old label first)."""
    ok = labels >= 0
    if not ok.any():
        return labels.copy()
    counts = np.bincount(labels[ok])
    present = np.flatnonzero(counts)
    order = present[np.lexsort((present, -counts[present]))]
    remap = np.full(len(counts), -1, dtype=np.int32)
    remap[order] = np.arange(len(order), dtype=np.int32)
    out = labels.copy()
    out[ok] = remap[labels[ok]]
    return out


def diameters(xy: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """(n,) horizontal diameter of each label's points (labels 0..n-1, every one present)."""
    if n == 0:
        return np.zeros(0)
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(n))
    x, y = xy[order, 0], xy[order, 1]
    width = np.zeros(n)
    for ang in np.linspace(0.0, np.pi, N_DIRECTIONS, endpoint=False):
        proj = x * np.cos(ang) + y * np.sin(ang)
        width = np.maximum(width, np.maximum.reduceat(proj, starts) - np.minimum.reduceat(proj, starts))
    return width


def boundary_points(xy: np.ndarray, labels: np.ndarray, n: int, cell_m: float,
                    max_points: int) -> tuple[np.ndarray, ...]:
    """Per label: façade xy thinned to one mean point per ``cell_m`` cell, then evenly strided
    down to at most ``max_points`` (deterministic: cells in sorted order)."""
    if n == 0:
        return ()
    cells = np.floor(xy / cell_m).astype(np.int64)
    cells -= cells.min(axis=0)
    span = int(cells.max()) + 1
    key = (labels.astype(np.int64) * span + cells[:, 0]) * span + cells[:, 1]
    uniq, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    mean = np.stack([np.bincount(inv, weights=xy[:, i]) / counts for i in range(2)], axis=1)
    cell_label = uniq // (span * span)
    bounds = np.searchsorted(cell_label, np.arange(n + 1))
    out = []
    for s in range(n):
        pts = mean[bounds[s]:bounds[s + 1]]
        if len(pts) > max_points:
            pts = pts[np.linspace(0, len(pts) - 1, max_points).round().astype(np.int64)]
        out.append(np.ascontiguousarray(pts))
    return tuple(out)
