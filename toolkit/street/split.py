"""Cutting façade segments where one house of a terrace ends and the next begins.

Terraced houses share one façade plane, so region growing (smooth normals) makes one segment of a
whole row. Neighbouring houses often differ in the height of the façade top (eaves), sometimes by
a set-back of the façade plane or a slight turn (``bench/street_terrace_ceiling.py`` counts how often
on a real LoD2 city, from the truth). Each segment is walked along its horizontal axis (normal to
its mean façade direction) in ``bin_m`` bins; per bin: the façade top (3rd highest point), the
median distance along the normal (the plane), the mean normal direction. At every bin boundary the
``window_m`` on either side are compared; the segment is cut where a step exceeds its threshold, is
the largest within a window (one cut per step), at least ``min_end_m`` from the segment's ends and
``min_gap_m`` from a stronger cut. The façade top's step must show both between the window medians
and where lines fitted to the two windows meet (less a doubt from their fit residuals and slopes),
so that the sloping top of a gable facing the street is not cut at its ridge.
Everything works on one array of all segments' bins: no loop over segments or points.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from pydantic import Field
from scipy.ndimage import maximum_filter1d

from toolkit.street.associate import group_median
from toolkit.street.params import StreetConfig

TOP_RANK = 3  # the façade top of a bin: its 3rd highest point (robust to two high outliers)
# Doubt taken off a fitted step: the fits' RMS residuals and their slopes (per bin) times these.
# A window straddling a gable's ridge fits badly and steeply; on the synthetic gables of
# tests/test_street_split.py, 0.5 / 1.0 cut no ridge up to 56° pitch and find 7/8 steps of 0.35 m.
RMS_WEIGHT = 0.5
SLOPE_WEIGHT = 1.0


class SplitConfig(StreetConfig):
    """Terrace split (the keyword arguments of ``split_terraces``)."""

    window_m: float = Field(0.0, ge=0, description="length compared either side of each place along a "
                                                   "façade top (m; 0 = no split; 2.0 for terraced cities)")
    bin_m: float = Field(0.5, gt=0, description="profile bin length along the façade (m)")
    top_step_m: float = Field(
        0.3, ge=0, description="cut where the façade top (eaves) steps by at least this (m; 0 = off)")
    setback_m: float = Field(
        0.0, ge=0, description="cut where the façade plane steps back by at least this (m; 0 = off)")
    turn_deg: float = Field(
        0.0, ge=0, description="cut where the façade direction turns by at least this (degrees; 0 = off)")
    min_end_m: float = Field(
        5.0, ge=0, description="no cut closer than this to a segment's end, where façade tops droop (m)")
    min_gap_m: float = Field(5.0, ge=0, description="cuts at least this far apart (m; the stronger step wins)")


def split_terraces(xyz: np.ndarray, azimuth: np.ndarray, labels: np.ndarray, bin_m: float, window_m: float,
                   top_step_m: float, setback_m: float, turn_deg: float,
                   min_end_m: float = 0.0, min_gap_m: float = 0.0) -> np.ndarray:
    """(F,) int32 labels (≥ 0 in segments, -1 kept) with segments cut at house boundaries.

    xyz: (F,3) levelled façade points; azimuth: (F,) horizontal normal direction (radians,
    orientation mod π); a threshold ≤ 0 turns its criterion off. The first piece of a cut segment
    keeps its label, the others get new ones above the largest (not ordered by size).
    """
    ok = labels >= 0
    off = top_step_m <= 0 and setback_m <= 0 and turn_deg <= 0
    if off or not ok.any() or window_m <= 0:
        return labels
    n = int(labels.max()) + 1
    w = max(1, int(round(window_m / bin_m)))
    m, g = int(np.ceil(min_end_m / bin_m)), int(np.ceil(min_gap_m / bin_m))
    doubled = 2.0 * azimuth[ok].astype(np.float64)
    mean2 = np.arctan2(np.bincount(labels[ok], np.sin(doubled), n), np.bincount(labels[ok], np.cos(doubled), n))
    normal = np.stack([np.cos(mean2 / 2), np.sin(mean2 / 2)], axis=1)
    # only segments long enough to be cut get profiles (most grown segments are small fragments)
    (xlo, xhi), (ylo, yhi) = _extents([xyz[ok, 0], xyz[ok, 1]], labels[ok], n)
    long = np.nan_to_num(np.hypot(xhi - xlo, yhi - ylo)) >= bin_m * max(2 * m, 2 * w)  # box diagonal ≥ length
    if not long.any():
        return labels
    sel = ok & long[np.maximum(labels, 0)]
    remap = np.cumsum(long) - 1
    lab = remap[labels[sel]]
    n = int(long.sum())
    p = xyz[sel]
    doubled = 2.0 * azimuth[sel].astype(np.float64)
    mean2, normal = mean2[long], normal[long]
    along = p[:, 1] * normal[lab, 0] - p[:, 0] * normal[lab, 1]
    ((lo, _),) = _extents([along], lab, n)
    local = np.floor((along - lo[lab]) / bin_m).astype(np.int64)
    n_bins = np.zeros(n, dtype=np.int64)
    np.maximum.at(n_bins, lab, local + 1)
    # all segments' profiles in one array, with empty bins between them so that neither the windows
    # nor the spacing of cuts mixes segments
    pad = max(w, m, g)
    start = np.concatenate([[0], np.cumsum(n_bins + pad)[:-1]]) + pad
    total = int(start[-1] + n_bins[-1] + pad)
    gbin = start[lab] + local
    score = np.zeros(total - 2 * w + 1)
    if top_step_m > 0:
        top = _kth_highest(p[:, 2], gbin, total, TOP_RANK)
        # a step shows both in the window medians and at the lines' meeting point; a sloping top
        # (gable) only in the medians, noise spikes mostly only in the extrapolated lines
        score = np.maximum(score, np.minimum(_step(top, w), _break(top, w)) / top_step_m)
    if setback_m > 0:
        across = p[:, 0] * normal[lab, 0] + p[:, 1] * normal[lab, 1]
        score = np.maximum(score, _step(group_median(across, gbin, total), w) / setback_m)
    if turn_deg > 0:
        dev = np.mod(doubled - mean2[lab] + np.pi, 2 * np.pi) - np.pi
        c, s = np.bincount(gbin, np.cos(dev), total), np.bincount(gbin, np.sin(dev), total)
        turn = np.where(c ** 2 + s ** 2 > 0, np.arctan2(s, c) / 2, np.nan)
        score = np.maximum(score, _step(turn, w) / np.radians(turn_deg))
    # score[j]: boundary between bins j+w-1 and j+w (left window j .. j+w-1, right j+w .. j+2w-1)
    peak = np.flatnonzero((score >= 1.0) & (score == maximum_filter1d(score, size=2 * w + 1, mode="constant")))
    if len(peak) == 0:
        return labels
    piece = np.cumsum(_cuts(score, peak + w, w, start, n_bins, total, m, g))  # cuts up to each bin: a piece id
    later = piece[gbin] > piece[start[lab]]  # not in its segment's first piece
    out = labels.copy()
    rows = np.flatnonzero(sel)[later]
    out[rows] = (int(labels.max()) + piece[gbin[later]]).astype(np.int32)
    return out


def _cuts(score: np.ndarray, at: np.ndarray, w: int, start: np.ndarray, n_bins: np.ndarray, total: int,
          m: int, g: int) -> np.ndarray:
    """(total,) int64, 1 at the first bin after each cut: of the candidates ``at`` (the bin after a
    peak of ``score``), those at least ``m`` bins from their segment's ends, ``g`` bins apart."""
    # façade tops often droop at a segment's ends (corners, occlusion): no cut within min_end_m of
    # them; cuts at least min_gap_m apart, the stronger first (a few vectorised greedy rounds; a
    # tiny rising offset breaks ties, e.g. the plateaus that window medians make, to one cut)
    seg_of = np.searchsorted(start, at, side="right") - 1
    room = (at - start[seg_of] >= m) & (start[seg_of] + n_bins[seg_of] - at >= m)
    strength = np.zeros(total)
    strength[at[room]] = score[at[room] - w] + 1e-9 * np.arange(int(room.sum()))
    cut = np.zeros(total, dtype=np.int64)
    reach = 2 * g - 1
    while g > 0 and strength.any():
        best = (strength > 0) & (strength == maximum_filter1d(strength, size=reach, mode="constant"))
        cut[best] = 1
        strength[maximum_filter1d(best.astype(np.int8), size=reach, mode="constant") > 0] = 0
    if g == 0:
        cut[at[room]] = 1
    return cut


def _step(values: np.ndarray, w: int) -> np.ndarray:
    """|median of the w bins right of each boundary - median of the w bins left of it|; 0 where
    either side has under 3/4 of its bins filled (segment ends, gaps)."""
    win = np.sort(sliding_window_view(values, w), axis=1)  # win[i] = sorted values[i:i+w], NaN last
    filled = np.isfinite(win).sum(axis=1)
    k = np.maximum(filled, 1)
    rows = np.arange(len(win))
    med = 0.5 * (win[rows, (k - 1) // 2] + win[rows, k // 2])
    ok = (filled[:-w] * 4 >= 3 * w) & (filled[w:] * 4 >= 3 * w)
    return np.where(ok, np.abs(med[w:] - med[:-w]), 0.0)


def _break(values: np.ndarray, w: int) -> np.ndarray:
    """At each boundary: |right - left| of the lines fitted (least squares) to the w bins either side,
    both evaluated at the boundary, less RMS_WEIGHT x their RMS residuals and SLOPE_WEIGHT x their
    slopes (per bin). A step in the façade top keeps its height; a sloping top (a gable facing the
    street) has none, and near its ridge a window fits badly and steeply, which cancels the
    apparent step there. 0 where either side has under 3/4 of its bins filled."""
    ok = np.isfinite(values)
    x = np.arange(len(values), dtype=np.float64) + 0.5  # bin centres; boundary b lies at x = b
    y = np.where(ok, values, 0.0)
    sums = [np.concatenate([[0.0], np.cumsum(v)])
            for v in (ok.astype(np.float64), ok * x, ok * x * x, y, y * x, y * y)]
    n, sx, sxx, sy, sxy, syy = (c[w:] - c[:-w] for c in sums)  # [i]: sum over bins i .. i+w-1
    with np.errstate(all="ignore"):
        vx, vy, cxy = sxx - sx * sx / n, syy - sy * sy / n, sxy - sx * sy / n
        slope = np.where(n >= 2, cxy / vx, 0.0)
        rms = np.sqrt(np.maximum(vy - slope * cxy, 0.0) / n)
        mean_x, mean_y = sx / n, sy / n
    b = np.arange(len(values) - 2 * w + 1, dtype=np.float64) + w
    left = mean_y[:-w] + slope[:-w] * (b - mean_x[:-w])
    right = mean_y[w:] + slope[w:] * (b - mean_x[w:])
    filled = (n[:-w] * 4 >= 3 * w) & (n[w:] * 4 >= 3 * w)
    doubt = RMS_WEIGHT * (rms[:-w] + rms[w:]) + SLOPE_WEIGHT * (np.abs(slope[:-w]) + np.abs(slope[w:]))
    return np.where(filled, np.maximum(np.abs(right - left) - doubt, 0.0), 0.0)


def _kth_highest(values: np.ndarray, groups: np.ndarray, n: int, k: int) -> np.ndarray:
    """(n,) the k-th highest value per group 0..n-1; NaN for groups with fewer than k values."""
    span = float(values.max() - values.min()) * 1.001 + 1e-9
    order = np.argsort(groups + (values - values.min()) / span)  # one float key: group, then value
    counts = np.bincount(groups, minlength=n)
    end = np.cumsum(counts)
    out = np.full(n, np.nan)
    has = counts >= k
    out[has] = values[order[end[has] - k]]
    return out


def _extents(columns: list[np.ndarray], labels: np.ndarray, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per label 0..n-1: (min, max) of each column (NaN for absent labels), with one sort."""
    order = np.argsort(labels, kind="stable")
    present = np.flatnonzero(np.bincount(labels, minlength=n))
    starts = np.searchsorted(labels[order], present)
    out = []
    for c in columns:
        lo, hi = np.full(n, np.nan), np.full(n, np.nan)
        lo[present] = np.minimum.reduceat(c[order], starts)
        hi[present] = np.maximum.reduceat(c[order], starts)
        out.append((lo, hi))
    return out
