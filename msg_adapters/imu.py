"""sensor_msgs/Imu (REP 145) <-> owl_core GyroSamples; the gyro-bias estimate <->
geometry_msgs/Vector3Stamped (``owl/gyro_bias``).

Only ``angular_velocity`` (rad/s, IMU frame = ``header.frame_id``) is used. REP 145 marks
a field as absent with covariance[0] == -1; such a message has no gyro data and is an
error. Non-finite rates are passed through: the engine's gyro buffer drops and counts them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
from geometry_msgs.msg import Vector3Stamped
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


def gyro_to_imus(
    samples: GyroSamples,
    frame_id: str,
    *,
    linear_acceleration: npt.ArrayLike | None = None,
    angular_velocity_covariance: npt.ArrayLike | None = None,
    linear_acceleration_covariance: npt.ArrayLike | None = None,
) -> list[Any]:
    """GyroSamples -> N sensor_msgs/Imu (orientation marked absent).

    Following REP 145, orientation_covariance[0] is -1 (not provided). Without
    ``linear_acceleration`` that field is marked absent too (covariance[0] = -1);
    ``angular_velocity_covariance`` defaults to all zero (unknown).

    Args:
        samples: (N,) stamps, ns, and (N, 3) rates, rad/s, IMU frame.
        frame_id: the IMU frame.
        linear_acceleration: (N, 3) specific force, m/s^2, IMU frame, or None.
        angular_velocity_covariance: (9,) row-major covariance, (rad/s)^2, or None.
        linear_acceleration_covariance: (9,) row-major covariance, (m/s^2)^2; used with
            ``linear_acceleration`` (default zero: unknown).
    """
    stamps = np.asarray(samples.stamp_ns)
    rates = np.asarray(samples.angular_velocity, dtype=np.float64)
    if stamps.ndim != 1 or rates.shape != (stamps.shape[0], 3):
        raise LayoutError(
            "GyroSamples must hold (N,) stamps and (N, 3) rates, got "
            f"{stamps.shape} and {rates.shape}"
        )
    absent = [-1.0] + [0.0] * 8
    accels = None
    acc_cov = absent
    if linear_acceleration is not None:
        accels = np.asarray(linear_acceleration, dtype=np.float64)
        if accels.shape != rates.shape:
            raise LayoutError(
                f"linear_acceleration must have shape {rates.shape}, got {accels.shape}"
            )
        acc_cov = _covariance(linear_acceleration_covariance, "linear_acceleration_covariance")
    gyro_cov = _covariance(angular_velocity_covariance, "angular_velocity_covariance")
    out = []
    for i, (stamp, (wx, wy, wz)) in enumerate(zip(stamps.tolist(), rates.tolist(), strict=True)):
        msg = Imu(header=make_header(int(stamp), frame_id))
        msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = wx, wy, wz
        msg.orientation_covariance = list(absent)
        msg.angular_velocity_covariance = list(gyro_cov)
        if accels is not None:
            a = msg.linear_acceleration
            a.x, a.y, a.z = (float(v) for v in accels[i])
        msg.linear_acceleration_covariance = list(acc_cov)
        out.append(msg)
    return out


def _covariance(value: npt.ArrayLike | None, name: str) -> list[float]:
    if value is None:
        return [0.0] * 9
    cov = np.asarray(value, dtype=np.float64).reshape(-1)
    if cov.shape != (9,):
        raise LayoutError(f"{name} must have 9 elements, got {cov.shape[0]}")
    return [float(v) for v in cov]


def gyro_bias_to_msg(bias: npt.ArrayLike, header: Any) -> Any:
    """(3,) finite gyro-bias estimate, rad/s, IMU frame -> geometry_msgs/Vector3Stamped
    (``owl/gyro_bias``) with the given header (stamp = the image's, frame = the IMU's)."""
    vec = np.asarray(bias, dtype=np.float64)
    if vec.shape != (3,):
        raise FieldError(f"gyro bias must have shape (3,), got {vec.shape}")
    if not np.isfinite(vec).all():
        raise FieldError(f"gyro bias must be finite, got {vec.tolist()}")
    msg = Vector3Stamped(header=header)
    msg.vector.x, msg.vector.y, msg.vector.z = (float(v) for v in vec)
    return msg


def msg_to_gyro_bias(msg: Any) -> npt.NDArray[np.float64]:
    """Vector3Stamped (``owl/gyro_bias``) -> (3,) float64 bias, rad/s, exactly as stored."""
    return np.array([msg.vector.x, msg.vector.y, msg.vector.z], dtype=np.float64)
