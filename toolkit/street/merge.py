"""Merging segments that belong to one wall or one building.

Rabbani growing stops at every sharp corner and at every gap (a tree or a pole in front of the
wall), so a building seen round its corner gives one segment per wall, short side walls fall under
the size limit, and an occluded wall comes in pieces. Two segments holding at least ``min_points``
points each and reaching the same height (98th percentiles of height within ``height_tol_m``:
the eaves of one building continue round its corners, neighbouring buildings rarely share an
eaves height) are merged when either
- they face directions at least ``min_corner_deg`` apart and their façade points come within
  ``contact_m`` of each other horizontally (a corner), or
- they face the same way (within ``parallel_deg``), their nearest points are within ``gap_m``
  of each other and the step between them across the wall is under ``offset_m`` (one wall seen
  in pieces; the released code likewise merges collinear 2D lines).
Merges are transitive (connected components of the "may merge" graph).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree

from toolkit.street.associate import decimate_xy, group_quantile
from toolkit.street.growing import components
from toolkit.street.params import StreetConfig


class MergeConfig(StreetConfig):
    """Merging at corners and across gaps (keyword arguments of ``merge_segments``)."""

    contact_m: float = Field(1.0, ge=0, description="merge segments whose façade points come this close (2D) "
                                                    "at equal wall height (0 = off)")
    gap_m: float = Field(0.0, ge=0, description="merge pieces of one wall (parallel, in line) up to this far apart "
                                                "at equal height (m; 0 = off)")
    height_tol_m: float = Field(1.0, gt=0, description="max difference of wall-top heights where segments meet (m)")
    min_corner_deg: float = Field(
        45.0, ge=0, le=90, description="merge only segments whose façades turn by at least this (degrees; a corner)")


def merge_segments(xy: np.ndarray, z: np.ndarray, azimuth: np.ndarray, labels: np.ndarray, contact_m: float,
                   gap_m: float, height_tol_m: float, min_corner_deg: float, min_points: int,
                   parallel_deg: float = 10.0, offset_m: float = 0.5, cell_m: float = 0.25) -> np.ndarray:
    """Labels (≥ 0 in segments; -1 kept) with corner-adjacent and collinear segments joined.

    azimuth: (F,) horizontal normal direction of each point (radians, orientation mod π).
    """
    ok = labels >= 0
    reach = max(contact_m, gap_m)
    if reach <= 0 or not ok.any():
        return labels
    n = int(labels.max()) + 1
    lab = labels[ok]
    size = np.bincount(lab, minlength=n)
    doubled = 2.0 * azimuth[ok].astype(np.float64)
    mean2 = np.arctan2(np.bincount(lab, weights=np.sin(doubled), minlength=n),
                       np.bincount(lab, weights=np.cos(doubled), minlength=n))
    normal = np.stack([np.cos(mean2 / 2), np.sin(mean2 / 2)], axis=1)
    top = group_quantile(z[ok], lab, n, 0.98)
    big = size[lab] >= min_points
    rep_xy, rep_lab = decimate_xy(xy[ok][big], lab[big], cell_m)
    if len(rep_xy) < 2:
        return labels
    pairs = cKDTree(rep_xy).query_pairs(reach, output_type="ndarray")
    a, b = rep_lab[pairs[:, 0]], rep_lab[pairs[:, 1]]
    differ = a != b
    pairs, a, b = pairs[differ], a[differ], b[differ]
    if len(pairs) == 0:
        return labels
    delta = rep_xy[pairs[:, 1]] - rep_xy[pairs[:, 0]]
    dist = np.hypot(delta[:, 0], delta[:, 1])
    # per segment pair: the closest pair of points and the step across the first one's wall there
    edge = np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b)
    order = np.lexsort((dist, edge))
    first = order[np.flatnonzero(np.r_[True, edge[order][1:] != edge[order][:-1]])]
    a, b, dist = a[first], b[first], dist[first]
    across = np.abs(np.einsum("ij,ij->i", delta[first], normal[a]))
    turn = np.abs(np.mod(mean2[a] - mean2[b] + np.pi, 2 * np.pi) - np.pi) / 2.0  # [0, π/2]
    corner = (turn >= np.radians(min_corner_deg)) & (dist <= contact_m)
    collinear = (turn <= np.radians(parallel_deg)) & (dist <= gap_m) & (across <= offset_m)
    join = (corner | collinear) & (np.abs(top[a] - top[b]) <= height_tol_m)
    a, b = a[join], b[join]
    order = np.argsort(a, kind="stable")
    indptr = np.concatenate([[0], np.cumsum(np.bincount(a, minlength=n))])
    merged = components(n, indptr, b[order].astype(np.int32))
    out = labels.copy()
    out[ok] = merged[lab]
    return out
