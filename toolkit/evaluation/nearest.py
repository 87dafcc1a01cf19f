"""Exact nearest-neighbour queries on a cKDTree that walk less of the tree.

A query keeps every subtree nearer than its ``distance_upper_bound`` on its search heap and scans the
leaves it pops, so a loose bound costs work on every query; a tight one prunes it. The bound never
changes an answer that lies within it, so the functions here return exactly what one plain query
returns, asking with tighter bounds first.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from toolkit.threads import thread_budget

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

# Relative and absolute slack on a bound that is itself a distance the tree returned: the tree keeps
# a point only when its squared distance is strictly below the squared bound.
_BOUND_SLACK = 1e-9
_BOUND_FLOOR_M = 1e-12
# Every PROBE_STEP-th point is asked first, to learn the typical nearest distance.
PROBE_STEP = 64


def nearest_up_to(tree: cKDTree, points: np.ndarray, cutoff_m: float,
                  workers: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``tree.query(points, k=1, distance_upper_bound=cutoff_m)``: (distances, indices), inf and
    ``tree.n`` where nothing lies within the cutoff.

    All points are first asked within twice the 75th percentile of a probe's nearest distances (on
    street clouds a tenth of the cutoff or less: ~15 % less time in 2D, ~7 % in 3D); the few left
    unanswered are asked again within the cutoff. Pass points in a spatially coherent order (e.g. a
    tree's leaf order): it keeps the probe representative and the walks cache-friendly.
    """
    points = np.asarray(points, np.float64)
    workers = thread_budget() if workers is None else workers
    probe = tree.query(points[::PROBE_STEP], k=1, distance_upper_bound=cutoff_m, workers=workers)[0]
    probe = probe[np.isfinite(probe)]
    first_m = 2.0 * float(np.percentile(probe, 75)) if len(probe) else cutoff_m
    if not first_m < cutoff_m:
        return tree.query(points, k=1, distance_upper_bound=cutoff_m, workers=workers)
    distances, nearest = tree.query(points, k=1, distance_upper_bound=first_m, workers=workers)
    rest = np.flatnonzero(~np.isfinite(distances))
    if len(rest):
        distances[rest], nearest[rest] = tree.query(points[rest], k=1, distance_upper_bound=cutoff_m,
                                                    workers=workers)
    return distances, nearest


def nearest_within(tree: cKDTree, points: np.ndarray, bound_m: np.ndarray,
                   split_percentile: float = 90.0, workers: int | None = None) -> np.ndarray:
    """Index (into ``tree.data``) of each point's nearest neighbour, when every point is known to
    have a neighbour within ``bound_m[k]`` metres (e.g. a distance the same tree already returned).

    The answer equals ``tree.query(points, k=1)[1]``. Points are queried in two groups, those whose
    bound is at most the ``split_percentile``-th percentile of the bounds and the rest, each with the
    group's largest bound as ``distance_upper_bound`` (cKDTree takes one bound per call): a third
    less time than unbounded queries for the back queries of the Chamfer metric.
    """
    points = np.asarray(points, np.float64)
    bound_m = np.asarray(bound_m, np.float64)
    workers = thread_budget() if workers is None else workers
    if len(points) != len(bound_m):
        raise ValueError(f"{len(points)} points but {len(bound_m)} bounds")
    if not np.isfinite(bound_m).all():
        raise ValueError("nearest_within needs finite bounds")
    nearest = np.empty(len(points), np.int64)
    if len(points) == 0:
        return nearest
    split = np.percentile(bound_m, split_percentile)
    typical = bound_m <= split
    for group in (np.flatnonzero(typical), np.flatnonzero(~typical)):
        if len(group) == 0:
            continue
        upper = float(bound_m[group].max()) * (1.0 + _BOUND_SLACK) + _BOUND_FLOOR_M
        nearest[group] = tree.query(points[group], k=1, distance_upper_bound=upper, workers=workers)[1]
    if (nearest == tree.n).any():
        raise ValueError("a bound was below the distance to the nearest neighbour")
    return nearest
