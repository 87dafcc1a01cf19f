"""Segment rotations smoothed along the route.

A segment's 2D rotation is fixed by its own façade against its own over-view outline. A short or
compact façade, or an outline with its own error (a label-map edge eroded on one side, an OSM
outline digitised askew), leaves it a degree or more off, and the ground the segment carries, tens
of metres from the façade, moves by that angle times the lever (campus seed 3, label map: a façade
within 0.25 m but turned 2.5°, its ground 2 m off). The street frame's heading drifts slowly (a
random walk), so the segments captured close together along the route share nearly the same
rotation: each segment's rotation is replaced by a weighted mean of the rotations of the segments
within ``window_m`` along the route (tricube on route distance, weight also growing with the
footprint's size), turned about the segment's own footprint centre so that its façade stays where
the search put it.
"""

from __future__ import annotations

import numpy as np

from toolkit.refine.route import route_neighbours, tricube


def rotation_deg(T2d: np.ndarray) -> np.ndarray:
    """(S,) rotation angles of (S,3,3) 2D rigid transforms (degrees)."""
    return np.degrees(np.arctan2(T2d[:, 1, 0], T2d[:, 0, 0]))


def smoothed_rotations(T2d: np.ndarray, idx: np.ndarray, route_s: np.ndarray, anchors_xy: np.ndarray,
                       centres_xy: np.ndarray, weights: np.ndarray, window_m: float) -> np.ndarray:
    """(S,3,3) copy of ``T2d`` (levelled → scene) where each segment of ``idx`` is turned about its
    footprint centre ``centres_xy[i]`` (levelled frame) to the weighted mean rotation of the segments
    of ``idx`` within ``window_m`` along the route (``route_s``, metres) and ``2·window_m`` in space
    (``anchors_xy``, street frame: another pass of the route never joins). ``weights``: (S,) each
    segment's say in its neighbours' rotations."""
    out = np.array(T2d, np.float64, copy=True)
    if window_m <= 0 or len(idx) < 2:
        return out
    angle = rotation_deg(T2d[idx])
    ds, near = route_neighbours(route_s[idx], anchors_xy[idx], window_m)
    w = tricube(ds / window_m) * near * weights[idx][None]
    # differences wrapped to (−180, 180], so that angles either side of ±180° average correctly
    diff = (angle[None] - angle[:, None] + 180.0) % 360.0 - 180.0
    turn = np.radians((w * diff).sum(1) / np.maximum(w.sum(1), 1e-12))
    c, s = np.cos(turn), np.sin(turn)
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)      # (n,2,2)
    T = T2d[idx]
    pivot = np.einsum("nij,nj->ni", T[:, :2, :2], centres_xy[idx]) + T[:, :2, 2]
    out[idx, :2, :2] = R @ T[:, :2, :2]
    out[idx, :2, 2] = pivot - np.einsum("nij,nj->ni", R, pivot) + np.einsum("nij,nj->ni", R, T[:, :2, 2])
    return out
