"""Terrace split (toolkit/street/split.py): segments cut where the façade top steps, not elsewhere."""

from __future__ import annotations

import numpy as np
import pytest

from plugins.street_region_growing import RegionGrowing
from toolkit.observe import NullObserver
from toolkit.street.split import split_terraces

DEFAULTS = dict(bin_m=0.5, window_m=2.0, top_step_m=0.3, setback_m=0.0, turn_deg=0.0, min_end_m=5.0, min_gap_m=5.0)


def _facade(rng, x0: float, x1: float, top, per_m: int = 600, noise_m: float = 0.03):
    """Points of a wall along x (normal +y) from x0 to x1 whose top is ``top(x)`` (a callable)."""
    n = int(per_m * (x1 - x0))
    x = rng.uniform(x0, x1, n)
    z = rng.uniform(0.0, 1.0, n) * top(x)
    xyz = np.column_stack([x, rng.normal(0.0, noise_m, n), z])
    return xyz


def _split(parts, labels=None, angle=0.0, **kw):
    xyz = np.concatenate(parts)
    if labels is None:
        labels = np.zeros(len(xyz), dtype=np.int32)
    c, s = np.cos(angle), np.sin(angle)
    xyz = xyz @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]).T  # any street direction
    azimuth = np.full(len(xyz), np.pi / 2 + angle)
    return split_terraces(xyz, azimuth, labels, **{**DEFAULTS, **kw})


@pytest.mark.parametrize("angle", [0.0, 0.7, 2.5])
def test_flush_facades_of_two_heights_become_two_segments(angle):
    rng = np.random.default_rng(1)
    a = _facade(rng, 0.0, 8.0, lambda x: np.full_like(x, 6.0))
    b = _facade(rng, 8.0, 16.0, lambda x: np.full_like(x, 9.0))
    out = _split([a, b], angle=angle)
    assert len(np.unique(out)) == 2
    house_a, house_b = out[:len(a)], out[len(a):]
    assert (house_a == house_a[0]).mean() > 0.97 and (house_b == house_b[0]).mean() > 0.97
    assert house_a[0] != house_b[0]
    # the cut lies within a bin of the true boundary
    wrong = np.concatenate([house_a != house_a[0], house_b != house_b[0]])
    x = np.concatenate([a, b])[:, 0]
    assert np.abs(x[wrong] - 8.0).max(initial=0.0) <= 0.5


def test_one_height_and_a_gable_stay_one_segment():
    rng = np.random.default_rng(2)
    flat = _facade(rng, 0.0, 16.0, lambda x: np.full_like(x, 7.0))
    assert len(np.unique(_split([flat]))) == 1
    for pitch_deg in (30.0, 45.0):  # a gable facing the street, ridge at x = 8
        rise = 8.0 * np.tan(np.radians(pitch_deg))
        gable = _facade(rng, 0.0, 16.0, lambda x, rise=rise: 6.0 + rise * (1.0 - np.abs(x - 8.0) / 8.0))
        assert len(np.unique(_split([gable]))) == 1, pitch_deg


def test_no_cut_near_the_segment_ends():
    rng = np.random.default_rng(3)
    wide = _facade(rng, 0.0, 12.0, lambda x: np.full_like(x, 6.0))
    narrow = _facade(rng, 12.0, 15.0, lambda x: np.full_like(x, 8.0))
    assert len(np.unique(_split([wide, narrow]))) == 1  # a 3 m piece would be dropped anyway
    out = _split([wide, narrow], min_end_m=2.5)
    assert len(np.unique(out)) == 2 and out[-1] != out[0]


def test_cuts_keep_min_gap_stronger_step_first():
    rng = np.random.default_rng(6)
    a = _facade(rng, 0.0, 8.0, lambda x: np.full_like(x, 6.0))
    b = _facade(rng, 8.0, 11.0, lambda x: np.full_like(x, 7.0))  # 3 m house: +1 m, then +3 m
    c = _facade(rng, 11.0, 19.0, lambda x: np.full_like(x, 10.0))
    out = _split([a, b, c])
    assert len(np.unique(out)) == 2
    assert out[len(a)] != out[-1] and out[len(a)] == out[0]  # the 3 m step (b | c) is cut, the 1 m one not
    out = _split([a, b, c], min_gap_m=2.5)
    assert len(np.unique(out)) == 3


def test_segments_are_split_separately_and_unlabelled_points_kept():
    rng = np.random.default_rng(4)
    flat = _facade(rng, 0.0, 16.0, lambda x: np.full_like(x, 7.0))
    a = _facade(rng, 30.0, 38.0, lambda x: np.full_like(x, 5.0))  # in line with the first segment
    b = _facade(rng, 38.0, 46.0, lambda x: np.full_like(x, 8.0))
    stray = _facade(rng, 20.0, 22.0, lambda x: np.full_like(x, 3.0))
    labels = np.concatenate([np.zeros(len(flat)), np.full(len(a) + len(b), 3),  # labels 1, 2 unused
                             np.full(len(stray), -1)]).astype(np.int32)
    out = _split([flat, a, b, stray], labels=labels)
    assert (out[labels == -1] == -1).all()
    assert (out[labels == 0] == 0).all()  # uncut: keeps its label
    assert set(out[labels == 3]) == {3, 4}  # the first piece keeps it, the other gets a new one
    off = _split([flat, a, b, stray], labels=labels, window_m=0.0)
    assert np.array_equal(off, labels)
    off = _split([flat, a, b, stray], labels=labels, top_step_m=0.0)
    assert np.array_equal(off, labels)


def test_setback_criterion():
    rng = np.random.default_rng(5)
    a = _facade(rng, 0.0, 8.0, lambda x: np.full_like(x, 6.0))
    b = _facade(rng, 8.0, 16.0, lambda x: np.full_like(x, 6.0))
    b[:, 1] += 0.4  # flush tops, the second house 0.4 m back
    assert len(np.unique(_split([a, b]))) == 1
    assert len(np.unique(_split([a, b], setback_m=0.2))) == 2


def _terrace_street(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Ground and two flush 10 m house fronts, 6 m and 9 m high, plus short side walls."""
    rng = np.random.default_rng(seed)
    parts, labels = [], []

    def rect(origin, u, v, lu, lv, label, per_m2):
        n = int(per_m2 * lu * lv)
        a, b = rng.uniform(0, lu, n), rng.uniform(0, lv, n)
        p = np.asarray(origin, float) + a[:, None] * np.asarray(u, float) + b[:, None] * np.asarray(v, float)
        parts.append(p + rng.normal(0, 0.02, p.shape))
        labels.append(np.full(n, label))

    ex, ey, ez = np.eye(3)
    rect((-10, -10, 0), ex, ey, 40, 15, -1, 40)  # road and pavement in front of the houses
    rect((0, 5, 0), ex, ez, 10, 6, 0, 150)
    rect((10, 5, 0), ex, ez, 10, 9, 1, 150)
    rect((0, 5, 0), ey, ez, 3, 6, 0, 150)
    rect((20, 5, 0), ey, ez, 3, 9, 1, 150)
    return np.concatenate(parts), np.concatenate(labels)


def test_stage_splits_a_terrace_of_two_houses():
    points, truth = _terrace_street()
    seg = RegionGrowing.from_config({"split_window_m": 2.0}).segment(points, NullObserver())
    fronts = []
    for house in (0, 1):
        lab = seg.point_labels[truth == house]
        best = np.bincount(lab[lab >= 0]).argmax()
        fronts.append(best)
        members = truth[seg.point_labels == best]
        assert (members == house).mean() >= 0.95  # a pure segment for each house
    assert fronts[0] != fronts[1]
    whole = RegionGrowing().segment(points, NullObserver())  # the split is off by default
    lab = whole.point_labels
    assert np.bincount(lab[(truth == 0) & (lab >= 0)]).argmax() == np.bincount(lab[(truth == 1) & (lab >= 0)]).argmax()
