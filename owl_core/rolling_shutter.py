"""Rolling shutter: each image row seen at its own time, and what the engine does about it.

Convention
----------
A rolling-shutter camera reads its rows one after the other. With ``T`` the readout time
(row 0 to the row after the last, i.e. image height x line time) and ``t_frame`` the image
stamp, the row at pixel coordinate ``v`` (row centres at integer ``v``, as OpenCV) is seen
at::

    t_row(v) = t_frame + (v / height) * T

so the stamp is the time of row 0. Drivers that stamp the start of the first row's
exposure give row 0's exposure start; the exposure midpoint is half an exposure later, a
constant that ``imu_time_offset`` absorbs (``owl_calibrate`` measures it). ``T = 0`` is a
global shutter.

What the engine does with ``T > 0`` (:class:`owl_core.engine.OwlEngine`):

- every tracked position gets its own time ``t_row(v)`` (its pixel row in its frame);
- the gyro rotation brings each position from *its* time to the camera orientation at the
  current image stamp (:class:`ReadoutRotations`: exact rotations at ``M + 1`` row times per
  frame, with a constant rate between them: ``T / M`` is a few milliseconds, over which
  the change of the rate contributes below 1e-5 rad at 10 rad/s^2);
- the bearing-vs-time fit of each track uses those times (:func:`fit_timed`); its bearing
  is referred to the same time as a global-shutter fit (the time centroid of the track's
  frame stamps), so neighbouring tracks in other rows still refer to one time, while its
  rate (the slope) belongs to the centroid of the entries' own times, a few milliseconds
  later: the range shrinks meanwhile (by L x that lag, about 1 % here), so each point is
  carried to the stamp from the time of its rate;
- the current bearing is moved from its row time back to the stamp along the fitted rate
  (:func:`bearings_at_stamp`): every output (bearings, points, r/|t|, L, omega, heading) is
  a snapshot at the image stamp in the camera frame at that stamp; the pixel ``u v`` stays
  where the feature was seen;
- the tracker's gyro prediction maps a feature from its row time in the previous frame to
  its (predicted) row time in the current one.

The gyro must cover up to ``t_frame + T`` (the last row), so a frame waits for the IMU that
much longer.

Units: seconds, radians, pixels; stamps in integer nanoseconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from owl_core.errors import InvalidInputError
from owl_core.geometry import so3_exp, so3_log
from owl_core.gyro import GyroBuffer
from owl_core.motion import row_norms

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

__all__ = [
    "READOUT_STEPS",
    "ReadoutRotations",
    "bearings_at_stamp",
    "fit_timed",
    "readout_rotations",
    "row_times",
]

#: Row times per frame with an exact gyro rotation (M): the rotation between two of them
#: (readout / M apart) is taken at a constant rate.
READOUT_STEPS = 8


@dataclass(frozen=True)
class ReadoutRotations:
    """Rotations from row times of K frames to the camera orientation at one stamp.

    Attributes:
        rotations: (K, M + 1, 3, 3) ``R_{stamp <- s_k + j T / M}``: takes a bearing seen at
            row fraction ``j / M`` of frame k (frame stamp ``s_k``) into the camera frame at
            ``stamp``.
        steps: (K, M, 3) rotation vectors of ``R_{t_j <- t_{j+1}}`` (from one grid time to
            the one before it), rad.
    """

    rotations: FloatArray
    steps: FloatArray

    def _at(self, frame: npt.ArrayLike, fraction: FloatArray) -> FloatArray:
        """(E, 3, 3) ``R_{stamp <- row time}`` for frames (E,) int and row fractions (E,)."""
        m = self.steps.shape[1]
        x = np.clip(np.nan_to_num(fraction, nan=0.0), 0.0, 1.0) * m
        j = np.minimum(x.astype(np.int64), m - 1)
        k = np.asarray(frame, dtype=np.int64)
        partial = so3_exp((x - j)[:, None] * self.steps[k, j])
        out: FloatArray = self.rotations[k, j] @ partial
        return out

    def to_stamp(
        self, frame: npt.ArrayLike, fraction: FloatArray, bearings: FloatArray
    ) -> FloatArray:
        """Bearings (E, 3) seen at row fraction ``fraction`` (E,) of frame ``frame`` (E,) or
        a scalar index, rotated into the camera frame at the stamp: (E, 3)."""
        k = np.broadcast_to(np.asarray(frame, dtype=np.int64), fraction.shape)
        out: FloatArray = np.einsum("eij,ej->ei", self._at(k, fraction), bearings)
        return out

    def from_stamp(
        self, frame: npt.ArrayLike, fraction: FloatArray, bearings: FloatArray
    ) -> FloatArray:
        """Inverse of :meth:`to_stamp`: bearings (E, 3) in the camera frame at the stamp,
        into the camera frame at row fraction ``fraction`` (E,) of frame ``frame``."""
        k = np.broadcast_to(np.asarray(frame, dtype=np.int64), fraction.shape)
        out: FloatArray = np.einsum("eji,ej->ei", self._at(k, fraction), bearings)
        return out


def readout_rotations(
    gyro: GyroBuffer,
    frame_stamps_ns: npt.ArrayLike,
    stamp_ns: int,
    readout_ns: int,
    bias_imu: npt.ArrayLike,
    steps: int = READOUT_STEPS,
) -> ReadoutRotations:
    """Exact gyro rotations from ``steps + 1`` row times of each frame to ``stamp_ns``.

    Args:
        gyro: the gyro buffer; it must cover ``[min(frame_stamps_ns), max(frame_stamps_ns,
            stamp_ns) + readout_ns]``.
        frame_stamps_ns: (K,) int64 frame stamps (row 0 times), ns.
        stamp_ns: the stamp whose camera orientation the rotations lead to, ns.
        readout_ns: readout time T, ns (> 0).
        bias_imu: (3,) gyro bias removed from the rates, IMU frame, rad/s.
        steps: M, row-time intervals per frame (>= 1).

    Returns:
        :class:`ReadoutRotations` with K frames.

    Raises:
        InvalidInputError: readout or steps not positive.
        TimeError: the gyro does not cover the interval.
    """
    if readout_ns <= 0 or steps < 1:
        raise InvalidInputError(
            f"readout_ns and steps must be positive, got {readout_ns} and {steps}"
        )
    starts = np.asarray(frame_stamps_ns, dtype=np.int64).reshape(-1)
    k = starts.shape[0]
    offsets = np.round(np.arange(steps + 1) * (readout_ns / steps)).astype(np.int64)
    times = (starts[:, None] + offsets[None, :]).reshape(-1)
    end = max(int(starts.max()), int(stamp_ns)) + int(readout_ns)
    to_end = gyro.relative_rotations(times, end, bias_imu)  # R_{end <- t}
    end_from_stamp = gyro.relative_rotation(int(stamp_ns), end, bias_imu)  # R_{end <- stamp}
    rotations = (end_from_stamp.T @ to_end).reshape(k, steps + 1, 3, 3)
    between = np.swapaxes(rotations[:, :-1], -1, -2) @ rotations[:, 1:]  # R_{t_j <- t_j+1}
    return ReadoutRotations(rotations, so3_log(between))


def row_times(
    rows_px: FloatArray, frame_tau_s: FloatArray, height: int, readout_s: float
) -> FloatArray:
    """Time of each tracked position relative to the current stamp, s.

    Args:
        rows_px: (N, W) pixel row v of each position (NaN where none).
        frame_tau_s: (W,) frame stamp of each column minus the current stamp, s.
        height: image height, px.
        readout_s: readout time T, s.

    Returns:
        (N, W) ``frame_tau + (v / height) T`` (NaN rows count as row 0).
    """
    fraction = np.nan_to_num(rows_px, nan=0.0) / float(height)
    out: FloatArray = frame_tau_s[None, :] + fraction * readout_s
    return out


def fit_timed(
    bearings: FloatArray,
    tau_s: FloatArray,
    mask: BoolArray,
    order: int,
    frame_tau_s: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, BoolArray, FloatArray]:
    """Weighted polynomial fit of bearing against time per track, each entry at its own time.

    The rolling-shutter form of :func:`owl_core.engine.fit_tracks`: the same straight line
    (or quadratic) through the same entries, with per-entry times. The line's bearing is
    referred to the time of the track's *frame stamps* (what the global-shutter fit
    refers to), so tracks in different rows refer to one time; its slope is the rate at
    the entries' own time. Each of those times is the centroid ``c`` of its samples moved
    by ``m3 / (2 m2)`` (their third and second central moments): a least-squares slope
    through unevenly spaced samples of a curving signal is its derivative there, not at
    ``c`` (exact for a quadratic; the same ``c`` on a regular grid). The quadratic refers
    both to tau = 0.

    Args:
        bearings: (N, W, 3) bearings, already in the current camera frame.
        tau_s: (N, W) time of each entry relative to the current stamp, s.
        mask: (N, W) bool, valid entries.
        order: 1 or 2.
        frame_tau_s: (W,) frame stamp of each column relative to the current stamp, s.

    Returns:
        (bearing (N, 3) unit at tau_ref, rate (N, 3) tangent, 1/s, tau_ref (N,) s, gain (N,)
        1/s per unit bearing noise, valid (N,), tau_rate (N,) the time the rate belongs to,
        s); invalid tracks hold NaN (gain inf).
    """
    n = bearings.shape[0]
    m = mask.astype(np.float64)
    b = np.where(mask[..., None], bearings, 0.0)
    tau = np.where(mask, tau_s, 0.0)
    count = m.sum(axis=1)
    out_b = np.full((n, 3), np.nan)
    rate = np.full((n, 3), np.nan)
    tau_ref = np.zeros(n)
    gain = np.full(n, np.inf)
    s0 = np.maximum(count, 1.0)
    centroid, dt, sxx, slope_time = _sample_times(m, tau)
    line = (count >= 2) & (sxx > 1e-18)
    safe = np.where(line, sxx, 1.0)
    mean = np.einsum("nw,nwc->nc", m, b) / s0[:, None]
    slope = np.einsum("nw,nwc->nc", m * dt, b) / safe[:, None]
    # the rate belongs to the entries' slope time, the bearing is referred to the frame
    # stamps' (one time for every track over the same frames)
    tau_rate = np.where(line, slope_time, 0.0)
    frame_tau = np.broadcast_to(frame_tau_s, m.shape)
    if np.array_equal(tau_s, frame_tau):  # each entry at its frame time: the slope time
        ref = slope_time
    else:
        ref = _sample_times(m, frame_tau)[3]
    out_b[line] = (mean + slope * (ref - centroid)[:, None])[line]
    rate[line] = slope[line]
    tau_ref[line] = ref[line]
    gain[line] = 1.0 / np.sqrt(safe[line])
    valid = line.copy()
    if order == 2:
        quad = count >= 3
        if quad.any():
            t = tau[quad]
            powers = np.stack([np.ones_like(t), t, t * t], axis=-1)  # (Q, W, 3)
            normal = np.einsum("nw,nwi,nwj->nij", m[quad], powers, powers)
            rhs = np.einsum("nw,nwi,nwc->nic", m[quad], powers, b[quad])
            ok = np.abs(np.linalg.det(normal)) > 1e-30
            inv = np.linalg.inv(np.where(ok[:, None, None], normal, np.eye(3)))
            coef = inv @ rhs
            idx = np.flatnonzero(quad)[ok]
            out_b[idx] = coef[ok, 0]
            rate[idx] = coef[ok, 1]
            tau_ref[idx] = 0.0
            tau_rate[idx] = 0.0
            gain[idx] = np.sqrt(np.maximum(inv[ok, 1, 1], 0.0))
    norm = row_norms(out_b)[:, None]
    out_b = out_b / np.where(norm > 0, norm, 1.0)
    rate = rate - np.einsum("nc,nc->n", rate, out_b)[:, None] * out_b
    return out_b, rate, tau_ref, gain, valid, tau_rate


def _sample_times(
    weights: FloatArray, times: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per row of (N, W) ``weights`` and ``times`` (s): the weighted centroid ``c`` (N,),
    the deviations from it (N, W; 0 where the weight is), their second moment ``m2`` (N,),
    and the time a least-squares slope through those samples belongs to, ``c + m3 / (2 m2)``
    (N,). On uneven samples (jittered or dropped frames) the slope of a signal with
    curvature is its derivative there, not at ``c``: exact for a quadratic, ``c`` itself
    on a regular grid. At ``c``, a dropped frame in a 0.15 s window at 30 Hz would refer
    the rate 11 ms late, and r/|t| of an approaching point would read 1 % short."""
    centroid = np.sum(weights * times, axis=1) / np.maximum(weights.sum(axis=1), 1.0)
    dev = np.where(weights > 0, times - centroid[:, None], 0.0)
    m2 = np.sum(weights * dev * dev, axis=1)
    m3 = np.sum(weights * dev**3, axis=1)
    return centroid, dev, m2, centroid + 0.5 * m3 / np.where(m2 > 1e-18, m2, np.inf)


def bearings_at_stamp(bearings: FloatArray, rate: FloatArray, tau_s: FloatArray) -> FloatArray:
    """Bearings (N, 3) seen ``tau_s`` (N,) seconds after the stamp (their row time), moved
    back to the stamp along the derotated rate (N, 3), 1/s: unit (N, 3)."""
    moved = bearings - np.nan_to_num(rate) * tau_s[:, None]
    out: FloatArray = moved / row_norms(moved)[:, None]
    return out
