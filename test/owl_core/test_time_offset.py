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
        used_offset, used_bias = filt.offset_s, filt.bias_camera.copy()
    assert abs(filt.offset_s - true_offset) < 3 * filt.offset_sigma_s
    assert filt.offset_sigma_s < 2e-4
    np.testing.assert_allclose(
        filt.bias_camera, true_bias, atol=3 * math.sqrt(filt.cov[1, 1]) + 1e-4
    )
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
    np.testing.assert_allclose(filt.bias_camera, [-0.003, 0.0, 0.002], atol=5e-4)


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


def _rates(n: int, axes: int) -> np.ndarray:
    """(n, 3) camera rotation rates, rad/s: turning about three axes, or about y only."""
    t = np.arange(n) / 30.0
    r = np.stack([0.5 * np.sin(2.8 * t), 0.8 * np.cos(1.9 * t), 0.3 * np.sin(3.5 * t)], 1)
    if axes == 1:
        r[:, [0, 2]] = 0.0
    return r


def _skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


@pytest.mark.parametrize("axes", [3, 1])
def test_the_rotation_error_is_found_along_the_axes_the_motion_determines(axes: int) -> None:
    """Leftovers of a rotation error ``phi`` (the leftover ``M phi``, ``M = [Omega]x`` to
    first order) with a bias and an offset: turning about three axes, ``phi``, the offset
    and the bias are each found within 3 of their sigma; about one axis (y), the component
    of ``phi`` along it keeps its prior sigma (not determined) while the other two are."""
    rng = np.random.default_rng(7)
    phi = np.radians([2.0, -3.0, 1.5])
    true_offset, true_bias = 0.012, np.array([0.003, -0.001, 0.002])
    filt = TimeOffsetFilter(0.0, options=TimeOffsetOptions(inflation=1.0))
    for j, w in zip(_frames(150, rng), _rates(150, axes), strict=True):
        filt.predict(1 / 30)
        m = _skew(w)
        r = -true_bias + j * true_offset + m @ phi + rng.normal(scale=SIGMA, size=3)
        filt.update(r, np.eye(3) * SIGMA**2, np.zeros(3), j, 0.0, np.zeros(3), m)
    sigma = np.sqrt(np.diag(filt.misalignment_cov))
    assert abs(filt.offset_s - true_offset) < 3 * filt.offset_sigma_s
    np.testing.assert_array_less(
        np.abs(filt.bias_camera - true_bias), 3 * np.sqrt(np.diag(filt.cov)[1:4]) + 1e-5
    )
    if axes == 3:
        np.testing.assert_array_less(np.abs(filt.misalignment - phi), 3 * sigma)
        assert np.all(sigma < np.radians(0.1))
    else:
        assert sigma[1] == pytest.approx(TimeOffsetOptions().misalignment_sigma, rel=0.05)
        np.testing.assert_array_less(np.abs(filt.misalignment - phi)[[0, 2]], 3 * sigma[[0, 2]])
        assert np.all(sigma[[0, 2]] < np.radians(0.1))
    snap = filt.snapshot()
    assert snap.offset_s == filt.offset_s and snap.updates == filt.updates == 150
    np.testing.assert_array_equal(snap.misalignment, filt.misalignment)


def test_without_angular_acceleration_the_rotation_error_still_updates() -> None:
    """A steady turn carries no offset information, but ``M`` still informs ``phi`` (and
    the bias); the offset does not move, not even through its correlations."""
    filt = TimeOffsetFilter(0.0)
    cov = np.eye(3) * SIGMA**2
    m = _skew(np.array([0.0, 0.5, 0.0]))
    assert filt.update(np.zeros(3), cov, np.zeros(3), np.zeros(3), 0.0, np.zeros(3), m)
    assert filt.offset_sigma_s == pytest.approx(0.05)  # the offset untouched
    assert np.sqrt(filt.misalignment_cov[0, 0]) < 0.1  # phi_x informed (with the bias)
    # once an excited frame has correlated the offset with the bias, a frame without
    # angular acceleration still leaves the offset where it is (a consider update)
    j = np.array([2.0, 0.0, 0.0])
    assert filt.update(np.array([0.01, 0, 0]), cov, np.zeros(3), j, 0.0, np.zeros(3), m)
    offset, sigma = filt.offset_s, filt.offset_sigma_s
    assert offset != 0.0 and filt.cov[0, 1] != 0.0
    assert filt.update(np.array([0.004, 0, 0]), cov, np.zeros(3), np.zeros(3), 0.0, np.zeros(3), m)
    assert filt.offset_s == offset and filt.offset_sigma_s == pytest.approx(sigma, rel=1e-12)
    with pytest.raises(InvalidInputError, match="misalignment jacobian"):
        filt.update(np.zeros(3), cov, np.zeros(3), np.zeros(3), 0.0, np.zeros(3), np.eye(2))
    with pytest.raises(InvalidInputError, match="misalignment_sigma"):
        TimeOffsetOptions(misalignment_sigma=0.0)
