"""A Kalman filter on the camera's log speed: the relative speed change d ln|t|/dt from
frame-to-frame scale ratios, with a motion model instead of a fixed-gain average.

OWL's scaled points are in units of the camera speed at their track fit's reference time,
``tau`` seconds before the image (tau <= 0). Each frame, the static points of the previous
frame moved on at constant speed predict this frame's; the median log ratio of predicted
to measured r/|t| is the log speed change between the two frames' reference times,

    increment_k = l(t_k + tau_k) - l(t_(k-1) + tau_(k-1)) + e_(k-1) - e_k,

with ``l = ln|t|`` and ``e_k`` the frame's common scale error (a few 0.1 %, shared by its
points, so not averaged away by the median). The increments telescope: their running sum
``z_k`` measures ``l(t_k + tau_k)`` up to a constant with the bounded error ``-e_k``, where a
per-frame rate ``increment / dt`` has the error ``(e_(k-1) - e_k) / dt`` (0.1 /s at 26 Hz).
:class:`SpeedChangeFilter` keeps

    state  x = (l, s, a): log speed at the image time, its rate s = dl/dt (1/s) and
           the rate's rate a = ds/dt (1/s^2),

* **predict** over ``dt``: ``F = [[1, dt, dt^2/2], [0, 1, dt], [0, 0, 1]]`` and the process
  noise of a white ``da/dt`` of density ``q`` (1/s^2.5):
  ``Q = q^2 [[dt^5/20, dt^4/8, dt^3/6], [dt^4/8, dt^3/3, dt^2/2], [dt^3/6, dt^2/2, dt]]``.
* **update** with ``z`` at ``tau``: ``H = [1, tau, tau^2/2]``, variance ``sigma^2``.

On a constant-speed path the rate settles at 0 (the measurements agree with it), on an
accelerating one the rate and its rate follow, and :meth:`SpeedChangeFilter.log_change`
gives ``l(t + tau) - l(t)`` to bring a point from its reference speed to the current one.
Pure numpy; units: seconds, natural log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from owl_core.errors import InvalidInputError

FloatArray = npt.NDArray[np.float64]

__all__ = ["SpeedChangeFilter", "SpeedFilterOptions", "TwoModelSpeed", "TwoModelSpeedOptions"]


@dataclass(frozen=True)
class SpeedFilterOptions:
    """Options of :class:`SpeedChangeFilter`.

    Attributes:
        jerk_density: density of the white change of ``a = d^2 ln|t|/dt^2``, 1/s^2.5;
            larger follows faster speed changes, smaller averages more.
        log_sigma: 1-sigma of one frame's common scale error ``e_k`` (natural log).
        rate_sigma: prior 1-sigma of ``s`` at the start, 1/s.
        accel_sigma: prior 1-sigma of ``a`` at the start, 1/s^2.
        max_rate: an increment above ``max_rate * dt`` in magnitude is clamped to it, 1/s.
    """

    jerk_density: float = 3.0
    log_sigma: float = 0.01
    rate_sigma: float = 1.0
    accel_sigma: float = 2.0
    max_rate: float = 5.0

    def __post_init__(self) -> None:
        for name in ("jerk_density", "rate_sigma", "accel_sigma"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InvalidInputError(f"{name} must be finite and >= 0, got {value!r}")
        for name in ("log_sigma", "max_rate"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InvalidInputError(f"{name} must be finite and > 0, got {value!r}")


class SpeedChangeFilter:
    """Log speed, its rate and its rate's rate from per-frame log-speed increments.

    Args:
        options: :class:`SpeedFilterOptions`.
    """

    def __init__(self, options: SpeedFilterOptions | None = None) -> None:
        self.options = options or SpeedFilterOptions()
        self.reset()

    def reset(self) -> None:
        """Forget everything; the next :meth:`step` starts the filter."""
        self._stamp: int | None = None
        self._x: FloatArray = np.zeros(3)
        self._p: FloatArray = np.zeros((3, 3))
        self._anchor = 0.0
        self.last_loglik: float | None = None

    @property
    def rate(self) -> float:
        """``s = d ln|t|/dt`` at the last stamp, 1/s (0 before the first step)."""
        return float(self._x[1])

    @property
    def rate_of_rate(self) -> float:
        """``a = ds/dt`` at the last stamp, 1/s^2."""
        return float(self._x[2])

    @property
    def rate_sigma(self) -> float:
        """1-sigma of :attr:`rate`, 1/s (the prior's before any measurement)."""
        if self._stamp is None:
            return self.options.rate_sigma
        return math.sqrt(max(float(self._p[1, 1]), 0.0))

    def log_change(self, tau: FloatArray) -> FloatArray:
        """``ln|t(t + tau)| - ln|t(t)|`` for times ``tau`` (any shape) relative to the last
        stamp, s (<= 0 for the past): multiply a scaled point in units of the speed at
        ``t + tau`` by ``exp`` of this to have it in units of the current speed."""
        t = np.asarray(tau, dtype=np.float64)
        return np.asarray(float(self._x[1]) * t + 0.5 * float(self._x[2]) * t * t)

    def step(self, stamp: int, increment: float | None, dt_ref: float, tau: float) -> float:
        """Advance to ``stamp`` and fuse one measurement.

        Args:
            stamp: image stamp, ns; not earlier than the last.
            increment: the log speed change since the previous frame's reference time
                (natural log), or None when this frame has none (too few common points):
                the chain restarts here from the model's prediction.
            dt_ref: time between the two reference times, s (> 0), for the clamp.
            tau: this frame's reference time relative to ``stamp``, s (<= 0).

        Returns:
            the filtered rate ``s`` at ``stamp``, 1/s.
        """
        opts = self.options
        h = np.array([1.0, tau, 0.5 * tau * tau])
        self.last_loglik = None
        if self._stamp is None:
            # the chain's first reference time defines l = 0 there: one measurement z = 0
            # at tau, on a prior that knows nothing of l (the log speed has no origin)
            self._stamp = stamp
            self._x = np.zeros(3)
            self._p = np.diag([1.0, opts.rate_sigma**2, opts.accel_sigma**2])
            self._anchor = 0.0
            self._update(h, 0.0)
            return self.rate
        dt = (stamp - self._stamp) * 1e-9
        if dt < 0:
            raise InvalidInputError(f"speed filter stamp went back by {-dt:.6f} s")
        self._stamp = stamp
        f = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
        q = opts.jerk_density**2 * np.array(
            [
                [dt**5 / 20.0, dt**4 / 8.0, dt**3 / 6.0],
                [dt**4 / 8.0, dt**3 / 3.0, dt**2 / 2.0],
                [dt**3 / 6.0, dt**2 / 2.0, dt],
            ]
        )
        self._x = f @ self._x
        self._p = f @ self._p @ f.T + q
        if increment is None or not math.isfinite(increment) or not dt_ref > 0:
            self._anchor = float(h @ self._x)
            return self.rate
        limit = opts.max_rate * dt_ref
        z = self._anchor + min(max(increment, -limit), limit)
        self.last_loglik = self._update(h, z)
        self._anchor = z
        return self.rate

    def _update(self, h: FloatArray, z: float) -> float:
        """Kalman update with the scalar measurement ``z = h . x``, variance log_sigma^2.
        Returns the innovation's log-likelihood."""
        ph = self._p @ h
        var = float(h @ ph) + self.options.log_sigma**2
        gain = ph / var
        nu = z - float(h @ self._x)
        self._x = self._x + gain * nu
        self._p = self._p - np.outer(gain, ph)
        self._p = 0.5 * (self._p + self._p.T)
        return -0.5 * (nu * nu / var + math.log(2.0 * math.pi * var))


@dataclass(frozen=True)
class TwoModelSpeedOptions:
    """Options of :class:`TwoModelSpeed`.

    Attributes:
        steady: the constant-speed model: no rate, no rate of rate, no process noise;
            it holds the log speed where the measurements put it, so the scale errors of
            a noisy scene (0.3 % per frame sideways) do not become a rate.
        changing: the model whose rate follows accelerations and braking.
        memory: forgetting factor (0..1) of each model's accumulated log-likelihood per
            frame (about 1 / (1 - memory) frames are remembered).
    """

    steady: SpeedFilterOptions = SpeedFilterOptions(
        jerk_density=0.0, rate_sigma=0.0, accel_sigma=0.0
    )
    changing: SpeedFilterOptions = SpeedFilterOptions()
    memory: float = 0.9

    def __post_init__(self) -> None:
        if not 0.0 <= self.memory < 1.0:
            raise InvalidInputError(f"memory must be in [0, 1), got {self.memory!r}")


class TwoModelSpeed:
    """A steady-speed and a changing-speed :class:`SpeedChangeFilter` side by side,
    weighted by how well each predicted the recent measurements (weight_i ~
    exp(sum_k memory^(n-k) log N(innovation_k; 0, S_k))); same interface as
    :class:`SpeedChangeFilter`.

    Args:
        options: :class:`TwoModelSpeedOptions`.
    """

    def __init__(self, options: TwoModelSpeedOptions | None = None) -> None:
        self.options = options or TwoModelSpeedOptions()
        self.models = (
            SpeedChangeFilter(self.options.steady),
            SpeedChangeFilter(self.options.changing),
        )
        self.loglik = np.zeros(2)

    def reset(self) -> None:
        """Forget both models and the weights."""
        for m in self.models:
            m.reset()
        self.loglik = np.zeros(2)

    @property
    def weights(self) -> FloatArray:
        """(2,) probabilities of the steady and the changing model."""
        w = np.exp(self.loglik - self.loglik.max())
        return np.asarray(w / w.sum(), dtype=np.float64)

    @property
    def rate(self) -> float:
        """The weighted ``d ln|t|/dt`` at the last stamp, 1/s."""
        w = self.weights
        return float(w[0] * self.models[0].rate + w[1] * self.models[1].rate)

    def log_change(self, tau: FloatArray) -> FloatArray:
        """The weighted :meth:`SpeedChangeFilter.log_change`."""
        w = self.weights
        return np.asarray(
            w[0] * self.models[0].log_change(tau) + w[1] * self.models[1].log_change(tau)
        )

    def step(self, stamp: int, increment: float | None, dt_ref: float, tau: float) -> float:
        """:meth:`SpeedChangeFilter.step` of both models, then re-weight them. Returns the
        weighted rate, 1/s."""
        for m in self.models:
            m.step(stamp, increment, dt_ref, tau)
        ll = [m.last_loglik for m in self.models]
        if ll[0] is not None and ll[1] is not None:
            self.loglik = self.options.memory * self.loglik + np.array(ll)
        return self.rate
