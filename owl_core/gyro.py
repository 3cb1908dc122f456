"""Gyro buffer: camera rotation between two image stamps from IMU angular rates.

Convention
----------
Let ``R_wc(t)`` be the camera orientation (camera-frame vectors into a world
frame) and ``Omega(t)`` the camera angular velocity in the camera frame, so
``dR_wc/dt = R_wc [Omega]x``. A world-fixed direction ``d`` has the camera-frame
bearing ``e(t) = R_wc(t)^T d``, hence ``de/dt = -Omega x e`` (the rotational
part of the motion field in ``owl-math.md``). The buffer returns::

    R_{1<-0} = R_wc(t1)^T R_wc(t0),        e(t1) = R_{1<-0} e(t0)

which solves ``dY/dt = -[Omega(t)]x Y``, ``Y(t0) = I``; for a constant rate
``R_{1<-0} = so3_exp(-Omega (t1 - t0))``.

The gyro measures ``omega_imu`` in the IMU frame. With ``R = R(q)`` the
camera-to-IMU extrinsic rotation (``camera_to_imu_rotation_xyzw``: takes
camera-frame vectors into the IMU frame) and ``b`` the gyro bias (IMU frame)::

    Omega = R^T (omega_imu - b)

Clocks: an event at camera time ``t`` carries the IMU stamp ``t + offset``
(``imu_time_offset_ns``). Between samples the rate is taken as piecewise
linear in time (interpolated at both interval ends). Each linear piece of
length ``h`` is integrated with fourth-order Magnus steps (two Gauss
points ``w1, w2`` per step)::

    Phi = so3_exp(-(h/2)(w1 + w2) + (sqrt(3) h^2 / 12) (w2 x w1))

which is exact for a constant rate; otherwise each piece is subdivided so
that the local error stays below 1e-12 rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from owl_core.errors import CalibrationError, InvalidInputError, TimeError
from owl_core.geometry import quat_xyzw_to_matrix, so3_exp, so3_log
from owl_core.motion import cross, row_norms
from owl_core.types import GyroSamples

FloatArray = npt.NDArray[np.float64]

__all__ = ["DROP_REASONS", "GyroBuffer", "GyroIntake", "GyroProblem"]

#: Keys of :attr:`GyroBuffer.dropped`.
DROP_REASONS = ("non_finite", "duplicate", "out_of_order")

_SQRT3 = math.sqrt(3.0)
_GAUSS_LO = 0.5 - _SQRT3 / 6.0
_GAUSS_HI = 0.5 + _SQRT3 / 6.0
_STEP_TOL = 1e-12  # rad, target local error of one Magnus sub-step
_MAX_SUBSTEPS = 64


@dataclass(frozen=True)
class GyroProblem:
    """The last rejected or gap-opening sample of one :meth:`GyroBuffer.intake` call.

    Attributes:
        kind: ``"non_finite"``, ``"duplicate"``, ``"out_of_order"`` or ``"gap"``.
        stamp_ns: the sample's stamp, IMU clock, ns.
        prior_ns: the newest accepted stamp before it, ns (None for ``"non_finite"`` or
            an empty buffer).
        rate: (3,) the sample's angular rate, IMU frame, rad/s.
    """

    kind: str
    stamp_ns: int
    prior_ns: int | None
    rate: tuple[float, float, float]


@dataclass(frozen=True)
class GyroIntake:
    """What one :meth:`GyroBuffer.intake` call did with its samples.

    Attributes:
        accepted: samples added.
        non_finite, duplicate, out_of_order: samples rejected for that reason.
        gaps: accepted samples more than ``max_gap_ns`` after the newest before them
            (the buffer was emptied before each: no interpolation across a gap).
        problem: the last rejected or gap-opening sample, or None.
    """

    accepted: int
    non_finite: int = 0
    duplicate: int = 0
    out_of_order: int = 0
    gaps: int = 0
    problem: GyroProblem | None = None


class GyroBuffer:
    """Time-ordered gyro samples and exact rotation integration between camera stamps.

    Args:
        camera_to_imu_rotation_xyzw: (4,) quaternion (x, y, z, w) of the rotation
            taking camera-optical-frame vectors into the IMU frame (the rotation of
            the TF transform IMU (parent) -> camera optical frame (child)). Default
            identity. Normalised; must be finite with norm within 1% of 1.
        imu_time_offset_ns: IMU stamp minus camera stamp for simultaneous
            events, integer nanoseconds.
        capacity_s: samples older than ``capacity_s`` seconds before the newest
            sample are discarded, seconds (> 0).

    Attributes:
        dropped: counts of rejected samples by reason: ``"non_finite"`` (NaN/inf
            rate), ``"duplicate"`` (stamp equal to the newest accepted one),
            ``"out_of_order"`` (stamp older than the newest accepted one).

    Raises:
        CalibrationError: bad extrinsic quaternion.
        InvalidInputError: bad offset or capacity.
    """

    def __init__(
        self,
        camera_to_imu_rotation_xyzw: npt.ArrayLike = (0.0, 0.0, 0.0, 1.0),
        imu_time_offset_ns: int = 0,
        capacity_s: float = 10.0,
    ) -> None:
        q = np.asarray(camera_to_imu_rotation_xyzw, dtype=np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)):
            raise CalibrationError(
                f"camera_to_imu_rotation_xyzw must be 4 finite numbers, got {q.tolist()}"
            )
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > 1e-2:
            raise CalibrationError(
                f"camera_to_imu_rotation_xyzw must be a unit quaternion, got {q.tolist()} "
                f"(norm {norm:.6g})"
            )
        if isinstance(imu_time_offset_ns, bool) or not isinstance(
            imu_time_offset_ns, int | np.integer
        ):
            raise InvalidInputError(
                f"imu_time_offset_ns must be an integer (nanoseconds), got {imu_time_offset_ns!r}"
            )
        if not (isinstance(capacity_s, int | float) and math.isfinite(capacity_s)) or (
            capacity_s <= 0
        ):
            raise InvalidInputError(f"capacity_s must be positive and finite, got {capacity_s!r}")
        self._rotation: FloatArray = quat_xyzw_to_matrix(q / norm)
        self._rotation.setflags(write=False)
        self._offset_ns = int(imu_time_offset_ns)
        self._capacity_ns = round(capacity_s * 1e9)
        self.dropped: dict[str, int] = dict.fromkeys(DROP_REASONS, 0)
        self._t = np.zeros(0, dtype=np.int64)
        self._w = np.zeros((0, 3), dtype=np.float64)
        self._i0 = 0  # first live sample
        self._n = 0  # one past the last live sample

    # ------------------------------------------------------------ properties

    @property
    def camera_to_imu_rotation(self) -> FloatArray:
        """(3, 3) float64 read-only rotation taking camera-frame vectors into the IMU frame."""
        return self._rotation

    @property
    def imu_time_offset_ns(self) -> int:
        """IMU stamp minus camera stamp, nanoseconds."""
        return self._offset_ns

    @property
    def stamps_ns(self) -> npt.NDArray[np.int64]:
        """(N,) int64 stamps of the held samples, IMU clock, nanoseconds (a copy)."""
        return self._t[self._i0 : self._n].copy()

    @property
    def rates_imu(self) -> FloatArray:
        """(N, 3) float64 held angular rates, IMU frame, rad/s (a copy)."""
        return self._w[self._i0 : self._n].copy()

    @property
    def camera_span_ns(self) -> tuple[int, int] | None:
        """(first, last) sample times on the camera clock, nanoseconds, or None if empty."""
        if self._n == self._i0:
            return None
        return (
            int(self._t[self._i0]) - self._offset_ns,
            int(self._t[self._n - 1]) - self._offset_ns,
        )

    def __len__(self) -> int:
        return self._n - self._i0

    # ------------------------------------------------------------------ input

    def reset(self) -> None:
        """Forget every sample and zero the drop counters (e.g. after a time jump)."""
        self._i0 = self._n = 0
        self.dropped = dict.fromkeys(DROP_REASONS, 0)

    def set_calibration(
        self, camera_to_imu_rotation_xyzw: npt.ArrayLike, imu_time_offset_ns: int
    ) -> None:
        """Use another extrinsic rotation and IMU time offset for the held samples (they are
        stored as measured: IMU frame, IMU clock). Same checks as the constructor.

        Raises:
            CalibrationError: bad quaternion.
            InvalidInputError: bad offset.
        """
        other = GyroBuffer(camera_to_imu_rotation_xyzw, imu_time_offset_ns)
        self._rotation, self._offset_ns = other._rotation, other._offset_ns

    def add(self, samples: GyroSamples) -> int:
        """Append samples, rejecting bad ones (counted in :attr:`dropped`).

        A sample is accepted when its rate is finite and its stamp is later than
        every sample accepted before it. Samples older than ``capacity_s``
        before the newest are then discarded.

        Args:
            samples: ``stamp_ns`` (N,) integer ns (IMU clock), ``angular_velocity``
                (N, 3) rad/s (IMU frame).

        Returns:
            Number of samples accepted.

        Raises:
            InvalidInputError: wrong shapes or a non-integer stamp dtype.
        """
        return self.intake(samples).accepted

    def intake(self, samples: GyroSamples, max_gap_ns: float | None = None) -> GyroIntake:
        """:meth:`add` that also never bridges a gap, and says what it rejected.

        An accepted sample more than ``max_gap_ns`` after the newest accepted one before it
        opens a gap: every sample before it is forgotten, so no rotation is ever
        interpolated across the gap (frames spanning it are not covered). Vectorised over
        the samples.

        Args:
            samples: ``stamp_ns`` (N,) integer ns (IMU clock), ``angular_velocity``
                (N, 3) rad/s (IMU frame).
            max_gap_ns: longest gap between accepted samples, ns; None: no limit.

        Returns:
            A :class:`GyroIntake` (counts, and the last problem sample).

        Raises:
            InvalidInputError: wrong shapes or a non-integer stamp dtype.
        """
        t = np.asarray(samples.stamp_ns)
        w = np.asarray(samples.angular_velocity, dtype=np.float64)
        if t.ndim != 1 or t.dtype.kind not in "iu":
            raise InvalidInputError(
                f"gyro stamp_ns must be a 1-D integer array, got shape {t.shape} dtype {t.dtype}"
            )
        if w.shape != (t.shape[0], 3):
            raise InvalidInputError(
                f"gyro angular_velocity must have shape ({t.shape[0]}, 3), got {w.shape}"
            )
        if t.shape[0] == 0:
            return GyroIntake(0)
        t = t.astype(np.int64)
        finite = np.all(np.isfinite(w), axis=1)
        floor = np.iinfo(np.int64).min
        last = int(self._t[self._n - 1]) if self._n > self._i0 else floor
        # Newest accepted stamp before each sample = running max of the earlier
        # finite stamps (a rejected stamp never exceeds it, so it cannot matter).
        prior = np.maximum.accumulate(np.concatenate([[last], np.where(finite, t, floor)]))[:-1]
        accept = finite & (t > prior)
        kinds = {
            "non_finite": ~finite,
            "duplicate": finite & (t == prior),
            "out_of_order": finite & (t < prior),
            "gap": np.zeros_like(accept),
        }
        if max_gap_ns is not None:
            kinds["gap"] = accept & (prior != floor) & ((t - prior) > max_gap_ns)
        counts = {k: int(np.count_nonzero(m)) for k, m in kinds.items()}
        for reason in DROP_REASONS:
            self.dropped[reason] += counts[reason]
        if counts["gap"]:
            opened = int(np.flatnonzero(kinds["gap"])[-1])
            self._i0 = self._n = 0  # forget what lies before the (last) gap
            accept[:opened] = False
        self._append(t[accept], w[accept])
        return GyroIntake(
            accepted=int(np.count_nonzero(accept)),
            non_finite=counts["non_finite"],
            duplicate=counts["duplicate"],
            out_of_order=counts["out_of_order"],
            gaps=counts["gap"],
            problem=_last_problem(kinds, t, prior, w, floor),
        )

    def _append(self, t: npt.NDArray[np.int64], w: FloatArray) -> None:
        m = t.shape[0]
        if m == 0:
            return
        live = self._n - self._i0
        if self._n + m > self._t.shape[0]:
            size = max(2 * (live + m), 64)
            new_t = np.empty(size, dtype=np.int64)
            new_w = np.empty((size, 3), dtype=np.float64)
            new_t[:live] = self._t[self._i0 : self._n]
            new_w[:live] = self._w[self._i0 : self._n]
            self._t, self._w, self._i0, self._n = new_t, new_w, 0, live
        self._t[self._n : self._n + m] = t
        self._w[self._n : self._n + m] = w
        self._n += m
        cutoff = int(self._t[self._n - 1]) - self._capacity_ns
        self._i0 += int(np.searchsorted(self._t[self._i0 : self._n], cutoff, side="left"))

    # ------------------------------------------------------------- integration

    def covers(self, t0_ns: int, t1_ns: int) -> bool:
        """Whether the samples span camera times ``[min(t0,t1), max(t0,t1)]`` (ns)."""
        if self._n == self._i0:
            return False
        a, b = sorted((int(t0_ns), int(t1_ns)))
        return bool(
            self._t[self._i0] <= a + self._offset_ns
            and b + self._offset_ns <= self._t[self._n - 1]
        )

    def relative_rotation(
        self, t0_ns: int, t1_ns: int, bias_imu: npt.ArrayLike = (0.0, 0.0, 0.0)
    ) -> FloatArray:
        """Rotation ``R_{1<-0}`` taking camera-frame bearings at ``t0`` to those at ``t1``.

        See the module docstring for the equation. ``t1 < t0`` gives the inverse
        rotation; ``t1 == t0`` the identity.

        Args:
            t0_ns: first camera stamp, nanoseconds.
            t1_ns: second camera stamp, nanoseconds.
            bias_imu: (3,) gyro bias subtracted from the measured rates, IMU frame, rad/s.

        Returns:
            (3, 3) float64 rotation matrix.

        Raises:
            TimeError: the samples do not cover the interval.
            InvalidInputError: malformed bias.
        """
        if t1_ns < t0_ns:
            return self.relative_rotation(t1_ns, t0_ns, bias_imu).T.copy()
        knots_s, rates = self._knots(int(t0_ns), int(t1_ns), bias_imu)
        rotvec, _ = _magnus_steps(np.diff(knots_s), rates[:-1], rates[1:])
        steps = so3_exp(rotvec)
        result = np.eye(3)
        for step in steps:  # a few samples per frame interval, later steps on the left
            result = step @ result
        return result

    def relative_rotations(
        self, t0s_ns: npt.ArrayLike, t1_ns: int, bias_imu: npt.ArrayLike = (0.0, 0.0, 0.0)
    ) -> FloatArray:
        """``R_{1<-0}`` for several start stamps and one end stamp, in one integration.

        Equals ``[relative_rotation(t0, t1_ns, bias_imu) for t0 in t0s_ns]`` (to the
        integration tolerance, 1e-12 rad) at about the cost of the longest interval:
        the pieces are integrated once and the products accumulated from ``t1_ns`` back.

        Args:
            t0s_ns: (K,) int64 start camera stamps, nanoseconds, each ``<= t1_ns``.
            t1_ns: end camera stamp, nanoseconds.
            bias_imu: (3,) gyro bias subtracted from the measured rates, IMU frame, rad/s.

        Returns:
            (K, 3, 3) float64 rotation matrices.

        Raises:
            TimeError: the samples do not cover ``[min(t0s_ns), t1_ns]``.
            InvalidInputError: a start after ``t1_ns``, or a malformed bias.
        """
        starts = np.asarray(t0s_ns, dtype=np.int64).reshape(-1)
        end = int(t1_ns)
        if starts.size == 0:
            return np.zeros((0, 3, 3))
        if np.any(starts > end):
            raise InvalidInputError(
                f"start stamps must not be after t1_ns = {end} ns, got {starts.tolist()}"
            )
        first = int(starts.min())
        knots_s, rates = self._knots(first, end, bias_imu)
        # Split the pieces at the other starts (the piecewise-linear rate is unchanged).
        starts_s = (starts - first).astype(np.float64) * 1e-9
        times = np.union1d(knots_s, starts_s)
        if times.shape[0] != knots_s.shape[0]:
            rates = np.stack([np.interp(times, knots_s, rates[:, i]) for i in range(3)], axis=-1)
        rotvec, substeps = _magnus_steps(np.diff(times), rates[:-1], rates[1:])
        steps = so3_exp(rotvec)
        # suffix[i] = steps[-1] @ ... @ steps[i]: the rotation from sub-step i's start to t1
        suffix = np.empty((steps.shape[0] + 1, 3, 3))
        suffix[-1] = np.eye(3)
        for i in range(steps.shape[0] - 1, -1, -1):
            suffix[i] = suffix[i + 1] @ steps[i]
        first_substep = np.concatenate([np.cumsum(substeps) - substeps, [steps.shape[0]]])
        result: FloatArray = suffix[first_substep[np.searchsorted(times, starts_s)]]
        return result

    def mean_rate_camera(
        self, t0_ns: int, t1_ns: int, bias_imu: npt.ArrayLike = (0.0, 0.0, 0.0)
    ) -> FloatArray:
        """Constant camera-frame rate producing the same rotation over ``[t0, t1]``.

        ``so3_exp(-mean * (t1 - t0)) == relative_rotation(t0, t1)``; for
        ``t0 == t1`` the interpolated rate at that instant.

        Returns:
            (3,) float64 angular velocity, camera frame, rad/s.

        Raises:
            TimeError: the samples do not cover the interval.
        """
        if t0_ns == t1_ns:
            return self.rate_camera(t0_ns, bias_imu)
        dt = (int(t1_ns) - int(t0_ns)) * 1e-9
        result: FloatArray = -so3_log(self.relative_rotation(t0_ns, t1_ns, bias_imu)) / dt
        return result

    def rate_camera(self, t_ns: int, bias_imu: npt.ArrayLike = (0.0, 0.0, 0.0)) -> FloatArray:
        """Linearly interpolated camera-frame angular velocity at camera time ``t_ns``.

        Returns:
            (3,) float64 rad/s, camera frame (bias removed).

        Raises:
            TimeError: ``t_ns`` outside the held samples.
        """
        _, rates = self._knots(int(t_ns), int(t_ns), bias_imu)
        result: FloatArray = rates[0].copy()
        return result

    def _knots(self, t0_ns: int, t1_ns: int, bias_imu: Any) -> tuple[FloatArray, FloatArray]:
        """Knot times (s, relative to t0) and bias-free camera-frame rates at them."""
        bias = np.asarray(bias_imu, dtype=np.float64)
        if bias.shape != (3,) or not np.all(np.isfinite(bias)):
            raise InvalidInputError(f"bias_imu must be 3 finite numbers, got {bias_imu!r}")
        if not self.covers(t0_ns, t1_ns):
            span = self.camera_span_ns
            held = "no samples" if span is None else f"camera times [{span[0]}, {span[1]}] ns"
            raise TimeError(
                f"gyro samples do not cover camera interval [{t0_ns}, {t1_ns}] ns "
                f"(imu_time_offset {self._offset_ns} ns); buffer holds {held}"
            )
        a = t0_ns + self._offset_ns
        b = t1_ns + self._offset_ns
        t = self._t[self._i0 : self._n]
        # Samples bracketing [a, b]: t[lo] <= a, t[hi] >= b.
        lo = max(int(np.searchsorted(t, a, side="right")) - 1, 0)
        hi = min(int(np.searchsorted(t, b, side="left")), t.shape[0] - 1)
        ts = t[lo : hi + 1]
        ws = self._w[self._i0 + lo : self._i0 + hi + 1]
        inner = (ts > a) & (ts < b)
        knots_ns = np.concatenate([[a], ts[inner], [b]]) if b > a else np.array([a])
        rel_knots = (knots_ns - a).astype(np.float64) * 1e-9
        rel_ts = (ts - a).astype(np.float64) * 1e-9
        rates_imu = np.stack([np.interp(rel_knots, rel_ts, ws[:, i]) for i in range(3)], axis=-1)
        rates_cam: FloatArray = (rates_imu - bias) @ self._rotation  # R^T w, row-wise
        return rel_knots, rates_cam


def _last_problem(
    kinds: dict[str, npt.NDArray[np.bool_]],
    t: npt.NDArray[np.int64],
    prior: npt.NDArray[np.int64],
    w: FloatArray,
    floor: int,
) -> GyroProblem | None:
    """The last sample flagged in any of ``kinds`` (masks over the N samples), or None."""
    flagged = np.zeros(t.shape[0], dtype=bool)
    for mask in kinds.values():
        flagged |= mask
    if not flagged.any():
        return None
    i = int(np.flatnonzero(flagged)[-1])
    kind = next(k for k, mask in kinds.items() if mask[i])
    p = int(prior[i])
    rate = (float(w[i, 0]), float(w[i, 1]), float(w[i, 2]))
    return GyroProblem(kind, int(t[i]), None if p == floor or kind == "non_finite" else p, rate)


def _magnus_steps(
    h: FloatArray, wa: FloatArray, wb: FloatArray
) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """Rotation vectors of the fourth-order Magnus steps over linear rate pieces.

    Each piece (length ``h`` s, rate ``wa`` -> ``wb`` rad/s, camera frame) is
    split into ``m`` equal sub-steps so that the leading error term, about
    ``h^3 |wb - wa| (|wa| + |wb|)^2 / (720 m^3)`` rad, stays below 1e-12 rad.

    Args:
        h: (K,) piece lengths, seconds.
        wa: (K, 3) rates at the piece starts, rad/s.
        wb: (K, 3) rates at the piece ends, rad/s.

    Returns:
        (S, 3) rotation vectors of the sub-steps in time order, rad, and (K,) int64
        the number of sub-steps of each piece.
    """
    dw = wb - wa
    size = row_norms(wa) + row_norms(wb)
    err = h**3 * row_norms(dw) * size**2 / 720.0
    m = np.clip(np.ceil(np.cbrt(err / _STEP_TOL)), 1, _MAX_SUBSTEPS).astype(np.int64)
    piece = np.repeat(np.arange(h.shape[0]), m)
    j = np.arange(piece.shape[0]) - np.repeat(np.cumsum(m) - m, m)
    mp = m[piece].astype(np.float64)
    hs = h[piece] / mp
    w1 = wa[piece] + dw[piece] * ((j + _GAUSS_LO) / mp)[:, None]
    w2 = wa[piece] + dw[piece] * ((j + _GAUSS_HI) / mp)[:, None]
    result: FloatArray = -0.5 * hs[:, None] * (w1 + w2) + (_SQRT3 / 12.0) * (hs * hs)[
        :, None
    ] * cross(w2, w1)
    return result, m
