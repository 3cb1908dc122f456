"""owl_core.speed_filter: the log-speed Kalman filters on inputs whose answer is known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from owl_core.errors import InvalidInputError
from owl_core.speed_filter import (
    SpeedChangeFilter,
    SpeedFilterOptions,
    TwoModelSpeed,
    TwoModelSpeedOptions,
)

DT = 1.0 / 30.0
DT_NS = round(DT * 1e9)
TAU = -2.0 * DT  # the fits' reference time, 67 ms before the image


def _feed(flt, log_speed, n, noise=0.0, seed=0, missing=()):
    """Feed ``n`` frames of the increments of ``log_speed(t)`` between reference times
    (``t + TAU``), each frame's reference scale off by a white error of 1-sigma ``noise``
    (the increments carry ``e_(k-1) - e_k``); frames in ``missing`` have no increment.
    Returns the per-frame (stamp s, filtered rate, log_change(TAU))."""
    rng = np.random.default_rng(seed)
    e_prev = rng.normal(0.0, noise) if noise else 0.0
    out = []
    for k in range(n):
        t = k * DT
        e = rng.normal(0.0, noise) if noise else 0.0
        inc = log_speed(t + TAU) - log_speed(t - DT + TAU) + e_prev - e
        e_prev = e
        flt.step(k * DT_NS, None if k in missing or k == 0 else inc, DT, TAU)
        out.append((t, flt.rate, float(flt.log_change(TAU))))
    return out


def test_constant_rate_is_tracked_exactly() -> None:
    # l = 0.4 t: the speed grows by 40 %/s
    flt = SpeedChangeFilter()
    out = _feed(flt, lambda t: 0.4 * t, 60)
    _, rate, lc = out[-1]
    assert rate == pytest.approx(0.4, abs=1e-3)
    assert lc == pytest.approx(0.4 * TAU, abs=1e-4)
    assert flt.rate_of_rate == pytest.approx(0.0, abs=0.02)


def test_accelerating_camera_log_change_converges() -> None:
    # l = ln(1 + 2 t) (1 m/s accelerating at 2 m/s^2): s = 2 / (1 + 2 t), ds/dt = -s^2,
    # and the jerk 2 s^3 the model treats as noise: the estimate lags it by a relative
    # error that shrinks with s (measured 2.3 % at 1 s, 0.4 % at 2.8 s)
    flt = SpeedChangeFilter()
    out = _feed(flt, lambda t: math.log1p(2.0 * t), 90)
    rel = []
    for t, rate, lc in out[30:]:
        true_lc = math.log1p(2.0 * (t + TAU)) - math.log1p(2.0 * t)
        rel.append(abs(lc - true_lc) / abs(true_lc))
        assert rate == pytest.approx(2.0 / (1.0 + 2.0 * t), rel=0.04)
    assert max(rel) < 0.04
    assert rel[-1] < 0.01


def test_missing_increments_restart_the_chain_without_a_jump() -> None:
    flt = SpeedChangeFilter()
    out = _feed(flt, lambda t: 0.3 * t, 60, missing=(20, 21, 40))
    assert out[-1][1] == pytest.approx(0.3, abs=2e-3)
    # a frame without an increment predicts; the rate does not jump
    assert abs(out[20][1] - out[19][1]) < 1e-3


def test_steady_model_keeps_a_noisy_constant_speed_at_rate_zero() -> None:
    # sideways-like scale errors: 0.3 % per frame, the speed constant
    two = TwoModelSpeed()
    one = SpeedChangeFilter(TwoModelSpeedOptions().changing)
    out_two = _feed(two, lambda t: 0.0, 90, noise=0.003, seed=3)
    out_one = _feed(one, lambda t: 0.0, 90, noise=0.003, seed=3)
    assert two.weights[0] > 0.9
    lc_two = np.array([lc for _, _, lc in out_two[30:]])
    lc_one = np.array([lc for _, _, lc in out_one[30:]])
    # the changing model alone turns the noise into a rate; the pair does not
    assert np.sqrt(np.mean(lc_two**2)) < 0.5 * np.sqrt(np.mean(lc_one**2))
    assert np.max(np.abs(lc_two)) < 0.003


def test_pair_follows_an_acceleration() -> None:
    two = TwoModelSpeed()
    out = _feed(two, lambda t: math.log1p(2.0 * t), 90, noise=0.0005, seed=1)
    assert two.weights[1] > 0.99
    t, rate, _ = out[-1]
    assert rate == pytest.approx(2.0 / (1.0 + 2.0 * t), rel=0.05)


def test_increment_is_clamped() -> None:
    opts = SpeedFilterOptions(max_rate=1.0)
    broken, clamped = SpeedChangeFilter(opts), SpeedChangeFilter(opts)
    for flt, inc in ((broken, 5.0), (clamped, 1.0 * DT)):  # 150 /s against the 1 /s clamp
        flt.step(0, None, DT, TAU)
        flt.step(DT_NS, inc, DT, TAU)
    assert broken.rate == clamped.rate
    assert 0.0 < broken.rate <= 1.0


def test_reset_and_invalid_input() -> None:
    flt = SpeedChangeFilter()
    _feed(flt, lambda t: 0.5 * t, 30)
    flt.reset()
    assert flt.rate == 0.0 and flt.rate_sigma == SpeedFilterOptions().rate_sigma
    flt.step(10 * DT_NS, None, DT, TAU)
    with pytest.raises(InvalidInputError, match="went back"):
        flt.step(5 * DT_NS, 0.01, DT, TAU)
    with pytest.raises(InvalidInputError, match="log_sigma"):
        SpeedFilterOptions(log_sigma=0.0)
    with pytest.raises(InvalidInputError, match="jerk_density"):
        SpeedFilterOptions(jerk_density=-1.0)
    with pytest.raises(InvalidInputError, match="memory"):
        TwoModelSpeedOptions(memory=1.0)
