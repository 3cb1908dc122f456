"""owl_core.heading_filter: the heading Kalman filters on inputs whose answer is known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from owl_core.errors import InvalidInputError
from owl_core.geometry import so3_exp
from owl_core.heading_filter import (
    HeadingFilter,
    HeadingFilterOptions,
    TwoModelHeading,
    filter_step,
    tangent_basis,
)

DT = 1.0 / 30.0
TAU = -2.0 * DT  # a 5-frame straight-line fit refers to its time centroid


def _run(flt, turn_rate, cam_rate, noise, n=90, seed=0):
    """Scene heading turning at ``turn_rate`` about the camera y axis, the camera yawing at
    ``cam_rate``; measurements at TAU with white angular noise ``noise`` (rad per axis).
    Returns per-frame (error of the output, error of the measurement against the truth at
    the image time), degrees."""
    rng = np.random.default_rng(seed)
    out, raw = [], []

    def world_h(s):
        return (
            so3_exp(np.array([0.0, turn_rate * s, 0.0]))
            @ np.array([0.3, 0.0, 1.0])
            / math.hypot(0.3, 1.0)
        )

    def r_wc(s):
        return so3_exp(np.array([0.0, cam_rate * s, 0.0]))

    for k in range(n):
        t = k * DT
        z = r_wc(t).T @ world_h(t + TAU)
        u1, u2 = tangent_basis(z)
        z = z + noise * (rng.standard_normal() * u1 + rng.standard_normal() * u2)
        z /= np.linalg.norm(z)
        stamps = np.array([round((t - j * DT) * 1e9) if k - j >= 0 else -1 for j in range(5)])
        rots = np.stack([r_wc(t).T @ r_wc(t - j * DT) for j in range(5)])
        sigma = max(noise, 1e-5) * math.sqrt(2.0)
        h, s = filter_step(flt, round(t * 1e9), z, TAU, sigma, stamps, rots)
        truth = r_wc(t).T @ world_h(t)
        out.append(math.degrees(math.acos(min(1.0, float(h @ truth)))))
        raw.append(math.degrees(math.acos(min(1.0, float(z @ truth)))))
        assert math.isfinite(s) and s > 0
    return np.array(out), np.array(raw)


def test_turning_path_lag_is_removed_and_the_rate_found():
    # 0.4 rad/s scene turn over tau = 67 ms: the measurement lags by 1.53 deg
    flt = HeadingFilter()
    out, raw = _run(flt, 0.4, 0.24, 0.0)
    assert np.median(raw) == pytest.approx(math.degrees(0.4 * 2 * DT), rel=1e-3)
    assert np.max(out[30:]) < 0.01
    assert float(np.linalg.norm(flt.rate)) == pytest.approx(0.4, rel=0.01)


def test_camera_rotation_alone_is_followed_exactly_by_the_gyro_prediction():
    # a straight path seen from a yawing camera: the heading moves in the camera frame by
    # the rotation only; noise-free measurements are reproduced to rounding
    for flt in (HeadingFilter(), TwoModelHeading()):
        out, raw = _run(flt, 0.0, 0.5, 0.0)
        assert np.max(raw) < 1e-5  # degrees; acos near 1 resolves ~1e-6 deg
        assert np.max(out) < 1e-5


def test_straight_model_averages_noise_instead_of_amplifying_it():
    # white noise of 0.1 deg per axis: over 60 frames the straight model averages it
    noise = math.radians(0.1)
    out, raw = _run(TwoModelHeading(), 0.0, 0.3, noise, n=120, seed=3)
    rms_out = math.sqrt(np.mean(out[60:] ** 2))
    rms_raw = math.sqrt(np.mean(raw[60:] ** 2))
    # the straight model has no process noise: from frame 60 on it is the mean of at least
    # 60 measurements, 1/sqrt(60) = 0.13 of one (the turning model's share adds a little)
    assert rms_out < 0.25 * rms_raw
    # the turning model alone follows the noise more closely (its rate takes some of it)
    out_t, _ = _run(HeadingFilter(), 0.0, 0.3, noise, n=120, seed=3)
    assert rms_out <= math.sqrt(np.mean(out_t[60:] ** 2))


def test_two_models_switch_to_the_turning_one_on_a_curve():
    flt = TwoModelHeading()
    out, _ = _run(flt, 0.4, 0.24, math.radians(0.02), n=90, seed=1)
    assert flt.weights[1] > 0.9
    assert np.median(out[30:]) < 0.1  # against a 1.53 deg lag without the rate


def test_gap_and_antipodal_measurement_restart_and_bad_input_is_refused():
    flt = HeadingFilter(HeadingFilterOptions(max_gap_s=0.2))
    flt.update(0, np.array([0.0, 0.0, 1.0]), 0.0, 0.01)
    flt.predict(int(0.3e9), np.eye(3))  # 0.3 s > max_gap_s
    assert flt.heading is None and flt.sigma_rad == math.inf
    flt.update(int(0.3e9), np.array([0.0, 0.0, 1.0]), 0.0, 0.01)
    flt.predict(int(0.33e9), np.eye(3))
    flt.update(int(0.33e9), np.array([0.0, 0.0, -1.0]), 0.0, 0.01)
    np.testing.assert_allclose(flt.heading, [0.0, 0.0, -1.0])
    with pytest.raises(InvalidInputError):
        flt.update(0, np.zeros(3), 0.0, 0.01)
    with pytest.raises(InvalidInputError):
        flt.update(0, np.array([0.0, 0.0, 1.0]), 0.1, 0.01)
    with pytest.raises(InvalidInputError):
        HeadingFilterOptions(inflation=0.5)


def test_constant_heading_model_is_the_mean_of_its_measurements():
    """No rate, no process noise: after n updates (camera still, tau = 0) the state is the
    normalised mean of the measurements, to second order in their spread (0.01 rad)."""
    flt = HeadingFilter(HeadingFilterOptions(accel_density=0.0, initial_rate_sigma=0.0))
    rng = np.random.default_rng(5)
    h0 = np.array([0.2, -0.1, 1.0]) / math.sqrt(1.05)
    u1, u2 = tangent_basis(h0)
    zs = []
    for k in range(50):
        z = h0 + 0.01 * (rng.standard_normal() * u1 + rng.standard_normal() * u2)
        zs.append(z / np.linalg.norm(z))
        if k:
            flt.predict(round(k * DT * 1e9), np.eye(3))
        flt.update(round(k * DT * 1e9), zs[-1], 0.0, 0.01)
        np.testing.assert_array_equal(flt.rate, 0.0)
    mean = np.mean(zs, axis=0)
    assert flt.heading is not None
    assert math.acos(min(1.0, float(flt.heading @ (mean / np.linalg.norm(mean))))) < 1e-4
    # its stated uncertainty is that of a mean of 50: sigma / sqrt(50) x sqrt(inflation)
    assert flt.sigma_rad == pytest.approx(0.01 * math.sqrt(3.0 / 50.0), rel=1e-6)
