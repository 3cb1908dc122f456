"""owl_core.calibration: the estimators on exact scenario rotations (no rendering).

The rendered end-to-end cases (images -> tracks -> estimate) are in
test/owl_ros/test_calibrate.py, through the owl_calibrate tool.
"""

from __future__ import annotations

import math
from dataclasses import replace
from itertools import pairwise

import cv2
import numpy as np
import pytest

from bags.sim import scenarios
from bags.sim.scenarios import SimOptions
from bags.sim.sensors import ImuOptions, random_camera_to_imu
from owl_core import calibration as cal
from owl_core.geometry import matrix_to_quat_xyzw, quat_xyzw_to_matrix, so3_exp, so3_log

SMALL = SimOptions(seconds=3.0, rate_hz=30.0, width=320, height=240)


def exact_intervals(sim: scenarios.Simulation, sigma: float, seed: int) -> cal.IntervalRotations:
    """The true camera rotation increments between frames, plus white noise of ``sigma``."""
    stamps = sim.frame_stamps_ns
    theta = np.array([-so3_log(sim.relative_rotation(a, b)) for a, b in pairwise(stamps)])
    theta += np.random.default_rng(seed).normal(scale=sigma, size=theta.shape)
    k = theta.shape[0]
    return cal.IntervalRotations(
        stamps[:-1].copy(),
        stamps[1:].copy(),
        theta,
        np.full(k, sigma),
        np.full(k, 200, dtype=np.int64),
        np.zeros(k, dtype=bool),
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_rotation_offset_and_bias(seed: int) -> None:
    rng = np.random.default_rng(seed)
    r = random_camera_to_imu(rng)
    offset = float(rng.uniform(-0.05, 0.05))
    bias = tuple(rng.uniform(-0.02, 0.02, 3))
    imu = ImuOptions(
        camera_to_imu_xyzw=tuple(matrix_to_quat_xyzw(r)), time_offset_s=offset, gyro_bias=bias
    )
    sim = scenarios.get("rotation_only").simulate(replace(SMALL, imu=imu, seed=seed))
    # 5e-5 rad per interval: about what 200 tracked features at 0.15 px give at 320 px
    rot = exact_intervals(sim, 5e-5, seed)
    res = cal.calibrate(rot, sim.gyro_samples(), cal.CalibrationOptions(bootstrap=10))
    err = math.degrees(float(np.linalg.norm(so3_log(res.camera_to_imu @ r.T))))
    assert err < 0.05
    assert abs(res.time_offset_s - offset) < 0.5e-3
    np.testing.assert_allclose(res.gyro_bias, bias, atol=5e-4)
    # the uncertainties are of the size of the errors (not zero, not huge)
    assert 0 < res.time_offset_sigma_s < 1e-3
    assert np.all((res.rotation_sigma_rad > 0) & (res.rotation_sigma_rad < math.radians(0.1)))
    assert 0.5 < res.residual_rms < 2.0
    np.testing.assert_allclose(
        quat_xyzw_to_matrix(res.camera_to_imu_xyzw), res.camera_to_imu, atol=1e-12
    )


def test_offset_search_is_independent_of_the_rotation() -> None:
    """The magnitude search finds the offset before any rotation is known."""
    imu = ImuOptions(time_offset_s=-0.037, camera_to_imu_xyzw=(0.3, -0.5, 0.1, math.sqrt(0.65)))
    sim = scenarios.get("rotation_only").simulate(replace(SMALL, imu=imu))
    rot = exact_intervals(sim, 5e-5, 0)
    best, grid, cost = cal.search_offset(rot, sim.gyro_samples(), 0.2)
    assert abs(best + 0.037) < 1e-3
    assert grid[0] == pytest.approx(-0.2) and cost.shape == grid.shape


def test_one_axis_is_refused_with_what_to_record() -> None:
    sim = scenarios.get("pan_only").simulate(SMALL)
    rot = exact_intervals(sim, 5e-5, 0)
    with pytest.raises(cal.NotExcitedError, match=r"one axis only.*tilt") as info:
        cal.calibrate(rot, sim.gyro_samples())
    assert "\n" not in str(info.value)
    assert info.value.rms_rates[0] > 0.3 and info.value.rms_rates[1] < 0.01
    # the pan is about the camera's y axis (down): the dominant principal axis
    assert abs(info.value.axes[0][1]) > 0.99


def test_rotation_from_bearings_ignores_outliers() -> None:
    rng = np.random.default_rng(4)
    e0 = rng.normal(size=(200, 3)) + np.array([0.0, 0.0, 3.0])
    e0 /= np.linalg.norm(e0, axis=1, keepdims=True)
    true = so3_exp([0.01, -0.02, 0.005])
    e1 = e0 @ true.T + rng.normal(scale=1e-4, size=e0.shape)
    e1[:40] = rng.normal(size=(40, 3))  # 20 % garbage
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    rot, inliers, rms = cal.rotation_from_bearings(e0, e1, 1e-3, np.random.default_rng(0))
    assert np.linalg.norm(so3_log(rot @ true.T)) < 3e-5
    assert inliers[40:].all() and not inliers[:40].any()
    assert rms < 3e-4


def test_bad_input_is_named() -> None:
    with pytest.raises(ValueError, match="max_offset_s"):
        cal.CalibrationOptions(max_offset_s=0.0)
    sim = scenarios.get("rotation_only").simulate(replace(SMALL, seconds=0.3))
    rot = exact_intervals(sim, 5e-5, 0)
    with pytest.raises(cal.CalibrationError, match="only 9 frame intervals"):
        cal.calibrate(rot, sim.gyro_samples())


@pytest.mark.parametrize("seed", range(6))
def test_recover_pose_equals_opencv(seed: int) -> None:
    # Points from 1 to 400 baselines away (beyond the 50-baseline cut), pixel noise, 15 %
    # outliers and a RANSAC mask: the cheirality check gives OpenCV's pose and mask exactly.
    rng = np.random.default_rng(seed)
    n = 150
    rot = so3_exp(rng.normal(scale=0.05, size=3))
    t = rng.normal(size=3)
    t /= np.linalg.norm(t)
    depth = np.exp(rng.uniform(0.0, np.log(400.0), n))
    x = np.concatenate([rng.uniform(-0.5, 0.5, (n, 2)), np.ones((n, 1))], axis=1) * depth[:, None]
    y = x @ rot.T + t
    p0 = x[:, :2] / x[:, 2:]
    p1 = y[:, :2] / y[:, 2:] + rng.normal(scale=1e-3, size=(n, 2))
    p1[: n // 7] = rng.uniform(-0.5, 0.5, (n // 7, 2))
    e_mat, mask = cv2.findEssentialMat(
        p0, p1, focal=1.0, pp=(0.0, 0.0), method=cv2.RANSAC, prob=0.999, threshold=2e-3
    )
    count_cv, rot_cv, t_cv, mask_cv = cv2.recoverPose(e_mat, p0, p1, mask=mask.copy())
    count, rot_ours, t_ours, good = cal._recover_pose(e_mat, p0, p1, mask.reshape(-1) > 0)
    assert count == count_cv > 20
    np.testing.assert_array_equal(rot_ours, rot_cv)
    np.testing.assert_array_equal(t_ours, t_cv.reshape(3))
    np.testing.assert_array_equal(good, mask_cv.reshape(-1) > 0)
