"""A Kalman filter on the heading direction: each frame's measurement brought to the image
time by a motion model instead of a finite difference.

Each frame, :func:`owl_core.heading.estimate_motion` gives a heading ``z`` (unit vector,
current camera frame) that refers to the time centroid of the track fits, ``tau`` seconds
before the image (tau <= 0), with a 1-sigma angular uncertainty. Consecutive estimates
share most of their frames, and the camera rotates between frames (the gyro knows by how
much). :class:`HeadingFilter` keeps

    state  h: unit heading at the image time (current camera frame),
           r: its rate of turn in the scene, a tangent vector at h (1/s; zero on a
              straight path, the path curvature x speed on a curving one),

with the error state ``x = (a1, a2, r1, r2)`` in an orthonormal tangent basis ``(u1, u2)``
of ``h`` (``h_true ~ h + a1 u1 + a2 u2``, ``r = r1 u1 + r2 u2``) and covariance ``P``.

* **predict** over ``dt`` with the camera rotation ``R`` (R_{now<-prev}): the heading moves
  by ``r dt`` in the scene, then both are turned into the new camera frame by ``R``;
  ``F = [[I, dt I], [0, I]]`` and the process noise of a white heading acceleration of
  density ``q`` (rad/s^2/sqrt(Hz)): ``Q = q^2 [[dt^3/3, dt^2/2], [dt^2/2, dt]]``.
* **update** with ``z`` at ``tau``: the model predicts ``h + tau r`` (to first order), so
  ``H = [I, tau I]``; the measurement covariance is isotropic, ``(sigma^2 / 2) I`` per
  tangent axis times ``inflation`` (overlapping fit windows make consecutive measurements
  correlated). A measurement whose squared Mahalanobis distance exceeds ``gate`` is
  rejected; ``max_rejections`` in a row restart the filter from the measurement.

On a straight path the filter averages the measurements (the jitter falls with the number
of frames averaged, it is not doubled by extrapolation); on a curving path the rate state
removes the lag of the fit's reference time. Pure numpy; units: radians, seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from owl_core.errors import InvalidInputError
from owl_core.motion import cross

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "HeadingFilter",
    "HeadingFilterOptions",
    "TwoModelHeading",
    "TwoModelOptions",
    "filter_step",
    "tangent_basis",
]


def tangent_basis(h: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Orthonormal (u1, u2), both perpendicular to the unit vector ``h`` (3,), with
    u1 x u2 = h."""
    x, y, z = float(h[0]), float(h[1]), float(h[2])
    if abs(x) <= abs(y) and abs(x) <= abs(z):
        u1 = np.array([0.0, -z, y])
    elif abs(y) <= abs(z):
        u1 = np.array([z, 0.0, -x])
    else:
        u1 = np.array([-y, x, 0.0])
    u1 /= math.sqrt(float(u1 @ u1))
    u2 = np.array([y * u1[2] - z * u1[1], z * u1[0] - x * u1[2], x * u1[1] - y * u1[0]])  # h x u1
    return u1, u2 / math.sqrt(float(u2 @ u2))


def _unit(v: FloatArray) -> FloatArray:
    return np.asarray(v / np.linalg.norm(v), dtype=np.float64)


def _transport(h_old: FloatArray, h_new: FloatArray, vectors: FloatArray) -> FloatArray:
    """Move tangent vectors (K, 3) at h_old to h_new by the minimal rotation h_old -> h_new."""
    axis = cross(h_old, h_new)
    s = float(np.linalg.norm(axis))
    c = float(h_old @ h_new)
    if s < 1e-12:
        return vectors
    k = axis / s
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    rot = np.eye(3) + s * kx + (1.0 - c) * (kx @ kx)
    return np.asarray(vectors @ rot.T, dtype=np.float64)


@dataclass(frozen=True)
class HeadingFilterOptions:
    """Settings of :class:`HeadingFilter`.

    Attributes:
        accel_density: white heading-acceleration density q, rad/s^2/sqrt(Hz): how fast
            the rate of turn of the path may change (0 with ``initial_rate_sigma`` 0: a
            constant heading, the average of every measurement since the last restart).
        initial_rate_sigma: 1-sigma of the rate of turn at the first measurement, rad/s.
        inflation: multiplier (>= 1) of each measurement's variance (correlated
            consecutive measurements).
        gate: squared Mahalanobis distance (2 dof) beyond which a measurement is rejected.
        heading_density: white heading random-walk density, rad/sqrt(s) (process noise on
            the heading itself, besides the rate's; it bounds the memory of a model
            without a rate).
        max_rejections: that many rejections in a row restart the filter (count, >= 1).
        max_gap_s: a larger time between steps restarts the filter, s.
    """

    accel_density: float = 0.5
    initial_rate_sigma: float = 0.5
    inflation: float = 3.0
    gate: float = 13.8
    max_rejections: int = 3
    max_gap_s: float = 0.5
    heading_density: float = 0.0

    def __post_init__(self) -> None:
        for name in ("gate", "max_gap_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InvalidInputError(f"{name} must be positive and finite, got {value!r}")
        for name in ("accel_density", "initial_rate_sigma", "heading_density"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InvalidInputError(f"{name} must be >= 0 and finite, got {value!r}")
        if not self.inflation >= 1.0:
            raise InvalidInputError(f"inflation must be >= 1, got {self.inflation!r}")
        if self.max_rejections < 1:
            raise InvalidInputError(f"max_rejections must be >= 1, got {self.max_rejections!r}")


class HeadingFilter:
    """Heading and its rate of turn, filtered over frames (see the module docstring).

    Args:
        options: :class:`HeadingFilterOptions`.
    """

    def __init__(self, options: HeadingFilterOptions | None = None) -> None:
        self.options = options or HeadingFilterOptions()
        self.reset()

    def reset(self) -> None:
        """Forget the state (the next measurement starts the filter again)."""
        self.heading: FloatArray | None = None
        self.rate = np.zeros(3)
        self.cov = np.eye(4)
        self.stamp_ns: int | None = None
        self.rejections = 0
        self.updates = 0
        #: log-likelihood of the last measurement under the prediction (0 at a restart)
        self.last_loglik = 0.0

    @property
    def sigma_rad(self) -> float:
        """1-sigma (RMS) angular uncertainty of the heading, rad (inf without state)."""
        if self.heading is None:
            return math.inf
        return float(math.sqrt(max(self.cov[0, 0] + self.cov[1, 1], 0.0)))

    def predict(self, stamp_ns: int, rotation: npt.ArrayLike) -> None:
        """Move the state to ``stamp_ns``: the camera rotated by ``rotation`` (3, 3)
        R_{now<-prev} since the previous step. No state or a gap > ``max_gap_s``: reset."""
        if self.heading is None or self.stamp_ns is None:
            return
        dt = (int(stamp_ns) - self.stamp_ns) * 1e-9
        if not 0.0 < dt <= self.options.max_gap_s:
            self.reset()
            return
        rot = np.asarray(rotation, dtype=np.float64)
        if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
            raise InvalidInputError(f"rotation must be a finite (3, 3) matrix, got {rot.shape}")
        h = self.heading
        u1, u2 = tangent_basis(h)
        moved = _unit(h + self.rate * dt)
        basis = _transport(h, moved, np.stack([u1, u2, self.rate]))
        h_new = _unit(rot @ moved)
        basis = basis @ rot.T
        v1, v2 = tangent_basis(h_new)
        # old tangent coordinates -> new ones (both bases are tangent at h_new up to O(eps))
        t = np.array([[v1 @ basis[0], v1 @ basis[1]], [v2 @ basis[0], v2 @ basis[1]]])
        rate = basis[2] - (basis[2] @ h_new) * h_new
        f = np.eye(4)
        f[0:2, 2:4] = np.eye(2) * dt
        tt = np.zeros((4, 4))
        tt[0:2, 0:2] = t
        tt[2:4, 2:4] = t
        q = self.options.accel_density**2
        qm = np.zeros((4, 4))
        qm[0:2, 0:2] = np.eye(2) * q * dt**3 / 3.0
        qm[0:2, 2:4] = qm[2:4, 0:2] = np.eye(2) * q * dt**2 / 2.0
        qm[2:4, 2:4] = np.eye(2) * q * dt
        qm[0:2, 0:2] += np.eye(2) * self.options.heading_density**2 * dt
        cov = tt @ (f @ self.cov @ f.T + qm) @ tt.T
        self.heading, self.rate = h_new, rate
        self.cov = 0.5 * (cov + cov.T)
        self.stamp_ns = int(stamp_ns)

    def update(
        self, stamp_ns: int, heading: npt.ArrayLike, tau_s: float, sigma_rad: float
    ) -> bool:
        """Fuse a heading measured at ``tau_s`` (<= 0) seconds before ``stamp_ns``.

        Call :meth:`predict` for ``stamp_ns`` first. Returns False when the measurement
        was rejected by the gate (the state is then kept, or restarted from the measurement
        after ``max_rejections`` in a row).
        """
        z = np.asarray(heading, dtype=np.float64)
        if z.shape != (3,) or not np.all(np.isfinite(z)) or not np.any(z):
            raise InvalidInputError(f"heading must be a finite non-zero (3,) vector, got {z}")
        if not (math.isfinite(tau_s) and tau_s <= 0.0):
            raise InvalidInputError(f"tau_s must be <= 0 and finite, got {tau_s!r}")
        if not (math.isfinite(sigma_rad) and sigma_rad > 0):
            raise InvalidInputError(f"sigma_rad must be positive and finite, got {sigma_rad!r}")
        z = _unit(z)
        opts = self.options
        var = 0.5 * sigma_rad**2 * opts.inflation
        h = self.heading
        if h is None or self.stamp_ns != int(stamp_ns) or float(z @ h) <= 0.0:
            self._start(stamp_ns, z, tau_s, var)
            return True
        u1, u2 = tangent_basis(h)
        pred = _unit(h + tau_s * self.rate)
        y = np.array([u1 @ (z - pred), u2 @ (z - pred)])
        hm = np.zeros((2, 4))
        hm[:, 0:2] = np.eye(2)
        hm[:, 2:4] = np.eye(2) * tau_s
        s = hm @ self.cov @ hm.T + np.eye(2) * var
        s_inv = np.linalg.inv(s)
        d2 = float(y @ s_inv @ y)
        self.last_loglik = -0.5 * (min(d2, opts.gate) + math.log(float(np.linalg.det(s))))
        if d2 > opts.gate:
            self.rejections += 1
            if self.rejections >= opts.max_rejections:
                self._start(stamp_ns, z, tau_s, var)
            return False
        self.rejections = 0
        gain = self.cov @ hm.T @ s_inv
        dx = gain @ y
        self.heading = _unit(h + dx[0] * u1 + dx[1] * u2)
        rate = self.rate + dx[2] * u1 + dx[3] * u2
        self.rate = rate - (rate @ self.heading) * self.heading
        ikh = np.eye(4) - gain @ hm
        cov = ikh @ self.cov @ ikh.T + gain @ (np.eye(2) * var) @ gain.T  # Joseph form
        self.cov = 0.5 * (cov + cov.T)
        self.updates += 1
        return True

    def _start(self, stamp_ns: int, z: FloatArray, tau_s: float, var: float) -> None:
        # h = z with rate 0; the true heading now is z - tau r with r ~ N(0, r0): its error
        # is correlated with the rate's (cov -tau r0)
        self.heading = z.copy()
        self.rate = np.zeros(3)
        r0 = self.options.initial_rate_sigma**2
        block = np.array([[var + tau_s**2 * r0, -tau_s * r0], [-tau_s * r0, r0]])
        self.cov = np.kron(block, np.eye(2))
        self.stamp_ns = int(stamp_ns)
        self.rejections = 0
        self.updates = 1
        self.last_loglik = 0.0


@dataclass(frozen=True)
class TwoModelOptions:
    """Settings of :class:`TwoModelHeading`.

    Attributes:
        straight: the constant-heading model: no rate of turn and a heading that drifts
            by only 1e-4 rad/sqrt(s) (0.006 deg in a second, 0.06 in 100 s), so it
            averages the measurements of the last seconds (a gate rejection
            ``max_rejections`` times in a row restarts it). The frames' errors are
            correlated over a track's life (a tracking error stays with its feature), so
            only a long average removes them: with 0.003 rad/sqrt(s) instead, 'street'
            went from 0.015/0.033 to 0.025/0.062 deg.
        turning: the model whose rate of turn may change quickly.
        memory: forgetting factor (0..1) of each model's accumulated log-likelihood per
            frame (about 1 / (1 - memory) frames are remembered).
    """

    straight: HeadingFilterOptions = HeadingFilterOptions(
        accel_density=0.0, initial_rate_sigma=0.0, heading_density=1e-4
    )
    turning: HeadingFilterOptions = HeadingFilterOptions()
    memory: float = 0.7

    def __post_init__(self) -> None:
        if not 0.0 <= self.memory < 1.0:
            raise InvalidInputError(f"memory must be in [0, 1), got {self.memory!r}")


class TwoModelHeading:
    """Two :class:`HeadingFilter` run side by side, a straight path and a turning one,
    weighted by how well each predicted the recent measurements (a multiple-model adaptive
    estimator: weight_i ~ exp(sum_k memory^(n-k) log N(innovation_k; 0, S_k)) ).

    On a straight path the straight model averages the measurements without a rate
    to amplify their noise; on a curving path its innovations grow and the turning model,
    whose rate removes the lag, takes over. Same interface as :class:`HeadingFilter`.
    """

    def __init__(self, options: TwoModelOptions | None = None) -> None:
        self.options = options or TwoModelOptions()
        self.models = (HeadingFilter(self.options.straight), HeadingFilter(self.options.turning))
        self.loglik = np.zeros(2)
        self.heading: FloatArray | None = None
        self._sigma = math.inf

    @property
    def stamp_ns(self) -> int | None:
        """Stamp of the last step, ns (None without state)."""
        return self.models[0].stamp_ns

    @property
    def rate(self) -> FloatArray:
        """(3,) the weighted rate of turn, 1/s."""
        w = self.weights
        return np.asarray(w[0] * self.models[0].rate + w[1] * self.models[1].rate)

    @property
    def weights(self) -> FloatArray:
        """(2,) probabilities of the straight and the turning model."""
        ll = self.loglik - self.loglik.max()
        w = np.exp(ll)
        return np.asarray(w / w.sum(), dtype=np.float64)

    @property
    def sigma_rad(self) -> float:
        """1-sigma of the combined heading, rad (inf without state)."""
        return self._sigma if self.heading is not None else math.inf

    def reset(self) -> None:
        """Forget both models' states and the weights."""
        for m in self.models:
            m.reset()
        self.loglik = np.zeros(2)
        self.heading = None
        self._sigma = math.inf

    def predict(self, stamp_ns: int, rotation: npt.ArrayLike) -> None:
        """:meth:`HeadingFilter.predict` of both models."""
        for m in self.models:
            m.predict(stamp_ns, rotation)
        if self.models[0].heading is None or self.models[1].heading is None:
            self.reset()

    def update(
        self, stamp_ns: int, heading: npt.ArrayLike, tau_s: float, sigma_rad: float
    ) -> bool:
        """Update both models, re-weight them, combine. Returns False when both rejected."""
        ok = [m.update(stamp_ns, heading, tau_s, sigma_rad) for m in self.models]
        if self.models[0].updates <= 1 and self.models[1].updates <= 1:
            self.loglik = np.zeros(2)
        else:
            lam = self.options.memory
            self.loglik = lam * self.loglik + np.array([m.last_loglik for m in self.models])
        w = self.weights
        h0, h1 = self.models[0].heading, self.models[1].heading
        assert h0 is not None and h1 is not None
        h = _unit(w[0] * h0 + w[1] * h1)
        spread = [math.acos(min(1.0, float(abs(hi @ h)))) for hi in (h0, h1)]
        var = sum(
            wi * (m.sigma_rad**2 + d * d) for wi, m, d in zip(w, self.models, spread, strict=True)
        )
        self.heading = h
        self._sigma = math.sqrt(var)
        return any(ok)


def filter_step(
    flt: HeadingFilter | TwoModelHeading,
    stamp_ns: int,
    heading: FloatArray,
    tau_s: float,
    sigma_rad: float,
    stamps_ns: npt.NDArray[np.int64],
    rotations: FloatArray,
) -> tuple[FloatArray, float]:
    """One engine frame: predict from the filter's last stamp, update, return (heading at
    ``stamp_ns`` (3,), its 1-sigma rad).

    Args:
        flt: the filter.
        stamp_ns: the image stamp, ns.
        heading: (3,) this frame's measured heading (current camera frame).
        tau_s: the time it refers to, relative to ``stamp_ns``, s (<= 0).
        sigma_rad: its 1-sigma angular uncertainty, rad.
        stamps_ns: (W,) int64 stamps of the track history (column 0 = now, -1 = none).
        rotations: (W, 3, 3) R_{now<-column k} of those columns.
    """
    last = flt.stamp_ns
    if last is not None:
        cols = np.flatnonzero(stamps_ns == last)
        if cols.size and cols[0] > 0:
            flt.predict(stamp_ns, rotations[int(cols[0])])
        else:
            flt.reset()
    flt.update(stamp_ns, heading, min(tau_s, 0.0), max(sigma_rad, 1e-9))
    assert flt.heading is not None
    return flt.heading.copy(), flt.sigma_rad
