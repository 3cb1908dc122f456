"""Imu (REP 145) <-> GyroSamples: exact stamps, batching, absent angular velocity; the
gyro-bias Vector3Stamped."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_msgs.msg import Vector3Stamped
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Imu

from msg_adapters.errors import FieldError, LayoutError
from msg_adapters.imu import (
    gyro_bias_to_msg,
    gyro_to_imus,
    imu_to_gyro,
    imus_to_gyro,
    msg_to_gyro_bias,
)
from msg_adapters.stamps import make_header
from owl_core.types import GyroSamples


def _samples(n: int = 6) -> GyroSamples:
    rng = np.random.default_rng(1)
    # stamps straddling a second boundary and a large epoch: exact integer ns
    stamps = 1_700_000_000_999_999_000 + np.arange(n, dtype=np.int64) * 2_500_001
    return GyroSamples(stamp_ns=stamps, angular_velocity=rng.normal(0, 0.5, (n, 3)))


def test_round_trip_batch_exact_through_the_wire():
    samples = _samples()
    msgs = [deserialize_message(serialize_message(m), Imu) for m in gyro_to_imus(samples, "imu")]
    back = imus_to_gyro(msgs)
    assert back.stamp_ns.dtype == np.int64
    np.testing.assert_array_equal(back.stamp_ns, samples.stamp_ns)
    np.testing.assert_array_equal(back.angular_velocity, samples.angular_velocity)
    assert msgs[0].header.frame_id == "imu"
    assert msgs[0].orientation_covariance[0] == -1.0
    assert msgs[0].linear_acceleration_covariance[0] == -1.0


def test_single_message():
    msg = gyro_to_imus(_samples(1), "imu")[0]
    one = imu_to_gyro(msg)
    assert one.stamp_ns.shape == (1,) and one.angular_velocity.shape == (1, 3)
    assert one.stamp_ns[0] == 1_700_000_000_999_999_000


def test_empty_batch():
    out = imus_to_gyro([])
    assert out.stamp_ns.shape == (0,) and out.angular_velocity.shape == (0, 3)


def test_nan_rates_pass_through_for_the_gyro_buffer_to_count():
    msg = gyro_to_imus(_samples(1), "imu")[0]
    msg.angular_velocity.y = float("nan")
    assert np.isnan(imu_to_gyro(msg).angular_velocity[0, 1])


def test_absent_angular_velocity_is_an_error():
    msg = gyro_to_imus(_samples(1), "imu_link")[0]
    msg.angular_velocity_covariance[0] = -1.0
    with pytest.raises(FieldError, match=r"angular_velocity_covariance\[0\] is -1.*'imu_link'"):
        imu_to_gyro(msg)


def test_bad_samples_shape():
    bad = GyroSamples(stamp_ns=np.zeros(3, np.int64), angular_velocity=np.zeros((2, 3)))
    with pytest.raises(LayoutError, match=r"got \(3,\) and \(2, 3\)"):
        gyro_to_imus(bad, "imu")


def test_linear_acceleration_and_covariances_through_the_wire():
    samples = _samples(4)
    acc = np.random.default_rng(2).normal(0, 9.8, (4, 3))
    gyro_cov = np.diag([1e-6, 2e-6, 3e-6]).reshape(-1)
    acc_cov = np.diag([0.01, 0.02, 0.03]).reshape(-1)
    msgs = gyro_to_imus(
        samples,
        "imu",
        linear_acceleration=acc,
        angular_velocity_covariance=gyro_cov,
        linear_acceleration_covariance=acc_cov,
    )
    msgs = [deserialize_message(serialize_message(m), Imu) for m in msgs]
    got = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]
                    for m in msgs])  # fmt: skip
    np.testing.assert_array_equal(got, acc)
    np.testing.assert_array_equal(np.asarray(msgs[0].angular_velocity_covariance), gyro_cov)
    np.testing.assert_array_equal(np.asarray(msgs[3].linear_acceleration_covariance), acc_cov)
    assert msgs[0].orientation_covariance[0] == -1.0
    np.testing.assert_array_equal(imus_to_gyro(msgs).angular_velocity, samples.angular_velocity)
    with pytest.raises(LayoutError, match=r"linear_acceleration must have shape \(4, 3\)"):
        gyro_to_imus(samples, "imu", linear_acceleration=acc[:2])
    with pytest.raises(LayoutError, match="angular_velocity_covariance must have 9 elements"):
        gyro_to_imus(samples, "imu", angular_velocity_covariance=np.zeros(3))


def test_gyro_bias_round_trip_exact_and_non_finite_rejected():
    bias = np.array([0.004, -0.002, 1e-9])
    msg = gyro_bias_to_msg(bias, make_header(1_700_000_000_000_000_001, "imu_link"))
    back = deserialize_message(serialize_message(msg), Vector3Stamped)
    np.testing.assert_array_equal(msg_to_gyro_bias(back), bias)
    assert back.header.frame_id == "imu_link"
    assert back.header.stamp.nanosec == 1
    np.testing.assert_array_equal(msg_to_gyro_bias(gyro_bias_to_msg(np.zeros(3), msg.header)), 0)
    with pytest.raises(FieldError, match="gyro bias must be finite"):
        gyro_bias_to_msg([0.0, float("nan"), 0.0], msg.header)
    with pytest.raises(FieldError, match=r"shape \(3,\)"):
        gyro_bias_to_msg([0.0, 0.0], msg.header)
