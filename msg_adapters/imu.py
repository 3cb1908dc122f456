"""sensor_msgs/Imu (REP 145) <-> owl_core GyroSamples.

Only ``angular_velocity`` (rad/s, IMU frame = ``header.frame_id``) is used. REP 145 marks
a field as absent with covariance[0] == -1; such a message has no gyro data and is an
error. Non-finite rates are passed through: the engine's gyro buffer drops and counts them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from sensor_msgs.msg import Imu

from msg_adapters.errors import FieldError, LayoutError
from msg_adapters.stamps import make_header, stamps_to_ns
from owl_core.types import GyroSamples


def _check_present(msg: Any) -> None:
    if float(msg.angular_velocity_covariance[0]) == -1.0:
        raise FieldError(
            "imu.angular_velocity_covariance[0] is -1 (REP 145: no angular velocity in "
            f"this message, frame_id {msg.header.frame_id!r})"
        )


def imus_to_gyro(msgs: Sequence[Any]) -> GyroSamples:
    """N sensor_msgs/Imu -> GyroSamples with (N,) int64 stamps and (N, 3) rad/s rates.

    Order is kept as given (the gyro buffer rejects out-of-order samples itself).
    """
    for msg in msgs:
        _check_present(msg)
    secs = np.fromiter((m.header.stamp.sec for m in msgs), dtype=np.int64, count=len(msgs))
    nsecs = np.fromiter((m.header.stamp.nanosec for m in msgs), dtype=np.int64, count=len(msgs))
    rates = np.array(
        [(m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z) for m in msgs],
        dtype=np.float64,
    ).reshape(len(msgs), 3)
    return GyroSamples(stamp_ns=stamps_to_ns(secs, nsecs), angular_velocity=rates)


def imu_to_gyro(msg: Any) -> GyroSamples:
    """One sensor_msgs/Imu -> GyroSamples with N = 1."""
    return imus_to_gyro([msg])


def gyro_to_imus(samples: GyroSamples, frame_id: str) -> list[Any]:
    """GyroSamples -> N sensor_msgs/Imu (orientation and linear acceleration marked absent).

    Following REP 145, orientation_covariance[0] and linear_acceleration_covariance[0]
    are -1 (not provided); angular_velocity_covariance is all zero (unknown).
    """
    stamps = np.asarray(samples.stamp_ns)
    rates = np.asarray(samples.angular_velocity, dtype=np.float64)
    if stamps.ndim != 1 or rates.shape != (stamps.shape[0], 3):
        raise LayoutError(
            "GyroSamples must hold (N,) stamps and (N, 3) rates, got "
            f"{stamps.shape} and {rates.shape}"
        )
    out = []
    absent = [-1.0] + [0.0] * 8
    for stamp, (wx, wy, wz) in zip(stamps.tolist(), rates.tolist(), strict=True):
        msg = Imu(header=make_header(int(stamp), frame_id))
        msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = wx, wy, wz
        msg.orientation_covariance = list(absent)
        msg.linear_acceleration_covariance = list(absent)
        out.append(msg)
    return out
