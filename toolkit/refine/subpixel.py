"""Sub-pixel refinement of 2D registrations: Gauss-Newton on the signed outline distance.

Point-to-outline least squares: the footprint points within ``inlier_m`` of the outline pull the
transform along the distance gradient, up to ten steps (``toolkit.refine.search2d`` runs it from
the grid optimum). Many independent problems (every segment of a refine pass) step together: the
per-point work (transform, raster lookup, bilinear samples, Jacobian rows) runs once over all the
problems' points, and only the small per-problem algebra (centroid, 3×3 normal equations, the
update) stays a loop. Each problem sees exactly the operations, in the same order, that it would
on its own (the per-problem sums and products are the same numpy calls on the same arrays), so
results are bit-identical to stepping them one at a time; ~100 numpy calls per problem and step
become ~25.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from toolkit.refine.bilinear import interpolate_planes, rows_cols
from toolkit.refine.columns import column_means

if TYPE_CHECKING:
    from toolkit.refine.search2d import OutlineField, SearchParams

POOLED_MAX_PX = 65536        # fields of their own up to this many pixels are pooled for sampling


def rotation_about(theta: float, centre: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """(3,3) rotation by theta about ``centre`` followed by ``shift`` (world frame)."""
    c, s = np.cos(theta), np.sin(theta)            # rigid2d(theta, 0), without its temporaries
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R[:2, 2] = centre - R[:2, :2] @ centre + shift
    return R


def gauss_newton_many(problems: list[tuple[np.ndarray, np.ndarray, OutlineField, SearchParams]],
                      iterations: int = 10) -> list[np.ndarray | None]:
    """Refined transforms of independent problems (street_xy, T0, field, params), fields on one grid,
    stepped together; None for a problem left with fewer than six inliers, a non-finite step, or a
    result more than two pixels or two rotation steps from T0."""
    T: list[np.ndarray | None] = [np.array(T0, copy=True) for _, T0, _, _ in problems]
    buffers, sources = _sampling_buffers(problems)
    active = list(range(len(problems)))
    for _ in range(iterations):
        if not active:
            break
        active = _step(problems, buffers, sources, active, T)
    return [None if T[k] is None else _accept(problems[k], T[k]) for k in range(len(problems))]


def _sampling_buffers(problems) -> tuple[list[np.ndarray], list[tuple[int, int, int]]]:
    """Flat (3, n) buffers holding every problem's field, and per problem (buffer, flat index of
    its window's top-left pixel, row width). Fields cut from a shared raster sample it in place;
    fields computed on their own small window are copied into one pool, so that they too are
    sampled in one pass."""
    users: dict[int, int] = {}
    for _, _, field, _ in problems:
        users[id(field.raster)] = users.get(id(field.raster), 0) + 1
    buffers, index, pooled = [], {}, []
    for k, (_, _, field, _) in enumerate(problems):
        h, w = field.raster.shape[1:]
        if users[id(field.raster)] == 1 and h * w <= POOLED_MAX_PX:
            pooled.append(k)
        elif id(field.raster) not in index:
            index[id(field.raster)] = len(buffers)
            buffers.append(field.raster.reshape(3, -1))
    sources = [(0, 0, 0)] * len(problems)
    in_pool = set(pooled)
    for k, (_, _, field, _) in enumerate(problems):
        if k not in in_pool:
            sources[k] = (index[id(field.raster)], field.raster_origin, field.raster.shape[2])
    if pooled:
        flats = [problems[k][2].raster.reshape(3, -1) for k in pooled]
        bases = np.cumsum([0] + [f.shape[1] for f in flats[:-1]])
        for k, base in zip(pooled, bases):
            field = problems[k][2]
            sources[k] = (len(buffers), int(base) + field.raster_origin, field.raster.shape[2])
        buffers.append(np.concatenate(flats, axis=1))
    return buffers, sources


def _step(problems, buffers: list[np.ndarray], sources: list[tuple[int, int, int]], active: list[int],
          T: list) -> list[int]:
    """One Gauss-Newton step of the active problems; returns those still stepping (a problem left
    with fewer than six inliers or a non-finite step gets T = None)."""
    sizes = [len(problems[k][0]) for k in active]
    bounds = np.cumsum([0] + sizes)
    xy = np.empty((bounds[-1], 2))
    for k, a, b in zip(active, bounds[:-1], bounds[1:]):
        np.matmul(problems[k][0], np.ascontiguousarray(T[k][:2, :2].T), out=xy[a:b])
        xy[a:b] += T[k][:2, 2]
    inside, sg = _sample_fields(problems, buffers, sources, active, xy, sizes)
    ends = np.searchsorted(inside, bounds)               # each problem's share of the inside points
    inlier_m = np.repeat([problems[k][3].inlier_m for k in active], np.diff(ends))
    near = np.flatnonzero(np.abs(sg[:, 0]) < inlier_m)
    n_near = np.diff(np.searchsorted(near, ends))
    sg = sg.take(near, axis=0)
    xy = xy.take(inside[near], axis=0)
    starts = np.concatenate([[0], np.cumsum(n_near)])
    c = np.zeros((len(active), 2))
    for j in range(len(active)):
        if n_near[j] >= 6:
            c[j] = column_means(xy[starts[j]:starts[j + 1]])
    rx, ry = xy[:, 0] - np.repeat(c[:, 0], n_near), xy[:, 1] - np.repeat(c[:, 1], n_near)
    J = np.empty((len(sg), 3))
    J[:, 0] = sg[:, 1] * -ry + sg[:, 2] * rx
    J[:, 1:] = sg[:, 1:]
    stepping, H, g = [], [], []
    for j, k in enumerate(active):
        if n_near[j] < 6:
            T[k] = None
            continue
        # fresh arrays, as a single problem's: BLAS sees the same operands
        Jk, sk = J[starts[j]:starts[j + 1]].copy(), sg[starts[j]:starts[j + 1]].copy()
        Hk = Jk.T @ Jk
        Hk.flat[::4] += 1e-6
        stepping.append(j)
        H.append(Hk)
        g.append(Jk.T @ sk[:, 0])
    if not stepping:
        return []
    steps = -np.linalg.solve(np.array(H), np.array(g)[..., None])[..., 0]   # LAPACK gesv per problem
    still = []
    for j, step in zip(stepping, steps):
        k = active[j]
        if not all(math.isfinite(v) for v in step):
            T[k] = None
            continue
        T[k] = rotation_about(step[0], c[j], step[1:]) @ T[k]
        if not (abs(step[0]) < 1e-6 and np.hypot(*step[1:]) < 1e-4):
            still.append(k)
    return still


def _sample_fields(problems, buffers, sources, active, xy, sizes) -> tuple[np.ndarray, np.ndarray]:
    """(indices of the points inside their problem's window, (M,3) signed distance and gradient
    there), the points of the active problems laid end to end in ``xy``."""
    fields = [problems[k][2] for k in active]
    # per point: window origin (row0, col0) and size (h, w) of its problem's field
    win = np.repeat(np.array([(f.row0, f.col0, *f.sdf.shape) for f in fields], np.int64), sizes, axis=0)
    row, col = rows_cols(fields[0].grid.transform, xy[:, 0], xy[:, 1])
    row -= win[:, 0]
    col -= win[:, 1]
    r0, c0 = np.floor(row), np.floor(col)
    inside = np.flatnonzero((r0 >= 0) & (c0 >= 0) & (r0 < win[:, 2] - 1) & (c0 < win[:, 3] - 1))
    if len(inside) < len(row):
        row, col, r0, c0 = row[inside], col[inside], r0[inside], c0[inside]
    ends = np.searchsorted(inside, np.cumsum([0] + sizes))
    src = [sources[k] for k in active]
    sg = np.empty((len(inside), 3))
    j = 0
    while j < len(active):          # runs of consecutive problems sharing a buffer (usually one)
        run = j + 1
        while run < len(active) and src[run][0] == src[j][0]:
            run += 1
        a, b = ends[j], ends[run]
        per_point = np.repeat(np.array([s[1:] for s in src[j:run]], np.int64), np.diff(ends[j:run + 1]), axis=0)
        sg[a:b] = interpolate_planes(buffers[src[j][0]], per_point[:, 1], row[a:b], col[a:b], r0[a:b], c0[a:b],
                                     per_point[:, 0])
        j = run
    return inside, sg


def _accept(problem, T: np.ndarray) -> np.ndarray | None:
    """T, unless it moved the footprint centre more than two pixels or turned it more than two
    rotation steps from the start."""
    street_xy, T0, field, p = problem
    gsd = field.grid.gsd_m
    c0 = column_means(street_xy @ T0[:2, :2].T + T0[:2, 2])
    c1 = column_means(street_xy @ T[:2, :2].T + T[:2, 2])
    dtheta = np.arctan2(T[1, 0], T[0, 0]) - np.arctan2(T0[1, 0], T0[0, 0])
    if np.hypot(*(c1 - c0)) > 2 * gsd or abs(np.degrees(dtheta)) > 2 * p.rotation_step_deg:
        return None
    return T
