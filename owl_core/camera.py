"""Calibrated camera model: pixels <-> unit bearings, with lens distortion.

Frames and conventions
----------------------
* Camera optical frame (REP 103): x right, y down, z forward.
* Pixel coordinates ``(u, v)`` follow OpenCV and ROS CameraInfo: the centre of
  the top-left pixel is ``(0, 0)``; the image covers ``[-0.5, W - 0.5] x
  [-0.5, H - 0.5]``.
* ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` (``s`` = skew, usually 0) maps
  distorted normalised coordinates ``(xd, yd)`` to pixels:
  ``u = fx xd + s yd + cx``, ``v = fy yd + cy``.

Distortion models (``D`` in ROS CameraInfo order)
-------------------------------------------------
* ``"plumb_bob"``: ``k1 k2 p1 p2 k3`` (OpenCV radial-tangential).
* ``"rational_polynomial"``: ``k1 k2 p1 p2 k3 k4 k5 k6``. With ``x = X/Z``,
  ``y = Y/Z``, ``r2 = x^2 + y^2``::

      g  = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
      xd = x g + 2 p1 x y + p2 (r2 + 2 x^2)
      yd = y g + p1 (r2 + 2 y^2) + 2 p2 x y

* ``"equidistant"``: ``k1 k2 k3 k4`` (OpenCV fisheye). With ``theta`` the angle
  between the ray and the optical axis::

      theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
      (xd, yd) = theta_d * (X, Y) / sqrt(X^2 + Y^2)

* ``"none"``: pinhole, ``D`` empty (or all zeros).

Validity region
---------------
A distortion polynomial is only invertible where it is monotonic in the radius.
The model finds the first radius (``x``-``y`` plane radius, or ``theta`` for
equidistant) where the radial map stops increasing, and treats rays beyond it as
not imageable: :meth:`CameraModel.bearing_to_pixel` returns NaN there (OpenCV
would fold such rays back into the image), and for points behind the camera
(``Z <= 0``) in the pinhole models. :meth:`CameraModel.pixel_to_bearing` returns
NaN for pixels outside the image of the valid region.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from owl_core.errors import CalibrationError, InvalidInputError

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

__all__ = ["DISTORTION_MODELS", "CameraModel"]

#: Number of distortion coefficients each model takes (ROS CameraInfo ``D``).
DISTORTION_MODELS: dict[str, int] = {
    "plumb_bob": 5,
    "rational_polynomial": 8,
    "equidistant": 4,
    "none": 0,
}

# Largest normalised radius |(x, y)| searched for the pinhole models
# (about 89.4 degrees off axis); largest theta for equidistant.
_R_CAP = 100.0
_THETA_CAP = math.pi
_LIMIT_GRID = 4001
# Newton iterations for the inverse map (convergence is quadratic; a handful
# usually suffices, the bracketed 1-D solver may need bisection steps first).
_MAX_ITER_1D = 100
_MAX_ITER_2D = 20
_TOL = 1e-15


def _radtan_coeffs(model: str, d: FloatArray) -> tuple[float, ...]:
    """(k1, k2, p1, p2, k3, k4, k5, k6), zero-padded."""
    full = np.zeros(8)
    if model in ("plumb_bob", "rational_polynomial"):
        full[: d.shape[0]] = d
    return tuple(float(c) for c in full)


@dataclass(frozen=True, eq=False)
class CameraModel:
    """An intrinsically calibrated camera (ROS CameraInfo semantics).

    Attributes:
        width: image width, pixels (> 0).
        height: image height, pixels (> 0).
        K: (3, 3) float64 intrinsic matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``,
            pixels. Stored read-only.
        D: (k,) float64 distortion coefficients in ROS order for ``distortion_model``.
            Stored read-only.
        distortion_model: one of ``DISTORTION_MODELS``: ``"plumb_bob"``,
            ``"rational_polynomial"``, ``"equidistant"``, ``"none"``.

    Raises:
        CalibrationError: (from construction) non-positive size, non-finite or
            malformed ``K``, non-positive focal length, unknown model name, wrong
            ``D`` length for the model, non-finite ``D``, or a distortion that is
            not monotonic even near the optical axis.
    """

    width: int
    height: int
    K: FloatArray
    D: FloatArray
    distortion_model: str
    #: radial validity limit: normalised radius (pinhole models) or theta (rad,
    #: equidistant) below which the radial map increases monotonically.
    _limit: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise CalibrationError(f"camera {name} must be an integer, got {value!r}")
            if value <= 0:
                raise CalibrationError(f"camera {name} must be positive, got {value}")
            object.__setattr__(self, name, int(value))

        model = self.distortion_model
        if model not in DISTORTION_MODELS:
            raise CalibrationError(
                f"unknown distortion_model {model!r}; expected one of {sorted(DISTORTION_MODELS)}"
            )

        try:
            k = np.array(self.K, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"K must be a numeric (3, 3) matrix, got {self.K!r}") from exc
        if k.size == 9 and k.shape != (3, 3):
            k = k.reshape(3, 3)  # ROS CameraInfo stores K as 9 numbers, row-major
        if k.shape != (3, 3):
            raise CalibrationError(f"K must have shape (3, 3), got {k.shape}")
        if not np.all(np.isfinite(k)):
            raise CalibrationError(f"K must be finite, got {k.tolist()}")
        if not (k[0, 0] > 0.0):
            raise CalibrationError(f"focal length fx = K[0,0] must be positive, got {k[0, 0]}")
        if not (k[1, 1] > 0.0):
            raise CalibrationError(f"focal length fy = K[1,1] must be positive, got {k[1, 1]}")
        if not np.allclose(k[2], (0.0, 0.0, 1.0), rtol=0.0, atol=1e-9) or abs(k[1, 0]) > 1e-9:
            raise CalibrationError(
                f"K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {k.tolist()}"
            )
        k.setflags(write=False)
        object.__setattr__(self, "K", k)

        try:
            d = np.array(self.D, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"D must be a numeric vector, got {self.D!r}") from exc
        if not np.all(np.isfinite(d)):
            raise CalibrationError(f"D must be finite, got {d.tolist()}")
        expected = DISTORTION_MODELS[model]
        if model == "none":
            if np.any(d != 0.0):
                raise CalibrationError(
                    f"distortion_model 'none' takes no coefficients, got D = {d.tolist()}"
                )
        elif d.shape[0] != expected:
            raise CalibrationError(
                f"distortion_model {model!r} needs {expected} coefficients in D, "
                f"got {d.shape[0]}: {d.tolist()}"
            )
        d.setflags(write=False)
        object.__setattr__(self, "D", d)
        object.__setattr__(self, "_limit", self._find_limit())

    # ------------------------------------------------------------------ basics

    @classmethod
    def pinhole(
        cls, width: int, height: int, fx: float, fy: float, cx: float, cy: float
    ) -> CameraModel:
        """A distortion-free camera (``distortion_model = "none"``)."""
        k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)
        return cls(width, height, k, np.zeros(0), "none")

    @property
    def fx(self) -> float:
        """Horizontal focal length, pixels."""
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        """Vertical focal length, pixels."""
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        """Principal point u, pixels."""
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        """Principal point v, pixels."""
        return float(self.K[1, 2])

    @property
    def valid_limit(self) -> float:
        """Radial validity limit: normalised radius (pinhole models, ``inf`` for
        ``"none"``) or angle theta in radians (``"equidistant"``)."""
        return self._limit

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraModel):
            return NotImplemented
        return (
            self.width == other.width
            and self.height == other.height
            and self.distortion_model == other.distortion_model
            and np.array_equal(self.K, other.K)
            and np.array_equal(self.D, other.D)
        )

    def __hash__(self) -> int:
        return hash(
            (self.width, self.height, self.distortion_model, self.K.tobytes(), self.D.tobytes())
        )

    def in_image(self, pixels: npt.ArrayLike, margin_px: float = 0.0) -> BoolArray:
        """Which pixels lie inside the image, at least ``margin_px`` from its border.

        Args:
            pixels: (..., 2) pixel coordinates (u, v); NaN counts as outside.
            margin_px: distance kept from the image border ``[-0.5, W - 0.5]``, pixels.

        Returns:
            (...,) bool mask.
        """
        p = _as_points(pixels, "pixels", 2)
        lo = -0.5 + margin_px
        with np.errstate(invalid="ignore"):
            result: BoolArray = (
                (p[..., 0] >= lo)
                & (p[..., 0] <= self.width - 0.5 - margin_px)
                & (p[..., 1] >= lo)
                & (p[..., 1] <= self.height - 0.5 - margin_px)
            )
        return result

    # ------------------------------------------------------------ projections

    def bearing_to_pixel(self, bearings: npt.ArrayLike) -> FloatArray:
        """Project ray directions to distorted pixel coordinates.

        Args:
            bearings: (..., 3) ray directions in the camera optical frame (any
                non-zero length; unit bearings typically).

        Returns:
            (..., 2) float64 pixels (u, v). NaN for rays that cannot be imaged:
            behind the camera (``Z <= 0``, pinhole models), beyond the validity
            limit of the distortion (see module doc), zero or non-finite input.
        """
        b = _as_points(bearings, "bearings", 3)
        xs, ys, zs = b[..., 0], b[..., 1], b[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.distortion_model == "equidistant":
                rho = np.hypot(xs, ys)
                theta = np.arctan2(rho, zs)
                valid = (theta <= self._limit) & ((rho > 0.0) | (zs > 0.0))
                theta_d = self._theta_d(theta)
                scale = np.where(rho > 0.0, theta_d / np.where(rho > 0.0, rho, 1.0), 0.0)
                xd, yd = xs * scale, ys * scale
            else:
                valid = zs > 0.0
                x = np.where(valid, xs / np.where(valid, zs, 1.0), np.nan)
                y = np.where(valid, ys / np.where(valid, zs, 1.0), np.nan)
                valid &= np.hypot(x, y) < self._limit
                if self.distortion_model == "none":
                    xd, yd = x, y
                else:
                    xd, yd = self._radtan(x, y)
            valid &= np.isfinite(xd) & np.isfinite(yd)
            out = self._to_pixels(xd, yd)
        out[~valid] = np.nan
        return out

    def pixel_to_bearing(self, pixels: npt.ArrayLike) -> FloatArray:
        """Unit bearings of pixels, undoing the lens distortion exactly.

        The distortion is inverted with vectorised, bracketed Newton iterations on
        all points at once (radial 1-D solve, then 2-D Newton for the tangential
        terms), converged to float64 resolution (well below 1e-9 rad).

        Args:
            pixels: (..., 2) distorted pixel coordinates (u, v).

        Returns:
            (..., 3) float64 unit bearings in the camera optical frame; NaN for
            non-finite input and for pixels outside the image of the distortion's
            validity region.
        """
        p = _as_points(pixels, "pixels", 2)
        yd = (p[..., 1] - self.cy) / self.fy
        xd = (p[..., 0] - self.cx - self.K[0, 1] * yd) / self.fx
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.distortion_model == "equidistant":
                return self._undistort_equidistant(xd, yd)
            if self.distortion_model == "none":
                x, y = xd, yd
            else:
                x, y = self._undistort_radtan(xd, yd)
            v = np.stack([x, y, np.ones_like(x)], axis=-1)
            norm = np.sqrt(x * x + y * y + 1.0)  # np.linalg.norm(v, axis=-1), faster
            result: FloatArray = v / norm[..., None]
        return result

    # ---------------------------------------------------------------- helpers

    def _to_pixels(self, xd: FloatArray, yd: FloatArray) -> FloatArray:
        u = self.fx * xd + self.K[0, 1] * yd + self.cx
        v = self.fy * yd + self.cy
        return np.stack([u, v], axis=-1)

    def _theta_d(self, theta: FloatArray) -> FloatArray:
        k1, k2, k3, k4 = (float(c) for c in self.D)
        t2 = theta * theta
        result: FloatArray = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        return result

    def _theta_d_and_slope(self, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
        k1, k2, k3, k4 = (float(c) for c in self.D)
        t2 = theta * theta
        slope = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        return self._theta_d(theta), slope

    def _radial(self, r2: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """g(r2), dg/dr2 and the denominator of the rational radial factor."""
        k1, k2, _, _, k3, k4, k5, k6 = _radtan_coeffs(self.distortion_model, self.D)
        a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        b = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        da = k1 + r2 * (2.0 * k2 + r2 * 3.0 * k3)
        db = k4 + r2 * (2.0 * k5 + r2 * 3.0 * k6)
        return a / b, (da * b - a * db) / (b * b), b

    def _radial_map_and_slope(self, r: FloatArray) -> tuple[FloatArray, FloatArray]:
        """f(r) = r g(r^2) and df/dr for the pinhole models."""
        g, dg, _ = self._radial(r * r)
        return r * g, g + 2.0 * r * r * dg

    def _radtan(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        _, _, p1, p2, *_ = _radtan_coeffs(self.distortion_model, self.D)
        r2 = x * x + y * y
        g, _, _ = self._radial(r2)
        xy = x * y
        xd = x * g + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x)
        yd = y * g + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy
        return xd, yd

    def _find_limit(self) -> float:
        """First radius where the radial map stops increasing (see module doc)."""
        model = self.distortion_model
        if model == "none":
            return math.inf
        if model == "equidistant":
            grid = np.linspace(0.0, _THETA_CAP, _LIMIT_GRID)

            def increasing(t: FloatArray) -> BoolArray:
                _, slope = self._theta_d_and_slope(t)
                ok: BoolArray = slope > 0.0
                return ok

            cap = _THETA_CAP
        else:
            grid = np.tan(np.linspace(0.0, math.atan(_R_CAP), _LIMIT_GRID))

            def increasing(t: FloatArray) -> BoolArray:
                _, slope = self._radial_map_and_slope(t)
                _, _, denom = self._radial(t * t)
                with np.errstate(invalid="ignore"):
                    ok: BoolArray = (slope > 0.0) & (denom > 0.0) & np.isfinite(slope)
                return ok

            cap = _R_CAP
        with np.errstate(all="ignore"):
            ok = increasing(grid)
        if not ok[0]:
            raise CalibrationError(
                f"distortion {model} D = {self.D.tolist()} is not monotonic at the optical axis"
            )
        bad = np.flatnonzero(~ok)
        if bad.size == 0:
            return cap
        lo, hi = float(grid[bad[0] - 1]), float(grid[bad[0]])
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            with np.errstate(all="ignore"):
                good = bool(increasing(np.array([mid]))[0])
            if good:
                lo = mid
            else:
                hi = mid
        if lo < 1e-3:
            raise CalibrationError(
                f"distortion {model} D = {self.D.tolist()} folds over within "
                f"{lo:.2g} of the optical axis"
            )
        return lo

    def _undistort_equidistant(self, xd: FloatArray, yd: FloatArray) -> FloatArray:
        rd = np.hypot(xd, yd)
        theta = _solve_monotone(self._theta_d_and_slope, rd, self._limit)
        rd_safe = np.where(rd > 0.0, rd, 1.0)
        s = np.sin(theta)
        sx = np.where(rd > 0.0, s * xd / rd_safe, 0.0)
        sy = np.where(rd > 0.0, s * yd / rd_safe, 0.0)
        return np.stack([sx, sy, np.cos(theta)], axis=-1)

    def _undistort_radtan(self, xd: FloatArray, yd: FloatArray) -> tuple[FloatArray, FloatArray]:
        _, _, p1, p2, *_ = _radtan_coeffs(self.distortion_model, self.D)
        # 1) radial-only inversion, bracketed, as the starting point.
        rd = np.hypot(xd, yd)
        r = _solve_monotone(self._radial_map_and_slope, rd, self._limit)
        ratio = np.where(rd > 0.0, r / np.where(rd > 0.0, rd, 1.0), 1.0)
        x, y = xd * ratio, yd * ratio
        if p1 == 0.0 and p2 == 0.0:
            return x, y
        # 2) full 2-D Newton including the tangential terms.
        for _ in range(_MAX_ITER_2D):
            r2 = x * x + y * y
            g, dg, _ = self._radial(r2)
            xy = x * y
            fx_ = x * g + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x) - xd
            fy_ = y * g + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy - yd
            j11 = g + 2.0 * x * x * dg + 2.0 * p1 * y + 6.0 * p2 * x
            j12 = 2.0 * xy * dg + 2.0 * p1 * x + 2.0 * p2 * y
            j22 = g + 2.0 * y * y * dg + 6.0 * p1 * y + 2.0 * p2 * x
            det = j11 * j22 - j12 * j12
            dx = (j22 * fx_ - j12 * fy_) / det
            dy = (j11 * fy_ - j12 * fx_) / det
            x = x - dx
            y = y - dy
            step = np.abs(dx) + np.abs(dy)
            if not np.any(step > _TOL * (1.0 + np.abs(x) + np.abs(y))):
                break
        xr, yr = self._radtan(x, y)
        residual = np.hypot(xr - xd, yr - yd)
        bad = ~(residual <= 1e-12 * (1.0 + rd)) | ~(np.hypot(x, y) < self._limit)
        x = np.where(bad, np.nan, x)
        y = np.where(bad, np.nan, y)
        return x, y


def _solve_monotone(
    f: Callable[[FloatArray], tuple[FloatArray, FloatArray]], target: FloatArray, hi_limit: float
) -> FloatArray:
    """Solve ``f(x) = target`` for ``x`` in ``[0, hi_limit]``, vectorised.

    ``f`` returns the value and slope and is increasing on the interval with
    ``f(0) = 0``. Newton steps, falling back to bisection whenever a step leaves
    the bracket. NaN where the target is outside ``[0, f(hi_limit)]`` or not finite.
    """
    hi_value, _ = f(np.array([hi_limit]))
    outside = ~(target >= 0.0) | ~(target <= hi_value[0])
    t = np.where(outside, 0.0, target)
    lo = np.zeros_like(t)
    hi = np.full_like(t, hi_limit)
    x = np.minimum(t, 0.5 * hi_limit)  # identity map is the natural first guess
    for _ in range(_MAX_ITER_1D):
        value, slope = f(x)
        residual = value - t
        above = residual > 0.0
        hi = np.where(above, x, hi)
        lo = np.where(above, lo, x)
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = x - residual / slope
        ok = np.isfinite(newton) & (newton > lo) & (newton < hi)
        x_new = np.where(ok, newton, 0.5 * (lo + hi))
        x_new = np.where(residual == 0.0, x, x_new)
        done = not np.any(np.abs(x_new - x) > _TOL * (1.0 + np.abs(x)))
        x = x_new
        if done:
            break
    result: FloatArray = np.where(outside, np.nan, x)
    return result


def _as_points(values: npt.ArrayLike, name: str, dim: int) -> FloatArray:
    """float64 array of shape (..., dim); raises InvalidInputError quoting the shape."""
    try:
        arr: Any = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name} must be numeric, got {values!r}") from exc
    if arr.ndim == 0 or arr.shape[-1] != dim:
        raise InvalidInputError(f"{name} must have shape (N, {dim}), got {arr.shape}")
    result: FloatArray = arr
    return result
