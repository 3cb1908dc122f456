"""Analytic camera/IMU trajectories and the synthetic IMU (REP 145) of the scenarios.

Frames
------
* World: x forward along the street, y left, z up; gravity ``(0, 0, -9.80665)`` m/s^2.
* Body = IMU frame ``imu_link``: x forward, y left, z up (REP 103/145). Its pose is the
  trajectory: position ``p(t)`` (world, metres) and ``R_wb(t) = Rz(yaw) Ry(pitch) Rx(roll)``.
* Camera optical frame ``camera_optical_frame`` (x right, y down, z forward) at the same
  point (no lever arm), rotated by the mount: ``R_bc`` maps camera vectors into the IMU
  frame, i.e. ``camera_to_imu_rotation_xyzw`` of the contract. The default mount looks
  along the IMU x axis: quaternion ``(-0.5, 0.5, -0.5, 0.5)``.

Every quantity is an exact analytic function of time (no numerical differentiation):
velocity and acceleration are the derivatives of the position functions, and the body
angular velocity of the ZYX Euler angles is ``w_b = Rx^T Ry^T (0, 0, yaw') +
Rx^T (0, pitch', 0) + (roll', 0, 0)``.

IMU model (:class:`ImuOptions`, :func:`synthesize_imu`): samples on a regular grid of IMU
stamps; IMU stamp = camera-clock time + ``time_offset_s`` for simultaneous events, so the
sample stamped ``s`` measures the truth at camera time ``s - offset``. Gyro = true
``w_b`` + bias (constant + random walk) + white noise; accelerometer = specific force
``R_wb^T (a_w - g_w)`` (reads +9.81 on z at rest) + bias + white noise.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bags.errors import ScenarioError
from owl_core.geometry import quat_xyzw_to_matrix, so3_exp

F64 = npt.NDArray[np.float64]

GRAVITY_W = np.array([0.0, 0.0, -9.80665])
#: The contract's example mount: camera looking along the IMU's x axis.
DEFAULT_CAMERA_TO_IMU_XYZW = (-0.5, 0.5, -0.5, 0.5)

#: position(t) -> (p, v, a), each (N, 3) world frame (m, m/s, m/s^2), t (N,) seconds.
PositionFn = Callable[[F64], tuple[F64, F64, F64]]
#: angles(t) -> (ypr, ypr_rate), each (N, 3): yaw, pitch, roll (rad) and rates (rad/s).
AnglesFn = Callable[[F64], tuple[F64, F64]]


def _rx(a: F64) -> F64:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack(
        [np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2
    )


def _ry(a: F64) -> F64:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack(
        [np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2
    )


def _rz(a: F64) -> F64:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


@dataclass(frozen=True)
class BodyState:
    """The exact state of the body (IMU) frame at N times.

    Attributes:
        t: (N,) float64 scenario time, seconds (camera clock, 0 = first image).
        position: (N, 3) world position, m. velocity: (N, 3) m/s. acceleration: (N, 3) m/s^2.
        R_wb: (N, 3, 3) body-to-world rotations.
        omega_b: (N, 3) angular velocity in the body (IMU) frame, rad/s.
    """

    t: F64
    position: F64
    velocity: F64
    acceleration: F64
    R_wb: F64
    omega_b: F64


@dataclass(frozen=True)
class Trajectory:
    """An analytic body trajectory: position and ZYX Euler angles as functions of time.

    Attributes:
        position_fn: t (N,) -> (p, v, a), each (N, 3), world frame.
        angles_fn: t (N,) -> ((yaw, pitch, roll), rates), each (N, 3), rad and rad/s.
    """

    position_fn: PositionFn
    angles_fn: AnglesFn

    def state(self, t: npt.ArrayLike) -> BodyState:
        """Exact state at times ``t`` (seconds, scalar or (N,)); arrays have N >= 1 rows."""
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
        p, v, a = self.position_fn(tt)
        ang, rate = self.angles_fn(tt)
        yaw, pitch, roll = ang[:, 0], ang[:, 1], ang[:, 2]
        rz, ry, rx = _rz(yaw), _ry(pitch), _rx(roll)
        r_wb = rz @ ry @ rx
        rxt = np.swapaxes(rx, -1, -2)
        ryt = np.swapaxes(ry, -1, -2)
        zero = np.zeros_like(yaw)
        w_yaw = np.stack([zero, zero, rate[:, 0]], -1)[..., None]
        w_pitch = np.stack([zero, rate[:, 1], zero], -1)[..., None]
        w_roll = np.stack([rate[:, 2], zero, zero], -1)
        omega = (rxt @ ryt @ w_yaw)[..., 0] + (rxt @ w_pitch)[..., 0] + w_roll
        return BodyState(tt, p, v, a, r_wb, omega)


# --- building blocks for trajectories (all exact derivatives) ------------------------------


def polynomial_path(
    p0: npt.ArrayLike, v0: npt.ArrayLike, a: npt.ArrayLike = (0, 0, 0)
) -> PositionFn:
    """p(t) = p0 + v0 t + a t^2 / 2 (world frame, metres)."""
    p0_, v0_, a_ = (np.asarray(x, dtype=np.float64) for x in (p0, v0, a))

    def fn(t: F64) -> tuple[F64, F64, F64]:
        tc = t[:, None]
        return (
            p0_ + v0_ * tc + 0.5 * a_ * tc**2,
            v0_ + a_ * tc,
            np.broadcast_to(a_, (t.size, 3)).copy(),
        )

    return fn


def scaled_path(fn: PositionFn, scale: float) -> PositionFn:
    """The same motion with positions, velocities and accelerations multiplied by ``scale``."""

    def out(t: F64) -> tuple[F64, F64, F64]:
        p, v, a = fn(t)
        return scale * p, scale * v, scale * a

    return out


def sine_angles(
    mean: npt.ArrayLike = (0, 0, 0),
    amplitude: npt.ArrayLike = (0, 0, 0),
    freq_hz: npt.ArrayLike = (0, 0, 0),
    phase: npt.ArrayLike = (0, 0, 0),
) -> AnglesFn:
    """yaw, pitch, roll = mean + amplitude sin(2 pi f t + phase) (rad), per axis."""
    m, amp, f, ph = (np.asarray(x, dtype=np.float64) for x in (mean, amplitude, freq_hz, phase))
    w = 2.0 * np.pi * f

    def fn(t: F64) -> tuple[F64, F64]:
        arg = w * t[:, None] + ph
        return m + amp * np.sin(arg), amp * w * np.cos(arg)

    return fn


def heading_following_angles(
    path: PositionFn, gain: float = 1.0, extra: AnglesFn | None = None
) -> AnglesFn:
    """yaw = gain * atan2(vy, vx) of the path (exact rate from v and a), plus ``extra``."""

    def fn(t: F64) -> tuple[F64, F64]:
        _, v, a = path(t)
        vx, vy, ax, ay = v[:, 0], v[:, 1], a[:, 0], a[:, 1]
        yaw = np.arctan2(vy, vx)
        yaw_rate = (vx * ay - vy * ax) / (vx * vx + vy * vy)
        ang = np.zeros((t.size, 3))
        rate = np.zeros((t.size, 3))
        ang[:, 0], rate[:, 0] = gain * yaw, gain * yaw_rate
        if extra is not None:
            ea, er = extra(t)
            ang, rate = ang + ea, rate + er
        return ang, rate

    return fn


# --- IMU --------------------------------------------------------------------------------


def _vec3(value: npt.ArrayLike, name: str) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        msg = f"{name} must be 3 finite numbers, got {value!r}"
        raise ScenarioError(msg)
    return (float(arr[0]), float(arr[1]), float(arr[2]))


@dataclass(frozen=True)
class ImuOptions:
    """The synthetic IMU.

    Attributes:
        rate_hz: sample rate, Hz (>= 200 recommended; > 0).
        gyro_noise: white noise of each gyro sample, standard deviation, rad/s.
        gyro_bias: constant gyro bias, IMU frame, rad/s (3 values).
        gyro_bias_walk: bias random walk, rad/s per sqrt(s) (each axis).
        accel_noise: white noise of each accelerometer sample, m/s^2.
        accel_bias: constant accelerometer bias, IMU frame, m/s^2.
        time_offset_s: IMU stamp = camera stamp + offset for simultaneous events, seconds.
        camera_to_imu_xyzw: rotation taking camera optical-frame vectors into the IMU frame.
        seed: seed of the noise and random walk.
    """

    rate_hz: float = 400.0
    gyro_noise: float = 0.001
    gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_bias_walk: float = 0.0
    accel_noise: float = 0.02
    accel_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    time_offset_s: float = 0.0
    camera_to_imu_xyzw: tuple[float, float, float, float] = DEFAULT_CAMERA_TO_IMU_XYZW
    seed: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            msg = f"IMU rate must be a positive number of Hz, got {self.rate_hz!r}"
            raise ScenarioError(msg)
        for name in ("gyro_noise", "gyro_bias_walk", "accel_noise"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                msg = f"{name} must be finite and >= 0, got {value!r}"
                raise ScenarioError(msg)
        if not math.isfinite(self.time_offset_s):
            msg = f"time offset must be finite seconds, got {self.time_offset_s!r}"
            raise ScenarioError(msg)
        object.__setattr__(self, "gyro_bias", _vec3(self.gyro_bias, "gyro_bias"))
        object.__setattr__(self, "accel_bias", _vec3(self.accel_bias, "accel_bias"))
        q = np.asarray(self.camera_to_imu_xyzw, dtype=np.float64).reshape(-1)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1) > 1e-6:
            msg = f"camera_to_imu_xyzw must be a unit quaternion (x, y, z, w), got {q.tolist()}"
            raise ScenarioError(msg)
        object.__setattr__(self, "camera_to_imu_xyzw", tuple(float(x) for x in q))

    @property
    def R_bc(self) -> F64:
        """(3, 3) rotation camera -> IMU (body) frame."""
        return quat_xyzw_to_matrix(np.asarray(self.camera_to_imu_xyzw))

    @property
    def time_offset_ns(self) -> int:
        """The offset in integer nanoseconds."""
        return round(self.time_offset_s * 1e9)


@dataclass(frozen=True)
class ImuData:
    """A run of IMU samples (IMU frame, IMU clock).

    Attributes:
        stamp_ns: (N,) int64 IMU stamps, ns.
        angular_velocity: (N, 3) measured angular velocity, rad/s.
        linear_acceleration: (N, 3) measured specific force, m/s^2 (REP 145).
        true_angular_velocity: (N, 3) noise- and bias-free angular velocity, rad/s.
        gyro_bias: (N, 3) the true gyro bias at each sample, rad/s.
    """

    stamp_ns: npt.NDArray[np.int64]
    angular_velocity: F64
    linear_acceleration: F64
    true_angular_velocity: F64
    gyro_bias: F64


def synthesize_imu(
    trajectory: Trajectory,
    options: ImuOptions,
    start_ns: int,
    t_begin_s: float,
    t_end_s: float,
) -> ImuData:
    """IMU samples whose truth spans camera times [t_begin_s, t_end_s] (seconds).

    Args:
        trajectory: the body trajectory (scenario time, seconds).
        options: noise, bias, rate, offset.
        start_ns: camera stamp of scenario time 0, ns.
        t_begin_s, t_end_s: camera-time interval the samples must cover, seconds.

    Returns:
        ImuData on the grid ``stamp = s0 + k * round(1e9 / rate_hz)`` (IMU clock).
    """
    period = round(1e9 / options.rate_hz)
    off = options.time_offset_ns
    first = start_ns + off + math.floor(t_begin_s * 1e9 / period) * period
    last = start_ns + off + math.ceil(t_end_s * 1e9 / period) * period
    stamps = np.arange(first, last + 1, period, dtype=np.int64)
    t = (stamps - off - start_ns).astype(np.float64) * 1e-9
    st = trajectory.state(t)
    rng = np.random.default_rng([0x1A0, options.seed & 0xFFFFFFFF])
    n = stamps.shape[0]
    walk = rng.normal(0.0, options.gyro_bias_walk * math.sqrt(period * 1e-9), (n, 3))
    walk[0] = 0.0
    bias = np.asarray(options.gyro_bias) + np.cumsum(walk, axis=0)
    gyro = st.omega_b + bias + rng.normal(0.0, options.gyro_noise, (n, 3))
    f_w = st.acceleration - GRAVITY_W
    f_b = np.einsum("nji,nj->ni", st.R_wb, f_w)
    accel = f_b + np.asarray(options.accel_bias) + rng.normal(0.0, options.accel_noise, (n, 3))
    return ImuData(stamps, gyro, accel, st.omega_b, bias)


# --- IMU models of real parts -------------------------------------------------------------


def imu_model(
    rate_hz: float,
    gyro_noise_density: float,
    gyro_bias_walk: float,
    accel_noise_density: float,
) -> ImuOptions:
    """An :class:`ImuOptions` from datasheet densities.

    Args:
        rate_hz: sample rate, Hz.
        gyro_noise_density: gyro white-noise density, rad/s/sqrt(Hz) (per-sample standard
            deviation = density * sqrt(rate)).
        gyro_bias_walk: gyro bias random walk, rad/s/sqrt(s).
        accel_noise_density: accelerometer noise density, m/s^2/sqrt(Hz).
    """
    root = math.sqrt(rate_hz)
    return ImuOptions(
        rate_hz=rate_hz,
        gyro_noise=gyro_noise_density * root,
        gyro_bias_walk=gyro_bias_walk,
        accel_noise=accel_noise_density * root,
    )


#: IMU models of real parts (densities from the datasheets / the datasets' calibrations):
#: ``adis16448``: Analog Devices ADIS16448 as in EuRoC MAV (kalibr values: gyro 1.6968e-4
#: rad/s/sqrt(Hz), bias random walk 1.9393e-5 rad/s^2/sqrt(Hz), accelerometer 2.0e-3),
#: 200 Hz. ``mems100`` / ``mems200`` / ``mems400``: a consumer MEMS IMU (Bosch BMI055-class
#: as in the RealSense D435i, phones: gyro 0.014 deg/s/sqrt(Hz) = 2.44e-4 rad/s/sqrt(Hz),
#: a bias random walk of 1e-4 rad/s/sqrt(s), accelerometer 150 ug/sqrt(Hz)) at 100, 200 and
#: 400 Hz.
IMU_MODELS: dict[str, ImuOptions] = {
    "adis16448": imu_model(200.0, 1.6968e-4, 1.9393e-5, 2.0e-3),
    **{
        f"mems{int(r)}": imu_model(r, math.radians(0.014), 1e-4, 150e-6 * 9.80665)
        for r in (100.0, 200.0, 400.0)
    },
}


# --- a car ----------------------------------------------------------------------------------


def car_trajectory(
    speed_fn: Callable[[F64], tuple[F64, F64]],
    yaw_fn: Callable[[F64], tuple[F64, F64, F64]],
    lever_m: float,
    p0: npt.ArrayLike = (0.0, 0.0, 0.0),
    t_range: tuple[float, float] = (-2.0, 62.0),
    dt: float = 1e-3,
) -> Trajectory:
    """A car without side slip: its rear axle moves along its own x axis at the speed
    ``speed_fn(t)``, its yaw is ``yaw_fn(t)``; the returned trajectory is the point
    ``lever_m`` ahead of the axle (where camera and IMU sit), with yaw = the car's.

    The camera velocity is exact: ``v = s (cos y, sin y, 0) + lever y' (-sin y, cos y, 0)``
    (in turns it points off the car's axis, by atan(lever y' / s)), and so is its
    acceleration; the axle position is integrated from the exact velocity (trapezoid rule on
    a ``dt`` grid over ``t_range``, then cubic Hermite interpolation with the exact
    velocity: position errors below 1e-6 m over a minute).

    Args:
        speed_fn: t (N,) -> (speed m/s, its rate m/s^2), each (N,).
        yaw_fn: t (N,) -> (yaw rad, yaw rate rad/s, yaw acceleration rad/s^2), each (N,).
        lever_m: camera ahead of the rear axle, metres.
        p0: axle position at t = 0, world, metres.
        t_range: times (s) the trajectory is defined on; outside, positions extrapolate.
        dt: integration step, s.
    """
    grid = np.arange(t_range[0], t_range[1] + dt, dt)
    s_g, _ = speed_fn(grid)
    y_g, _, _ = yaw_fn(grid)
    v_g = np.stack([s_g * np.cos(y_g), s_g * np.sin(y_g)], axis=1)
    steps = 0.5 * (v_g[1:] + v_g[:-1]) * dt
    p_g = np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
    k0 = int(np.argmin(np.abs(grid)))
    p_g = p_g - p_g[k0] + np.asarray(p0, dtype=np.float64)[:2] - v_g[k0] * grid[k0]
    z0 = float(np.asarray(p0, dtype=np.float64)[2])

    def position(t: F64) -> tuple[F64, F64, F64]:
        s, sd = speed_fn(t)
        yaw, yr, ya = yaw_fn(t)
        c, sn = np.cos(yaw), np.sin(yaw)
        # axle position: cubic Hermite between grid nodes with the exact velocity
        k = np.clip(np.floor((t - grid[0]) / dt).astype(np.int64), 0, grid.size - 2)
        u = (t - grid[k]) / dt
        h00, h10 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u
        h01, h11 = -2 * u**3 + 3 * u**2, u**3 - u**2
        axle = (
            h00[:, None] * p_g[k]
            + h10[:, None] * dt * v_g[k]
            + h01[:, None] * p_g[k + 1]
            + h11[:, None] * dt * v_g[k + 1]
        )
        fwd = np.stack([c, sn], axis=1)
        left = np.stack([-sn, c], axis=1)
        p2 = axle + lever_m * fwd
        v2 = s[:, None] * fwd + (lever_m * yr)[:, None] * left
        a2 = (
            sd[:, None] * fwd
            + (s * yr)[:, None] * left
            + (lever_m * ya)[:, None] * left
            - (lever_m * yr * yr)[:, None] * fwd
        )
        z = np.zeros((t.size, 1))
        return (
            np.concatenate([p2, z + z0], axis=1),
            np.concatenate([v2, z], axis=1),
            np.concatenate([a2, z], axis=1),
        )

    def angles(t: F64) -> tuple[F64, F64]:
        yaw, yr, _ = yaw_fn(t)
        ang = np.zeros((t.size, 3))
        rate = np.zeros((t.size, 3))
        ang[:, 0], rate[:, 0] = yaw, yr
        return ang, rate

    return Trajectory(position, angles)


def bump_yaw(
    start_s: float, duration_s: float, peak_rate: float
) -> Callable[[F64], tuple[F64, F64]]:
    """Yaw whose rate is zero, then rises and falls as a raised cosine (peak ``peak_rate``
    rad/s over ``duration_s`` from ``start_s``), then is zero again: a rotation that
    starts and stops. Returns angles(t) -> ((yaw, pitch, roll), rates)."""

    def fn(t: F64) -> tuple[F64, F64]:
        u = np.clip((t - start_s) / duration_s, 0.0, 1.0)
        inside = (t > start_s) & (t < start_s + duration_s)
        rate = np.where(inside, 0.5 * peak_rate * (1.0 - np.cos(2 * np.pi * u)), 0.0)
        yaw = 0.5 * peak_rate * duration_s * (u - np.sin(2 * np.pi * u) / (2 * np.pi))
        ang = np.zeros((t.size, 3))
        rates = np.zeros((t.size, 3))
        ang[:, 0], rates[:, 0] = yaw, rate
        return ang, rates

    return fn


def random_camera_to_imu(rng: np.random.Generator, max_tilt_deg: float = 25.0) -> F64:
    """A random camera-to-IMU rotation (3, 3) whose camera still looks at the scene.

    Any rotation about the IMU z axis (up), any roll about the optical axis, and a tilt
    of up to ``max_tilt_deg`` about a random axis, around :data:`DEFAULT_CAMERA_TO_IMU_XYZW`
    (for calibration tests: the images stay on the street, not on the sky).
    """
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)

    out: F64 = (
        so3_exp([0.0, 0.0, rng.uniform(-math.pi, math.pi)])
        @ so3_exp(axis * math.radians(rng.uniform(0.0, max_tilt_deg)))
        @ quat_xyzw_to_matrix(np.asarray(DEFAULT_CAMERA_TO_IMU_XYZW, dtype=np.float64))
        @ so3_exp([0.0, 0.0, rng.uniform(-math.pi, math.pi)])
    )
    return out
