"""Drift knobs of the generator: the signed scale trend (``scale_drift_signed``)."""

from __future__ import annotations

import numpy as np
import pytest

from toolkit.errors import CrossviewError


def _straight_track(n: int = 401, step_m: float = 2.0):
    centres = np.column_stack([np.arange(n) * step_m, np.zeros(n), np.full(n, 2.0)])
    fwd = np.tile([1.0, 0.0, 0.0], (n, 1))
    rgt = np.tile([0.0, -1.0, 0.0], (n, 1))
    R = np.stack([rgt, np.cross(fwd, rgt), fwd], axis=2)
    return centres, R, np.arange(n) * step_m


def _scale(**knobs) -> tuple[np.ndarray, np.ndarray]:
    from toolkit.synth.config import config_for
    from toolkit.synth.drift import make_drift

    cfg = config_for("tiny", scale_walk=0.0, heading_walk_deg=0, pitch_walk_deg=0, roll_walk_deg=0, **knobs)
    d = make_drift(*_straight_track(), cfg, np.random.default_rng(7))
    return d.drift_scale, d.global_rotation


@pytest.mark.parametrize("trend", [-0.03, -0.01, 0.02])
def test_signed_scale_drift_is_the_trend_as_given(trend):
    scale, _ = _scale(scale_drift=trend, scale_drift_signed=True)
    assert scale[0] == 1.0
    assert scale[-1] == pytest.approx(np.exp(trend), rel=1e-9)
    assert np.all(np.diff(scale) * np.sign(trend) > 0)  # monotonic along the route


def test_signed_drift_draws_the_same_random_numbers():
    """The sign is still drawn: the global transform (drawn after it) does not move."""
    s_signed, g_signed = _scale(scale_drift=0.02, scale_drift_signed=True)
    s_random, g_random = _scale(scale_drift=0.02)
    assert np.array_equal(g_signed, g_random)
    assert abs(np.log(s_random[-1])) == pytest.approx(0.02, rel=1e-9)  # |trend| kept, sign random


def test_negative_scale_drift_needs_the_signed_flag():
    from toolkit.synth.config import config_for

    with pytest.raises(CrossviewError, match="scale_drift_signed") as exc:
        config_for("tiny", scale_drift=-0.02)
    assert "\n" not in str(exc.value)
    assert config_for("tiny", scale_drift=-0.02, scale_drift_signed=True).scale_drift == -0.02
    with pytest.raises(CrossviewError, match="scale_drift"):
        config_for("tiny", scale_drift=-0.6, scale_drift_signed=True)
