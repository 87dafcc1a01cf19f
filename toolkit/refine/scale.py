"""Per-segment scale along the route: monocular SfM's slow scale drift, read off the registration.

A street frame from monocular video drifts in scale along the route (±1–3 % over a kilometre is
common), and a rigid transform per segment cannot absorb it: a 50 m façade 3 % too large ends
0.75 m off at both ends. Segments are registered rigidly first; each registered segment then
tells where its centre belongs. For two segments j, k at least ``min_baseline_m`` apart, the ratio
of their registered to their input centre distance is the street frame's scale between them. A
segment's scale is the baseline-weighted median of the ratios of every such pair captured within
``window_m`` of it along the route (not only its own pairs: its own placement error would enter
every one of them), shrunk towards 1 where it is not clearly above its own noise (positive-part
James-Stein, on the median's standard error) and clipped to ``1 ± max_deviation``; the later passes search its footprint at
that scale, about its centre, and the joint pass scales the whole window about it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toolkit.arrays import weighted_median


class ScaleConfig(BaseModel):
    """Per-segment scale from the route neighbours (see toolkit.refine.scale)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_deviation: float = Field(0.05, ge=0, le=0.5, description="a segment's scale stays within 1 ± this (fraction; 0: rigid segments)")
    window_m: float = Field(150.0, gt=0, description="segments captured within this route distance are paired (metres)")
    min_baseline_m: float = Field(20.0, gt=0, description="pairs of segment centres closer than this are not used (metres)")
    min_pairs: int = Field(3, ge=1, description="a segment with fewer pairs keeps scale 1 (count)")


@dataclass(frozen=True)
class SegmentScales:
    """Per segment: scale (1 where not estimated) and the number of pairs behind it."""

    scale: np.ndarray
    pairs: np.ndarray


def route_scales(placed_xy: np.ndarray, input_xy: np.ndarray, route_s: np.ndarray, valid: np.ndarray,
                 weight: np.ndarray, p: ScaleConfig) -> SegmentScales:
    """Scales from registered centres ``placed_xy`` (S,2, scene) and input centres ``input_xy`` (S,2,
    levelled street frame), for the valid segments with a route position; weight: per-segment support."""
    S = len(route_s)
    scale, pairs = np.ones(S), np.zeros(S, np.int64)
    idx = np.flatnonzero(valid & np.isfinite(route_s))
    if len(idx) < p.min_pairs + 1:
        return SegmentScales(scale, pairs)
    idx = idx[np.argsort(route_s[idx], kind="stable")]
    s_sorted = route_s[idx]
    lo, hi = 1.0 / (1.0 + p.max_deviation), 1.0 + p.max_deviation
    for i in idx:
        # the members of i's window: a contiguous run of the route-sorted segments
        a = max(int(np.searchsorted(s_sorted, route_s[i] - p.window_m)) - 1, 0)
        b = int(np.searchsorted(s_sorted, route_s[i] + p.window_m, side="right")) + 1
        members = idx[a:b][np.abs(s_sorted[a:b] - route_s[i]) <= p.window_m]
        d_in = np.linalg.norm(input_xy[members, None] - input_xy[None, members], axis=2)
        d_out = np.linalg.norm(placed_xy[members, None] - placed_xy[None, members], axis=2)
        pair = np.triu(d_in >= p.min_baseline_m, 1)
        pairs[i] = int(pair.sum())
        if pairs[i] >= p.min_pairs:
            ratio = d_out[pair] / d_in[pair]
            w = d_in[pair] * np.sqrt(np.outer(weight[members], weight[members])[pair])
            scale[i] = float(np.clip(_shrunk(np.log(ratio), w, len(members)), lo, hi))
    return SegmentScales(scale, pairs)


def scaling_about(pivots: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(S,4,4) maps p ↦ c + s (p − c), one per segment (pivot c (S,3), scale s (S,))."""
    M = np.repeat(np.eye(4)[None], len(scale), axis=0)
    M[:, :3, :3] *= scale[:, None, None]
    M[:, :3, 3] = pivots * (1.0 - scale[:, None])
    return M


def _shrunk(log_ratio: np.ndarray, w: np.ndarray, members: int) -> float:
    """exp of the weighted median of the log ratios, shrunk towards 0 by the positive-part
    James-Stein factor max(0, 1 − σ²/m²): m the median, σ its standard error (1.4826 · MAD over
    √members: the pairs share their segments' placement errors, so only the members are independent)."""
    m = weighted_median(log_ratio, w)
    sigma = 1.4826 * weighted_median(np.abs(log_ratio - m), w) / np.sqrt(max(members, 1))
    if m == 0.0:
        return 1.0
    return float(np.exp(m * max(0.0, 1.0 - (sigma / m) ** 2)))
