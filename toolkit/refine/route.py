"""Where along the route each street segment was captured, from the COLMAP model.

A route that loops brings the vehicle back past earlier places; the street frame has drifted in
between, so segments of the two passes sit next to each other in it while their transforms
rightly differ. Neighbour searches therefore use keys (x, y, z, s): the segment's centre plus its
position s along the route (metres travelled by the cameras that observe it), which keeps the two
passes apart. s is the median, over the segment's observations, of the observing camera's route
position; a sparse point belongs to the segment whose façade point is next to it (the façade is what
registers the segment), else, for a segment with no façade point near a sparse one, to the segment
carrying the dense point next to it. Carried ground points alone can mislead: where the route
loops back, the ground of the later pass is carried by the earlier pass's façades next to it (campus
seed 6: a façade seen at 0-100 m along the route had s = 1448 m from the ground it carries).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from toolkit.threads import query_workers
from toolkit.types import SparseModel, StreetSegments

MAX_TREE_POINTS = 1_000_000


def camera_route_positions(model: SparseModel) -> np.ndarray:
    """(C,) metres travelled along the camera path up to each camera (in model order)."""
    steps = np.linalg.norm(np.diff(model.centres, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def tricube(d: np.ndarray) -> np.ndarray:
    """(1 − |d|³)³ for |d| < 1, else 0: the weight of a segment ``d`` windows away along the route."""
    return np.clip(1.0 - np.abs(d) ** 3, 0.0, None) ** 3


def route_neighbours(route_s: np.ndarray, anchors: np.ndarray, window_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(n,n) route distances ``ds[i, j] = s_j − s_i`` and (n,n) bool: j lies within ``window_m`` of i
    along the route and within ``2·window_m`` in the street frame (``anchors`` (n,3)), so that a
    segment of another pass of the route, next to i in the drifted frame, never joins."""
    ds = route_s[None, :] - route_s[:, None]
    apart = np.linalg.norm(anchors[None, :] - anchors[:, None], axis=2)
    return ds, (np.abs(ds) <= window_m) & (apart <= 2 * window_m)


def sparse_segments(model: SparseModel, dense: np.ndarray, carrier: np.ndarray, valid: np.ndarray,
                    max_gap_m: float = 1.0, only: np.ndarray | None = None) -> np.ndarray:
    """(P,) valid carrier segment of the dense point next to each sparse point (−1: none within
    max_gap_m); ``only``: (N,) bool, the dense points considered (e.g. façade points)."""
    out = np.full(len(model.points3d), -1, np.int64)
    if len(model.points3d) == 0:
        return out
    ok = (carrier >= 0)
    ok[ok] = valid[carrier[ok]]
    if only is not None:
        ok &= only
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return out
    if len(idx) > MAX_TREE_POINTS:
        idx = idx[np.linspace(0, len(idx) - 1, MAX_TREE_POINTS).astype(np.int64)]
    # a tree over the dense points, queried by the few sparse ones: its build dominates, and an
    # unbalanced, non-compacted build is ~2× faster to make for the same nearest neighbours
    tree = cKDTree(dense[idx], balanced_tree=False, compact_nodes=False)
    d, nn = tree.query(model.points3d, distance_upper_bound=max_gap_m, workers=query_workers(len(model.points3d)))
    return np.where(np.isfinite(d), carrier[idx[np.minimum(nn, len(idx) - 1)]], -1)


def route_positions(street: StreetSegments, model: SparseModel | None, dense: np.ndarray,
                    max_gap_m: float = 1.0) -> np.ndarray:
    """(S,) metres along the route of each segment (NaN when no camera sees it or no model); ``dense``:
    the street cloud (metres), ``model``: the COLMAP model (``StreetCapture.sparse``)."""
    S = len(street)
    out = np.full(S, np.nan)
    if model is None or S == 0:
        return out
    if len(model.observations) == 0 or len(model.image_names) < 2:
        return out
    carrier = np.asarray(street.carrier, np.int64)
    s_cam = camera_route_positions(model)
    everyone = np.ones(S, bool)

    def observed_medians(only: np.ndarray | None) -> np.ndarray:
        seg = sparse_segments(model, dense, carrier, everyone, max_gap_m, only=only)[
            model.observations[:, 1].astype(np.int64)]
        keep = seg >= 0
        s_obs = s_cam[model.observations[keep, 0].astype(np.int64)]
        order = np.lexsort((s_obs, seg[keep]))
        segs, s_sorted = seg[keep][order], s_obs[order]
        bounds = np.searchsorted(segs, np.arange(S + 1))
        med = np.full(S, np.nan)
        for i in np.flatnonzero(bounds[1:] > bounds[:-1]):
            med[i] = float(np.median(s_sorted[bounds[i]:bounds[i + 1]]))
        return med

    out = observed_medians(np.asarray(street.point_labels) >= 0)      # façade points first
    unknown = ~np.isfinite(out)
    if unknown.any():                                                 # the rest from every carried point
        out[unknown] = observed_medians(None)[unknown]
    return out


def neighbour_keys(anchors: np.ndarray, route_s: np.ndarray) -> np.ndarray:
    """(S,d+1) keys [anchor, s] for neighbour searches; a segment no camera sees takes the route
    position of the nearest segment that has one (all zero when none has: plain distances)."""
    s = np.asarray(route_s, np.float64).copy()
    known = np.isfinite(s)
    if not known.any():
        return np.column_stack([anchors, np.zeros(len(s))])
    if (~known).any():
        _, nn = cKDTree(anchors[known]).query(anchors[~known])
        s[~known] = s[known][nn]
    return np.column_stack([anchors, s])
