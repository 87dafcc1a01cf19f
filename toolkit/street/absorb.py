"""Leftover façade points absorbed into the adjacent segments (after region growing and filtering).

Region growing leaves pieces of a wall outside its segment: façade points too rough to seed or
link (curvature above the seed limit with no smooth neighbour, e.g. around windows and edges) and
small fragments split off by the strict smoothness angle, then dropped as too small. On the campus
scene they were 2/3 of the missed wall points (median fragment: 5 analysis points). Each such point
takes the segment of its nearest façade-graph neighbour that is already in a segment and whose
normal agrees within a looser angle; repeated ``hops`` times, so a fragment is absorbed through
its own points up to ``hops`` graph links of at most ``max_link_m`` from the segment. Points of no segment's
wall stay out: clutter is rarely linked to a wall by a chain of façade points with agreeing normals.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from toolkit.street.params import StreetConfig


class AbsorbConfig(StreetConfig):
    """Absorption of leftover façade points (see ``absorb_leftovers``)."""

    hops: int = Field(3, ge=0, description="leftover façade points join a neighbour segment whose normal "
                                           "agrees, through up to this many graph links (0 = off)")
    link_m: float = Field(1.0, gt=0, description="absorption follows graph links no longer than this (3D, metres)")
    angle_deg: float = Field(
        10.0, gt=0, lt=90, description="max angle between the normals of a leftover point and its absorbing neighbour")


def absorb_leftovers(labels: np.ndarray, graph: np.ndarray, index: np.ndarray, n_points: int,
                     xyz: np.ndarray, normals: np.ndarray, max_angle_deg: float, max_link_m: float,
                     hops: int) -> np.ndarray:
    """(F,) int32 segment of each façade point, leftovers (-1) absorbed where possible.

    labels: (F,) segment (-1: none); graph: (F,g) analysis indices of each façade point's nearest
    neighbours, nearest first; index: (F,) analysis index of each façade point; xyz, normals: (F,3).
    Links longer than ``max_link_m`` are not followed (a k-nearest graph reaches far in sparse parts).
    """
    out = labels.astype(np.int32, copy=True)
    rows = np.flatnonzero(out < 0).astype(np.int32)
    if hops <= 0 or len(rows) == 0 or not (out >= 0).any():
        return out
    pos = np.full(n_points, -1, dtype=np.int32)
    pos[index] = np.arange(len(index), dtype=np.int32)
    nb = pos[graph[rows]]
    ok = nb >= 0
    nb[~ok] = 0
    cols = [np.ascontiguousarray(normals[:, a], dtype=np.float32) for a in range(3)]
    dot = cols[0][nb] * cols[0][rows, None]
    dot += cols[1][nb] * cols[1][rows, None]
    dot += cols[2][nb] * cols[2][rows, None]
    ok &= np.abs(dot) > np.float32(np.cos(np.radians(max_angle_deg)))
    dot[:] = 0
    for a in range(3):
        dot += (xyz[nb, a] - xyz[rows, a][:, None]) ** 2
    ok &= dot <= max_link_m ** 2
    del dot
    for _ in range(hops):  # one graph link per pass, nearest labelled neighbour first
        cand = np.where(ok, out[nb], -1)
        has = (cand >= 0).any(axis=1)
        if not has.any():
            break
        first = np.argmax(cand[has] >= 0, axis=1)
        out[rows[has]] = cand[has][np.arange(len(first)), first]
        rows, nb, ok = rows[~has], nb[~has], ok[~has]
    return out
