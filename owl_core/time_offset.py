"""Online estimate of a residual camera-IMU time offset from the flow (as OpenVINS does).

Why it is observable
--------------------
The engine derotates each track with the gyro rotation between its frames. With the IMU
clock read ``delta`` off (the configured ``imu_time_offset`` differs from the true one by
``delta``), each rotation is the one of an interval shifted by ``delta``: column k's bearing
is off by about ``phi_k delta``, ``phi_k = Omega(now) - Omega(s_k)`` (rates carried to the
current camera frame). The track fit turns that into a leftover rotation rate
``J delta``, ``J`` the slope of ``phi_k`` over the window's frame times, i.e. minus the
angular acceleration: a time offset looks like a gyro bias proportional to ``dOmega/dt``.
The heading estimator measures the leftover rotation of every frame; a bias is constant
(a slow random walk) while ``dOmega/dt`` changes direction and size, so the two separate.

The filter
----------
:class:`TimeOffsetFilter` is a Kalman filter on ``x = (offset, b)``: the true offset (s,
IMU stamp minus camera stamp, as ``imu_time_offset``) and the true gyro bias in the camera
frame (rad/s; a nuisance here, the engine's own bias filter keeps its estimate). Each frame
gives the leftover rotation ``r`` (estimated jointly with the heading, with a wide prior so
that it is not shrunk) measured with the bias ``b_used`` and offset ``o_used`` the frame
was derotated with::

    r = b_used - b + L(offset - o_used) + noise

``L`` (the caller computes it from the gyro, exactly: the derotation with the camera times
shifted) is nonlinear in the offset error (5-10 % at 40 ms while turning at 0.5 Hz), so the
filter is an extended Kalman filter linearised at its current estimate,
``H = [L'(offset_est - o_used), -I]``.

Its information is divided by ``inflation`` (consecutive fit windows share frames) and a
measurement farther than a chi-square gate (3 dof, 99.9 %) from the prediction is dropped.

The extrinsic rotation, too
---------------------------
The same leftover shows a small error of the configured camera-to-IMU rotation: with the
true one ``R_ci Exp(phi)`` (``phi`` a camera-frame rotation vector, rad), every gyro
rotation seen in the camera frame is conjugated by ``Exp(phi)``, which leaves a leftover
``M phi`` with ``M`` about ``[Omega]x`` (the window's rotation rate; the caller computes it
exactly from the gyro, as for ``L``). A bias is constant, ``M`` turns with the rotation
axis: with rotation about two axes all three components of ``phi`` separate from it (about
one axis, the component along it stays at its prior). When the caller passes ``M``, the
state is ``x = (offset, b, phi)``; ``phi`` is never applied (the derotation keeps the
configured rotation), so the model is linear in it. A frame without angular acceleration
then updates the bias and ``phi`` only: the offset's gain is zeroed (a consider update),
so a leftover the model misses cannot move the offset through its correlations (on a
steady turn that had taken it 50 ms off at a 1-sigma of 7 ms; now 32 ms at 10 ms, still
far from the 2 ms at which the check judges it). The live calibration check
(:mod:`owl_core.calib_check`) reads it: translation, which leaks into rotation fits on the
tracks alone, is estimated jointly with the leftover here and does not.

Units: seconds, radians; the caller supplies J (s^-2... rad/s per s) from the gyro.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from owl_core.errors import InvalidInputError

FloatArray = npt.NDArray[np.float64]

__all__ = ["OnlineCalibration", "TimeOffsetFilter", "TimeOffsetOptions"]

#: chi-square 99.9 % quantile with 3 degrees of freedom (the measurement gate).
GATE = 16.27


@dataclass(frozen=True)
class TimeOffsetOptions:
    """Settings of :class:`TimeOffsetFilter`.

    Attributes:
        initial_sigma_s: 1-sigma of the configured offset, s (> 0).
        random_walk_s: offset random walk, s/sqrt(s) (>= 0; clocks drift slowly).
        bias_sigma: 1-sigma of the initial bias (camera frame), rad/s (> 0).
        bias_random_walk: bias random walk, rad/s/sqrt(s) (>= 0).
        inflation: divisor (>= 1) of each frame's information.
        min_excitation: frames whose |J| (the window's angular acceleration) is below
            this carry no offset information: skipped, or without ``M`` used for the bias
            and ``phi`` only, rad/s^2 (>= 0).
        misalignment_sigma: 1-sigma of each component of ``phi``, the error of the
            configured camera-to-IMU rotation, rad (> 0).
    """

    initial_sigma_s: float = 0.05
    random_walk_s: float = 1e-4
    bias_sigma: float = 0.02
    bias_random_walk: float = 1e-4
    inflation: float = 3.0
    min_excitation: float = 0.05
    misalignment_sigma: float = 0.1

    def __post_init__(self) -> None:
        for name in ("initial_sigma_s", "bias_sigma", "misalignment_sigma"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InvalidInputError(f"{name} must be positive and finite, got {value!r}")
        for name in ("random_walk_s", "bias_random_walk", "min_excitation"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InvalidInputError(f"{name} must be >= 0 and finite, got {value!r}")
        if not self.inflation >= 1.0:
            raise InvalidInputError(f"inflation must be >= 1, got {self.inflation!r}")


@dataclass(frozen=True)
class OnlineCalibration:
    """What :class:`TimeOffsetFilter` holds, for readers (the live calibration check).

    Attributes:
        offset_s: the offset estimate, s (IMU stamp minus camera stamp).
        offset_sigma_s: its 1-sigma, s.
        misalignment: (3,) ``phi``, camera frame, rad: the true camera-to-IMU rotation is
            the configured one times ``Exp(phi)``.
        misalignment_cov: (3, 3) its covariance, rad^2.
        updates: frames applied, count.
        rejected: frames the gate dropped, count.
    """

    offset_s: float
    offset_sigma_s: float
    misalignment: FloatArray
    misalignment_cov: FloatArray
    updates: int
    rejected: int


class TimeOffsetFilter:
    """Kalman filter on the camera-IMU time offset, the gyro bias and the error of the
    configured extrinsic rotation (module docstring). ``x`` (7,): offset s, bias rad/s
    (camera frame), ``phi`` rad; ``cov`` (7, 7).

    Args:
        initial_offset_s: the configured offset, s.
        initial_bias_camera: (3,) the configured bias, camera frame, rad/s.
        options: settings.
    """

    def __init__(
        self,
        initial_offset_s: float,
        initial_bias_camera: npt.ArrayLike = (0.0, 0.0, 0.0),
        options: TimeOffsetOptions | None = None,
    ) -> None:
        self.options = opts = options if options is not None else TimeOffsetOptions()
        bias = np.asarray(initial_bias_camera, dtype=np.float64)
        if bias.shape != (3,) or not math.isfinite(initial_offset_s):
            raise InvalidInputError(
                f"need a finite offset and a (3,) bias, got {initial_offset_s!r}, {bias!r}"
            )
        self._x0 = np.concatenate([[float(initial_offset_s)], bias, np.zeros(3)])
        self._p0 = np.diag(
            [opts.initial_sigma_s**2] + [opts.bias_sigma**2] * 3 + [opts.misalignment_sigma**2] * 3
        )
        self.x = self._x0.copy()
        self.cov = self._p0.copy()
        self.updates = 0
        self.rejected = 0

    @property
    def offset_s(self) -> float:
        """The offset estimate, s."""
        return float(self.x[0])

    @property
    def offset_sigma_s(self) -> float:
        """Its 1-sigma, s."""
        return math.sqrt(float(self.cov[0, 0]))

    @property
    def bias_camera(self) -> FloatArray:
        """(3,) the bias estimate, camera frame, rad/s."""
        return np.asarray(self.x[1:4].copy(), dtype=np.float64)

    @property
    def misalignment(self) -> FloatArray:
        """(3,) ``phi``: the true camera-to-IMU rotation is the configured one times
        ``Exp(phi)``, camera frame, rad."""
        return np.asarray(self.x[4:].copy(), dtype=np.float64)

    @property
    def misalignment_cov(self) -> FloatArray:
        """(3, 3) its covariance, rad^2."""
        return np.asarray(self.cov[4:, 4:].copy(), dtype=np.float64)

    def snapshot(self) -> OnlineCalibration:
        """The current estimates (copies)."""
        return OnlineCalibration(
            self.offset_s,
            self.offset_sigma_s,
            self.misalignment,
            self.misalignment_cov,
            self.updates,
            self.rejected,
        )

    def reset(self) -> None:
        """Back to the configured offset and bias."""
        self.x = self._x0.copy()
        self.cov = self._p0.copy()
        self.updates = 0
        self.rejected = 0

    def predict(self, dt_s: float) -> None:
        """Grow the uncertainty by the random walks over ``dt_s`` seconds (>= 0)."""
        if not dt_s >= 0:
            raise InvalidInputError(f"dt_s must be >= 0, got {dt_s!r}")
        o = self.options
        q = [o.random_walk_s**2 * dt_s] + [o.bias_random_walk**2 * dt_s] * 3 + [0.0] * 3
        self.cov = self.cov + np.diag(q)

    def update(
        self,
        leftover: npt.ArrayLike,
        leftover_cov: npt.ArrayLike,
        offset_leftover: npt.ArrayLike,
        jacobian: npt.ArrayLike,
        at_offset_s: float,
        used_bias_camera: npt.ArrayLike,
        misalignment_jacobian: npt.ArrayLike | None = None,
    ) -> bool:
        """Apply one frame's leftover rotation.

        Args:
            leftover: (3,) leftover rotation rate r, camera frame, rad/s (f_true = f + r x e).
            leftover_cov: (3, 3) its covariance (no prior in it), (rad/s)^2.
            offset_leftover: (3,) L at ``at_offset_s``: the leftover rotation this frame
                would show if the true offset were ``at_offset_s``, rad/s.
            jacobian: (3,) dL/d offset there, rad/s per s.
            at_offset_s: the offset of that linearisation point, s (the current estimate
                when the gyro covers it).
            used_bias_camera: (3,) the bias it was derotated with, camera frame, rad/s.
            misalignment_jacobian: (3, 3) ``M`` = d leftover / d ``phi``, rad/s per rad, or
                None (``phi`` then stays at its prior).

        Returns:
            True when applied; False when the frame had too little angular acceleration
            (and no ``M``), a singular covariance, or failed the gate.
        """
        r = np.asarray(leftover, dtype=np.float64)
        c = np.asarray(leftover_cov, dtype=np.float64) * self.options.inflation
        lo = np.asarray(offset_leftover, dtype=np.float64)
        j = np.asarray(jacobian, dtype=np.float64)
        b_used = np.asarray(used_bias_camera, dtype=np.float64)
        m = (
            np.zeros((3, 3))
            if misalignment_jacobian is None
            else (np.asarray(misalignment_jacobian, dtype=np.float64))
        )
        shapes = (r.shape, c.shape, lo.shape, j.shape, b_used.shape, m.shape)
        if shapes != ((3,), (3, 3), (3,), (3,), (3,), (3, 3)):
            raise InvalidInputError(
                f"need (3,) leftover, (3, 3) covariance, (3,) model leftover, jacobian and "
                f"bias, (3, 3) misalignment jacobian, got {', '.join(map(str, shapes))}"
            )
        arrays = (r, c, lo, j, m)
        if not all(np.all(np.isfinite(a)) for a in arrays):
            return False
        excited = float(np.linalg.norm(j)) >= self.options.min_excitation
        if not excited:
            if misalignment_jacobian is None:
                return False
            j = np.zeros(3)  # no offset information in this frame
        predicted = (
            b_used - self.x[1:4] + lo + j * (self.x[0] - float(at_offset_s)) + m @ self.x[4:]
        )
        h = np.zeros((3, 7))
        h[:, 0] = j
        h[:, 1:4] = -np.eye(3)
        h[:, 4:] = m
        s = h @ self.cov @ h.T + c
        try:
            s_inv = np.linalg.inv(s)
        except np.linalg.LinAlgError:
            return False
        innovation = r - predicted
        if float(innovation @ s_inv @ innovation) > GATE:
            self.rejected += 1
            return False
        gain = self.cov @ h.T @ s_inv
        if not excited:
            # the offset is not updated through its correlation with the bias and phi
            # either (a consider update; the Joseph form below holds for any gain): a
            # frame without angular acceleration says nothing about it, and a leftover
            # the model misses (a steady turn: 50 ms off at 7 ms 1-sigma) would move it
            gain[0] = 0.0
        self.x = self.x + gain @ innovation
        ikh = np.eye(7) - gain @ h
        self.cov = ikh @ self.cov @ ikh.T + gain @ c @ gain.T  # Joseph form
        self.updates += 1
        return True
