"""Keep each street point with a segment of its own pass of the route.

Where the route comes back past an earlier place (a closed loop: its start and end), the drifted
street frame puts the two passes a few metres to tens of metres apart, and the street segmentation
can merge façades of both passes into one segment, or anchor a point without a valid carrier on a
segment of the other pass. That segment's transform is right for one pass only: on campus, points
of the first and last 5 % of the route made 47–85 % of the points above the 95th error percentile
(label map seed 0: segments whose points of the other pass land 5–15 m off).

Each point's route position (metres travelled by the cameras that observe the sparse point next to
it, within ``max_gap_m``) is compared with its anchor segment's route position
(``toolkit.refine.route``); a point farther than ``pass_gap_m`` along the route from its anchor is
re-anchored on the nearest valid segment of its own pass (nearest by footprint distance among the
segments within ``pass_gap_m`` of it along the route).
A segment's route position is where its façade was seen (``toolkit.refine.route``); a point with no
sparse point near it takes its carrier's (the façade segment nearest to it, registered or not).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from toolkit.refine.route import camera_route_positions
from toolkit.threads import query_workers
from toolkit.types import SparseModel


def median_observers(model: SparseModel) -> np.ndarray:
    """(P,) the lower-median observing image (index in model order) of each sparse point; -1: none."""
    P = len(model.points3d)
    out = np.full(P, -1, np.int64)
    if P == 0 or len(model.observations) == 0:
        return out
    pt = model.observations[:, 1].astype(np.int64)
    img = model.observations[:, 0].astype(np.int64)
    order = np.lexsort((img, pt))
    pt, img = pt[order], img[order]
    start = np.searchsorted(pt, np.arange(P))
    count = np.bincount(pt, minlength=P)
    has = count > 0
    out[has] = img[start[has] + (count[has] - 1) // 2]
    return out


def sparse_route_positions(model: SparseModel) -> np.ndarray:
    """(P,) route position (metres) of each sparse point: lower median over its observing cameras
    (route positions grow with the image order, so that of the median observer)."""
    out = np.full(len(model.points3d), np.nan)
    if len(model.image_names) < 2:
        return out
    observer = median_observers(model)
    seen = observer >= 0
    out[seen] = camera_route_positions(model)[observer[seen]]
    return out


def point_route_positions(points: np.ndarray, sparse_xyz: np.ndarray, sparse_s: np.ndarray,
                          max_gap_m: float) -> np.ndarray:
    """(N,) route position of the sparse point nearest to each point (NaN: none within max_gap_m)."""
    ok = np.isfinite(sparse_s)
    out = np.full(len(points), np.nan)
    if not ok.any() or len(points) == 0:
        return out
    d, nn = cKDTree(sparse_xyz[ok]).query(points, distance_upper_bound=max_gap_m,
                                          workers=query_workers(len(points)))
    hit = np.isfinite(d)
    out[hit] = sparse_s[ok][nn[hit]]
    return out


def reanchor_other_pass(anchors: np.ndarray, xy: np.ndarray, point_s: np.ndarray, segment_s: np.ndarray,
                        fp_xy: np.ndarray, fp_seg: np.ndarray, pass_gap_m: float) -> np.ndarray:
    """Anchors with points of another pass moved to the nearest valid segment of their own pass.

    ``fp_xy``/``fp_seg``: footprint points of the valid segments and their segment; ``segment_s``:
    (S,) route position per segment (NaN: unknown, never judged nor chosen). Points are taken in
    route bins of ``pass_gap_m / 2``; a bin's candidates are the segments within ``pass_gap_m`` of
    every point in it, searched by footprint distance alone (a segment of another pass at the same
    place must never win; Helsinki north: 8 % of the points, 9 m off, had been kept on one). A point
    with no segment of its own pass keeps its anchor.
    """
    anchors = np.asarray(anchors, np.int64).copy()
    s_anchor = segment_s[anchors]
    other = np.isfinite(point_s) & np.isfinite(s_anchor) & (np.abs(point_s - s_anchor) > pass_gap_m)
    keep = np.isfinite(segment_s[fp_seg])
    if not other.any() or not keep.any():
        return anchors
    fp_xy, fp_seg = fp_xy[keep], fp_seg[keep]
    fp_s = segment_s[fp_seg]
    idx = np.flatnonzero(other)
    width = pass_gap_m / 2
    bins = np.floor(point_s[idx] / width).astype(np.int64)
    for b in np.unique(bins):
        rows = idx[bins == b]
        lo = b * width
        cand = (fp_s >= lo + width - pass_gap_m) & (fp_s <= lo + pass_gap_m)   # within the gap of the whole bin
        if not cand.any():
            continue
        _, nn = cKDTree(fp_xy[cand]).query(xy[rows], workers=query_workers(len(rows)))
        anchors[rows] = fp_seg[cand][nn]
    return anchors
