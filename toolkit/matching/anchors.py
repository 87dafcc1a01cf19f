"""Anchored pose hypotheses for the data term: a sparse, exact sampling of the offset/rotation window.

The centre-line transform puts the façade centres where the building centres are, but a façade
lies on its building's *outline*, often 10 m or more from the building centre, so the centre-line
rotation can be off by 20° or more and the offset by the building's half size. Instead of a dense
grid over that window, a hypothesis puts the midpoint of one street segment's dominant wall (j)
on an outline sample ("anchor") of its candidate segment p, with the wall along the outline's
tangent there (either way round). That fixes the whole rigid pose; the hypothesis is kept when it
also puts the other segment's wall midpoint (k) near q's outline and stays within the candidate's
rotation and offset windows around the centre-line pose. Both ends are tried as the anchor, so a
label and its reverse are treated alike. Segments without a clear dominant wall are not anchors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from toolkit.matching.atlas import SCALE, CropAtlas, _segment_mask, boundary_tangent_angle
from toolkit.matching.chamfer import Pairs, ranges
from toolkit.matching.config import MatchingConfig
from toolkit.types import OverviewSegments


class AnchorConfig(MatchingConfig):
    """The anchored pose search of the data term (``search: anchor``)."""

    flat_names = {"spacing_m": "anchor_spacing_m", "tolerance_px": "anchor_tolerance_px"}

    spacing_m: float = Field(1.0, gt=0, description="outline sample spacing for anchored hypotheses (m)")
    tolerance_px: float = Field(3.0, gt=0, description="an anchored hypothesis must put the other façade centre "
                                                      "this close to its candidate's outline (px)")
    max_hypotheses: int = Field(16, ge=1, description="anchored hypotheses scored per candidate (count)")
    min_wall_share: float = Field(
        0.3, ge=0, le=1, description="share of a segment's points its dominant straight wall needs to anchor hypotheses (0-1)")
    rotation_window_from_extent: bool = Field(
        True, description="widen the rotation window per candidate to asin((ρ_p + ρ_q) / centre-line length)")
    rotation_window_max_deg: float = Field(
        60.0, ge=0, le=180, description="cap on that widened window (a straight façade also fits its wall "
                                        "turned by 180°; the cap keeps such flips out)")


@dataclass(frozen=True)
class Anchors:
    """Outline samples of every over-view segment, sorted by tangent angle within each segment.

    xy: (N,2) local metres; angle: (N,) tangent angle in [0, π) (world frame); ptr: (S+1,);
    key: (N,) ascending segment·4 + angle, for range look-ups by angle.
    """

    xy: np.ndarray
    angle: np.ndarray
    ptr: np.ndarray
    key: np.ndarray


def outline_anchors(overview: OverviewSegments, o_world: np.ndarray, A_inv: np.ndarray, px0: np.ndarray,
                    spacing_m: float) -> Anchors:
    cell = max(1, round(spacing_m / overview.grid.gsd_m))
    xy, tang, counts = [], [], []
    for p, b in enumerate(overview.boundary_px):  # one iteration per over-view segment
        b = np.asarray(b, dtype=np.int64).reshape(-1, 2)
        if len(b) == 0:
            counts.append(0)
            continue
        origin = b.min(axis=0) - 4
        shape = tuple(b.max(axis=0) - origin + 5)
        mask = _segment_mask(overview.label_image, p, origin, shape)
        ang = boundary_tangent_angle(mask, b[:, 0] - origin[0], b[:, 1] - origin[1])
        _, first = np.unique(b // cell, axis=0, return_index=True)
        first = np.sort(first)
        d_px = np.stack([np.sin(ang[first]), np.cos(ang[first])], axis=1)  # (drow, dcol)
        d_w = d_px @ A_inv.T
        xy.append((b[first] - px0) @ A_inv.T)
        tang.append(d_w / np.linalg.norm(d_w, axis=1, keepdims=True))
        counts.append(len(first))
    ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    xy_all = np.concatenate(xy) if xy else np.zeros((0, 2))
    t_all = np.concatenate(tang) if tang else np.zeros((0, 2))
    angle = np.mod(np.arctan2(t_all[:, 1], t_all[:, 0]), np.pi)
    seg = np.repeat(np.arange(len(counts)), counts)
    order = np.lexsort((angle, seg))
    key = seg[order] * 4.0 + angle[order]
    return Anchors(xy_all[order], angle[order], ptr, key)


def segment_walls(points: list[np.ndarray], bin_deg: float = 5.0, band_m: float = 1.0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The dominant straight wall of each street segment: its midpoint (S,2), unit direction (S,2)
    and the share of the segment's points on it (S,).

    A façade segment is often two or three walls around corners; its centre then lies inside the
    building, while the midpoint of its longest wall lies on the outline. The wall is the densest
    band (±band_m across) of points whose local direction is within 15° of the dominant one.
    """
    from toolkit.matching.chamfer import point_directions

    S = len(points)
    anchor = np.zeros((S, 2))
    direction = np.tile([1.0, 0.0], (S, 1))
    share = np.zeros(S)
    n_bins = round(180 / bin_deg)
    for i, xy in enumerate(points):  # one iteration per street segment
        if len(xy) < 5:
            if len(xy):
                anchor[i] = xy.mean(axis=0)
            continue
        a = point_directions(xy)
        hist = np.bincount((a / np.pi * n_bins).astype(np.int64) % n_bins, minlength=n_bins).astype(float)
        hist = hist + 0.5 * (np.roll(hist, 1) + np.roll(hist, -1))
        peak = (np.argmax(hist) + 0.5) * np.pi / n_bins
        near = np.abs(np.mod(a - peak + np.pi / 2, np.pi) - np.pi / 2) < np.deg2rad(15)
        # refine the direction: mean of doubled angles of the points near the peak
        phi = 0.5 * np.arctan2(np.sin(2 * a[near]).sum(), np.cos(2 * a[near]).sum())
        d = np.array([np.cos(phi), np.sin(phi)])
        normal_coord = xy[near] @ np.array([-d[1], d[0]])
        lo = normal_coord.min()
        counts = np.bincount(((normal_coord - lo) / band_m).astype(np.int64))
        counts = counts + np.concatenate([counts[1:], [0]])  # band of two bins
        b0 = np.argmax(counts)
        on = (normal_coord >= lo + b0 * band_m) & (normal_coord < lo + (b0 + 2) * band_m)
        wall = xy[near][on]
        anchor[i] = wall.mean(axis=0)
        direction[i] = d
        share[i] = len(wall) / len(xy)
    return anchor, direction, share


def observer_sides(cameras_xy: np.ndarray, anchor: np.ndarray, direction: np.ndarray, k: int = 5,
                   min_offset_m: float = 1.0) -> np.ndarray:
    """(S,2) unit normal of each segment's dominant wall pointing to where it was seen from (the
    median side of its k nearest cameras), or zeros when the cameras do not tell."""
    from scipy.spatial import cKDTree

    normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1)
    if len(cameras_xy) == 0 or len(anchor) == 0:
        return np.zeros_like(normal)
    kk = min(k, len(cameras_xy))
    _, idx = cKDTree(cameras_xy).query(anchor, k=kk)
    idx = idx.reshape(len(anchor), kk)
    along = np.einsum("skd,sd->sk", cameras_xy[idx] - anchor[:, None], normal)
    side = np.median(along, axis=1)
    sign = np.where(np.abs(side) >= min_offset_m, np.sign(side), 0.0)
    return normal * sign[:, None]


def _wrap_pi(a: np.ndarray) -> np.ndarray:
    return np.mod(a + np.pi, 2 * np.pi) - np.pi


def _rot(c: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def _angle_ranges(anchors: Anchors, seg: np.ndarray, centre: np.ndarray, half: np.ndarray | float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Anchors of segment ``seg[i]`` whose angle is within ``half`` of ``centre[i]`` (mod π):
    (item owner index, anchor index)."""
    half = np.broadcast_to(np.asarray(half, dtype=np.float64), centre.shape)
    full = half >= np.pi / 2
    lo, hi = centre - half, centre + half
    zero, top = np.zeros_like(lo), np.full_like(lo, np.pi)
    pieces = [(zero, top, full),
              (lo, hi, ~full & (lo >= 0) & (hi < np.pi)),                  # no wrap
              (zero, hi, ~full & (lo < 0)), (lo + np.pi, top, ~full & (lo < 0)),
              (lo, top, ~full & (hi >= np.pi)), (zero, hi - np.pi, ~full & (hi >= np.pi))]
    owners, items = [], []
    for a, b, use in pieces:
        i = np.nonzero(use)[0]
        start = np.searchsorted(anchors.key, seg[i] * 4.0 + a[i], side="left")
        stop = np.searchsorted(anchors.key, seg[i] * 4.0 + b[i], side="right")
        n = np.maximum(stop - start, 0)
        owners.append(np.repeat(i, n))
        items.append(ranges(start, n))
    return np.concatenate(owners), np.concatenate(items)


def hypotheses(atlas: CropAtlas, A: np.ndarray, px0: np.ndarray, anchors: Anchors, pairs: Pairs,
               s_anchor: np.ndarray, s_dir: np.ndarray, usable: np.ndarray, edges: np.ndarray,
               s_mid: np.ndarray, o_mid: np.ndarray, reach_m: np.ndarray, rot_window: np.ndarray, tol_px: float,
               max_per_pair: int, theta_prior: np.ndarray | None = None,
               prior_window: float = np.pi, prior_mid: np.ndarray | None = None,
               prior_radius_m: np.ndarray | None = None) -> tuple[np.ndarray, Pairs]:
    """Anchored hypotheses of ``pairs`` (whose ``theta`` is the centre-line angle θ0), each putting the
    street-edge midpoint within ``reach_m`` (P,) of ``o_mid`` (P,2, local metres) and, when given,
    within ``prior_radius_m`` of ``prior_mid``, turned by at most ``rot_window`` (P,) from θ0.

    theta_prior (P,): an absolute heading per pair (NaN: none, e.g. from GPS); hypotheses turned
    farther than ``prior_window`` from it are dropped before the best ``max_per_pair`` are kept.

    Returns (H,) the index of the pair each hypothesis belongs to, and the hypotheses as ``Pairs``
    (theta, pivot_px at the street-edge midpoint, zero offset)."""
    buf = atlas.level(1 if 1 in atlas.erosion_px else 0)
    tol = min(tol_px / atlas.truncate_px, 1.0) * SCALE
    s_ang = np.mod(np.arctan2(s_dir[:, 1], s_dir[:, 0]), np.pi)
    out_pair, out_theta, out_pivot, out_rank = [], [], [], []
    for side in (0, 1):
        a_seg = edges[pairs.edge, side]                 # anchored street segment
        b_seg = edges[pairs.edge, 1 - side]
        pid = np.nonzero(usable[a_seg])[0]
        # per-pair quantities, gathered once per item below through ``own`` (index into pid)
        v_mid = s_mid[pairs.edge[pid]] - s_anchor[a_seg[pid]]
        v_b = s_anchor[b_seg[pid]] - s_anchor[a_seg[pid]]
        o_mid_p, reach_p, rotw_p = o_mid[pid], reach_m[pid] + 1e-9, rot_window[pid]
        # the tangent must be the façade direction turned by θ0 ± rot_window (mod π)
        want = np.mod(pairs.theta[pid] + s_ang[a_seg[pid]], np.pi)
        own, ia = _angle_ranges(anchors, pairs.crops[pid, side], want, rotw_p)
        if len(own) == 0:
            continue
        delta = np.mod(anchors.angle[ia] - want[own] + np.pi / 2, np.pi) - np.pi / 2
        # a window of ±90° or more admits the wall either way round: both turns
        both = rotw_p[own] >= np.pi / 2
        own, ia, delta = (np.concatenate([own, own[both]]), np.concatenate([ia, ia[both]]),
                          np.concatenate([delta, delta[both] + np.pi]))
        th = pairs.theta[pid][own] + delta
        if theta_prior is not None:
            tp = theta_prior[pid][own]
            near = ~(np.abs(_wrap_pi(th - tp)) > prior_window)  # NaN prior: kept
            own, ia, delta, th = own[near], ia[near], delta[near], th[near]
        c_, s_ = np.cos(th), np.sin(th)
        xa = anchors.xy[ia]
        mid_w = xa + _rot(c_, s_, v_mid[own])
        within = np.linalg.norm(mid_w - o_mid_p[own], axis=1) <= reach_p[own]
        if prior_mid is not None:
            within &= np.linalg.norm(mid_w - prior_mid[pid][own], axis=1) <= prior_radius_m[pid][own]
        own, c_, s_, th, xa, mid_w, delta = (own[within], c_[within], s_[within], th[within], xa[within],
                                             mid_w[within], delta[within])
        xb = xa + _rot(c_, s_, v_b[own])
        pix = np.rint(xb @ A.T + px0).astype(np.int64)
        bins = None
        if atlas.n_bins > 1:  # directional maps: the plane of the other wall's turned direction
            d_w = _rot(c_, s_, s_dir[b_seg[pid]][own]) @ A.T
            pix_ang = np.mod(np.arctan2(d_w[:, 0], d_w[:, 1]), np.pi)
            bins = np.floor(pix_ang / np.pi * atlas.n_bins).astype(np.int64) % atlas.n_bins
        val = buf[atlas.flat_index(pix[:, 0].copy(), pix[:, 1].copy(), pairs.crops[pid, 1 - side][own], bins)]
        good = val <= tol
        out_pair.append(pid[own[good]])
        out_theta.append(th[good])
        out_pivot.append(mid_w[good] @ A.T + px0)
        turn = np.abs(_wrap_pi(delta[good]))
        # turn away from the centre line, blind to its direction (undefined for (p, p) labels)
        out_rank.append(val[good].astype(np.float64) + np.minimum(turn, np.pi - turn))
    if not out_pair:
        return np.zeros(0, np.int64), _empty_pairs()
    pair = np.concatenate(out_pair)
    theta = np.concatenate(out_theta)
    pivot = np.concatenate(out_pivot)
    # at most max_per_pair per pair: the best-anchored first (distance of the other wall to its
    # outline, then rotation away from the centre line), which does not depend on which end of
    # the edge was listed first
    rank_key = np.round(np.concatenate(out_rank), 9)
    order = np.lexsort((pivot[:, 1].round(6), pivot[:, 0].round(6), rank_key, pair))
    pair, theta, pivot = pair[order], theta[order], pivot[order]
    first = np.searchsorted(pair, pair, side="left")
    sel = np.arange(len(pair)) - first < max_per_pair
    pair, theta, pivot = pair[sel], theta[sel], pivot[sel]
    hyp = Pairs(pairs.edge[pair], pairs.crops[pair], theta, pivot, np.zeros((len(pair), 2), np.int64))
    return pair, hyp


def _empty_pairs() -> Pairs:
    z = np.zeros(0, np.int64)
    return Pairs(z, np.zeros((0, 2), np.int64), np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2), np.int64))
