"""Region growing of façade points as connected components of a kNN graph (Rabbani et al. 2006).

Rabbani et al. (2006) grow regions from the lowest-curvature seeds: a neighbour joins when its
normal is within ``smooth_angle_deg`` of the current point's, and continues the growth only if its
curvature is below the seed threshold. The regions this produces over the low-curvature points
do not depend on the seed order: they are the connected components of the graph whose edges
join low-curvature kNN neighbours with agreeing normals, which scipy.sparse.csgraph finds in one
call. High-curvature points (edges, corners, noise) then join the region of their nearest
agreeing low-curvature neighbour, which is where the seeded growth would have stopped with them.

Segments that bend (smoothly curved façades, rounded corners) are cut into pieces whose
horizontal normal azimuths stay within ``bend_split_angle_deg`` of the segment's mean.
The graph is built in row chunks as int32 CSR arrays.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from toolkit.arrays import sorted_unique
from toolkit.street.params import StreetConfig

CHUNK = 1 << 16


class GrowingConfig(StreetConfig):
    """Region growing over the façade kNN graph (see ``grow_regions``); its keys were flat unprefixed."""

    flat_prefix = ""
    graph_knn: int = Field(10, ge=1, description="links each façade point to at most its nearest graph_knn (≤ knn)")
    smooth_angle_deg: float = Field(10.0, gt=0, lt=90, description="max angle between neighbour normals (degrees)")
    seed_curvature_max: float = Field(
        0.1, gt=0, le=1 / 3, description="points with surface variation above this do not propagate")
    bend_split_angle_deg: float = Field(30.0, gt=0, le=180, description="split segments whose horizontal normals "
                                                                        "spread more than this (degrees; 180 = off)")


def _edge_chunks(indptr: np.ndarray, indices: np.ndarray):
    """(src, dst) int32 pairs of a CSR graph, a block of rows at a time."""
    n = len(indptr) - 1
    for s in range(0, n, CHUNK):
        e = min(n, s + CHUNK)
        src = np.repeat(np.arange(s, e, dtype=np.int32), np.diff(indptr[s:e + 1]))
        yield src, indices[indptr[s]:indptr[e]]


def _differing(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs (a[i], b[i]) with a[i] != b[i]."""
    differ = np.flatnonzero(a != b)
    return a[differ], b[differ]


def _compress(parent: np.ndarray) -> np.ndarray:
    while True:
        grand = parent[parent]
        if np.array_equal(grand, parent):
            return parent
        parent = grand


def components(n: int, indptr: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(n,) int32 component of each node of the graph given as CSR rows (edges either way).

    One union-find hooking pass over the edges (in row blocks) contracts the kNN graph, whose
    edges mostly join points already in one tree; scipy.sparse.csgraph then solves the small
    graph of the remaining roots. This keeps memory near the edge list itself, where
    connected_components on the full graph needs ~6x it (float64 data, transposes).
    Components are numbered in the order of their smallest node, as csgraph numbers them.
    """
    parent = np.arange(n, dtype=np.int32)
    for src, dst in _edge_chunks(indptr, indices):
        ps, pd = _differing(parent[src], parent[dst])
        np.minimum.at(parent, np.maximum(ps, pd), np.minimum(ps, pd))
    parent = _compress(parent)  # parent[i] <= i: each tree's root is its smallest node
    keys = []
    for src, dst in _edge_chunks(indptr, indices):
        ps, pd = _differing(parent[src], parent[dst])
        keys.append(sorted_unique(np.minimum(ps, pd).astype(np.int64) * n + np.maximum(ps, pd)))
    pairs = sorted_unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)
    is_root = parent == np.arange(n, dtype=np.int32)
    roots = np.flatnonzero(is_root)
    parent = (np.cumsum(is_root, dtype=np.int32) - 1)[parent]  # rank of each root among the roots
    if len(pairs):
        a = np.searchsorted(roots, pairs // n)
        b = np.searchsorted(roots, pairs % n)
        m = len(roots)
        graph = csr_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(m, m))
        root_label = connected_components(graph, directed=False)[1]
        parent = root_label[parent]
    return parent.astype(np.int32)


def group_min_max(values: np.ndarray, labels: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per label 0..n-1: min and max of ``values`` (NaN for labels without values)."""
    order = np.argsort(labels, kind="stable")
    lab = labels[order]
    starts = np.searchsorted(lab, np.arange(n))
    present = np.bincount(labels, minlength=n) > 0
    lo, hi = np.full(n, np.nan), np.full(n, np.nan)
    if len(lab):
        s = np.minimum(starts, len(lab) - 1)
        lo[present] = np.minimum.reduceat(values[order], s)[present]
        hi[present] = np.maximum.reduceat(values[order], s)[present]
    return lo, hi


def _indptr(degree: np.ndarray) -> np.ndarray:
    out = np.zeros(len(degree) + 1, dtype=np.int64)
    np.cumsum(degree, out=out[1:])
    return out


def grow_regions(normals: np.ndarray, graph: np.ndarray, index: np.ndarray, n_points: int,
                 curvature: np.ndarray, smooth_angle_deg: float, seed_curvature_max: float,
                 azimuth: np.ndarray, bend_split_angle_deg: float) -> np.ndarray:
    """(F,) int32 region of each façade point (-1: none).

    normals: (F,3) of the façade points; graph: (F,g) analysis indices of their nearest neighbours
    (itself excluded); index: (F,) analysis index of each façade point; curvature: (F,);
    azimuth: (F,) horizontal normal direction, radians (only its orientation mod π matters).
    """
    f = len(index)
    if f == 0:
        return np.zeros(0, dtype=np.int32)
    pos = np.full(n_points, -1, dtype=np.int32)
    pos[index] = np.arange(f, dtype=np.int32)
    cols = [np.ascontiguousarray(normals[:, a], dtype=np.float32) for a in range(3)]
    cos_smooth = np.float32(np.cos(np.radians(smooth_angle_deg)))
    smooth = curvature <= seed_curvature_max
    indices = np.empty(graph.size, dtype=np.int32)  # upper bound, filled front to back
    filled, degree = 0, np.zeros(f, dtype=np.int32)
    anchor = np.full(f, -1, dtype=np.int32)  # rough points: nearest agreeing smooth neighbour
    for s in range(0, f, CHUNK):
        nb = pos[graph[s:s + CHUNK]]
        valid = nb >= 0
        nb[~valid] = 0
        dot = cols[0][nb] * cols[0][s:s + CHUNK, None]
        dot += cols[1][nb] * cols[1][s:s + CHUNK, None]
        dot += cols[2][nb] * cols[2][s:s + CHUNK, None]
        ok = valid & (np.abs(dot) > cos_smooth) & smooth[nb]
        del dot, valid
        link = ok & smooth[s:s + CHUNK, None]
        degree[s:s + CHUNK] = link.sum(axis=1)
        kept = nb[link]
        indices[filled:filled + len(kept)] = kept
        filled += len(kept)
        rough = ~smooth[s:s + CHUNK] & ok.any(axis=1)
        first = np.argmax(ok[rough], axis=1)
        anchor[s:s + CHUNK][rough] = nb[rough][np.arange(int(rough.sum())), first]
    indices = indices[:filled]
    labels = components(f, _indptr(degree), indices)
    labels[~smooth] = -1
    labels = _split_bends(labels, azimuth, indices, degree, bend_split_angle_deg)
    has = anchor >= 0
    labels[has] = labels[anchor[has]]
    return labels


def _split_bends(labels: np.ndarray, azimuth: np.ndarray, indices: np.ndarray, degree: np.ndarray,
                 bend_deg: float) -> np.ndarray:
    """Bent segments cut by azimuth; ``indices`` (the CSR edges) is overwritten."""
    ok = labels >= 0
    if not ok.any() or bend_deg >= 180:
        return labels
    n = int(labels.max()) + 1
    lab = labels[ok]
    doubled = 2.0 * azimuth[ok].astype(np.float64)
    mean = np.arctan2(np.bincount(lab, weights=np.sin(doubled), minlength=n),
                      np.bincount(lab, weights=np.cos(doubled), minlength=n))
    doubled -= mean[lab]
    dev = ((np.mod(doubled + np.pi, 2 * np.pi) - np.pi) / 2.0).astype(np.float32)  # [-π/2, π/2)
    del doubled
    lo, hi = group_min_max(dev, lab, n)
    bends = np.nan_to_num(hi - lo) > np.radians(bend_deg)
    if not bends.any():
        return labels
    # key: one value per (segment, azimuth piece); only bent segments get several pieces
    piece = np.where(bends[lab], np.round(dev / np.float32(np.radians(bend_deg))), 0).astype(np.int64)
    del dev
    key = np.full(len(labels), -1, dtype=np.int64)
    key[ok] = lab.astype(np.int64) * 64 + piece + 16
    del piece, lab
    indptr = _indptr(degree)
    kept_degree = np.zeros(len(labels), dtype=np.int32)
    filled = 0
    for s in range(0, len(labels), CHUNK):  # compacts the kept edges in place, front to back
        e = min(s + CHUNK, len(labels))
        rows = np.repeat(np.arange(s, e, dtype=np.int32), degree[s:e])
        nbr = indices[indptr[s]:indptr[e]]
        same = key[rows] == key[nbr]
        kept = nbr[same]
        indices[filled:filled + len(kept)] = kept
        filled += len(kept)
        kept_degree[s:e] = np.bincount(rows[same] - s, minlength=e - s)
    new = components(len(labels), _indptr(kept_degree), indices[:filled])
    new[~ok] = -1
    return new
