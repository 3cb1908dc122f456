"""owl_core.time_offset: the offset-and-bias Kalman filter on synthetic leftover rotations
(the end-to-end test on a rendered bag is test_process::test_online_time_offset_...)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from owl_core.errors import InvalidInputError
from owl_core.time_offset import TimeOffsetFilter, TimeOffsetOptions

SIGMA = 1e-3  # rad/s, per-component noise of a frame's leftover rotation


def _frames(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) angular accelerations of a camera turning about three axes, rad/s^2."""
    t = np.arange(n) / 30.0
    return np.stack([2.5 * np.sin(2.8 * t), 1.5 * np.cos(4.4 * t), 0.5 * np.sin(3.5 * t)], 1)


def test_closed_loop_converges_to_the_true_offset_and_bias() -> None:
    """Derotating with the estimate (as the engine does once it is applied), the filter finds
    a 35 ms offset and a bias of 4 mrad/s within 3 of its own sigma."""
    rng = np.random.default_rng(3)
    true_offset, true_bias = 0.035, np.array([0.004, -0.002, 0.001])
    filt = TimeOffsetFilter(0.0, options=TimeOffsetOptions(inflation=1.0))
    used_offset, used_bias = 0.0, np.zeros(3)
    for j in _frames(150, rng):
        filt.predict(1 / 30)
        r = used_bias - true_bias + j * (true_offset - used_offset)
        r = r + rng.normal(scale=SIGMA, size=3)
        filt.update(r, np.eye(3) * SIGMA**2, np.zeros(3), j, used_offset, used_bias)
        used_offset, used_bias = filt.offset_s, filt.x[1:].copy()
    assert abs(filt.offset_s - true_offset) < 3 * filt.offset_sigma_s
    assert filt.offset_sigma_s < 2e-4
    np.testing.assert_allclose(filt.x[1:], true_bias, atol=3 * math.sqrt(filt.cov[1, 1]) + 1e-4)
    # the 99.9 % gate drops about one consistent frame in a thousand (here frame 3, whose
    # innovation has chi-square 20: the first frames cannot yet tell offset from bias)
    assert filt.updates + filt.rejected == 150 and filt.rejected <= 2


def test_a_constant_bias_alone_is_not_mistaken_for_an_offset() -> None:
    rng = np.random.default_rng(5)
    filt = TimeOffsetFilter(0.01)
    for j in _frames(150, rng):
        filt.predict(1 / 30)
        r = np.array([0.003, 0.0, -0.002]) + rng.normal(scale=SIGMA, size=3)
        filt.update(r, np.eye(3) * SIGMA**2, np.zeros(3), j, 0.01, np.zeros(3))
    assert abs(filt.offset_s - 0.01) < 3 * filt.offset_sigma_s
    np.testing.assert_allclose(filt.x[1:], [-0.003, 0.0, 0.002], atol=5e-4)


def test_gate_excitation_reset_and_bad_input() -> None:
    filt = TimeOffsetFilter(0.0)
    cov = np.eye(3) * SIGMA**2
    j = np.array([2.0, 0.0, 0.0])
    # no angular acceleration: no information about the offset
    assert not filt.update(np.zeros(3), cov, np.zeros(3), np.zeros(3), 0.0, np.zeros(3))
    # far outside the prior (50 ms x 2 rad/s^2 + 0.02 rad/s): gated out
    assert not filt.update(np.array([5.0, 0, 0]), cov, np.zeros(3), j, 0.0, np.zeros(3))
    assert filt.rejected == 1 and filt.offset_s == 0.0
    assert filt.update(np.array([0.02, 0, 0]), cov, np.zeros(3), j, 0.0, np.zeros(3))
    assert filt.offset_s > 0
    filt.reset()
    assert filt.offset_s == 0.0 and filt.offset_sigma_s == pytest.approx(0.05)
    with pytest.raises(InvalidInputError, match="need"):
        filt.update(np.zeros(2), cov, np.zeros(3), j, 0.0, np.zeros(3))
    with pytest.raises(InvalidInputError, match="inflation"):
        TimeOffsetOptions(inflation=0.5)
    with pytest.raises(InvalidInputError, match="initial_sigma_s"):
        TimeOffsetOptions(initial_sigma_s=0.0)
    with pytest.raises(InvalidInputError, match="dt_s"):
        filt.predict(-1.0)
