"""Dense OWL: per-pixel looming L, perceived rotation omega, r/|t| and time to contact.

The sparse engine (:mod:`owl_core.engine`) measures the heading and the gyro bias from
~1000 tracked features; this stage reuses both (it adds no estimate of either) and turns
a dense optical flow into OWL images at a working resolution ``(h, w)``:

1. **flow**: OpenCV DIS dense flow (``cv2.DISOpticalFlow``, preset configurable) from the
   current to the previous working image (so every output is on the current pixel grid),
   and back, for a forward-backward consistency check.
2. **derotate**: the bearing of each working pixel comes from a bearing map precomputed
   once through the camera model (distortion included); the bearing a pixel had in the
   previous frame is looked up in that map at the flowed position (bilinear) and rotated
   into the current camera frame with the gyro rotation over the frame interval (bias
   removed by the caller). ``f = (e_now - R e_prev) / dt`` is the derotated bearing rate at
   the mid bearing ``e_mid``, and ``omega = f x e_mid`` (owl-math.md).
3. **looming**, two routes (owl-math.md), fused by inverse variance:

   - local rule: a weighted affine fit of ``f`` (3 components) against the pixel offset
     over a ``window_px`` square (box filters: no per-pixel Python loop) gives the field's
     gradient ``J`` on the tangent plane; ``L = n^T J n`` with ``n`` perpendicular to
     ``f`` (immune to a leftover rotation, which only adds curl; ``trace(J)/2`` where
     ``f`` vanishes, at the focus of expansion). The fit residual gives its variance;
   - heading route: ``L = s cos(alpha)`` with ``s = omega.(e x h)/|e x h|^2`` (=
     ``|omega| cot(alpha)`` for a static point), the heading ``h`` from the sparse engine.

4. **scaled range**: ``r/|t| = 1/sqrt(L^2 + |omega|^2)`` at the mid time, brought to the
   current stamp by moving the scaled point ``-h_i dt/2`` (``h_i`` the pixel's own heading
   ``(L e + omega x e)/|ToR|``); ``z/|t|`` is its optical-axis component.
5. **confidence** (0..1, per pixel): texture (smallest eigenvalue of the structure tensor),
   forward-backward flow consistency, the local fit's residual against the flow noise, and
   the precision of L relative to ``|ToR|``, the agreement of the two L routes; a pixel
   is *confident* at or above ``min_confidence``.
6. **time to contact** (:func:`time_to_contact`): ``1/L`` for the confident approaching
   pixels inside the path cone (bearings within ``ttc_cone_deg`` of the heading), and the
   shortest of them.

Everything is vectorised over pixels (numpy and OpenCV filters). Units: seconds,
radians, pixels; the working images are ``(h, w)`` float32 with NaN where invalid.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from owl_core.camera import CameraModel
from owl_core.errors import InvalidInputError

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

__all__ = [
    "DIS_PRESETS",
    "DenseOptions",
    "DenseOwl",
    "DenseResult",
    "TimeToContact",
    "dense_owl",
    "time_to_contact",
]

#: DIS presets by name (OpenCV's constants).
DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


@dataclass(frozen=True)
class DenseOptions:
    """Settings of the dense stage, with units.

    Attributes:
        width: working width, pixels (the image is resized to ``width x height``).
        height: working height, pixels.
        preset: DIS preset, one of ``DIS_PRESETS``.
        baseline_frames: the flow is measured between the current image and the one this
            many frames earlier (a longer baseline: more flow for the same flow noise;
            the secant rate refers to the middle of the baseline), count (>= 1).
        window_px: side of the square window of the local affine fit, working pixels
            (odd, >= 3).
        local_step: the local fit runs on a grid this many times coarser than the working
            grid (block means of the field; its window is ``window_px // local_step``
            rounded up to odd) and is interpolated back, count (1 or 2).
        flow_noise_px: 1-sigma noise of the DIS flow per axis, working pixels.
        min_texture: smallest structure-tensor eigenvalue of a *textured* pixel, (grey
            levels / working pixel)^2 (5x5 box average of the gradient products).
        local_variance_scale: factor on the local rule's variance from its window
            residual: DIS flow errors are correlated over its patches, so the residual of
            independent-noise least squares understates the gradient's error (30 matched
            the spread of the local-rule L against the truth on the street scene),
            dimensionless (> 0).
        fb_max_px: forward-backward flow disagreement at which the consistency factor is
            halved, working pixels (pixels beyond 2x this are left out of the local fit).
        heading_min_sin: no heading-route L closer than asin(this) to the focus of
            expansion (or its antipode), dimensionless.
        max_disagreement: a pixel whose two L routes differ by this many combined sigmas
            has its confidence halved (something moving, or an outlier).
        rel_sigma: relative 1-sigma of r/|t| at which the precision factor of the
            confidence is halved, dimensionless.
        min_confidence: confidence (0..1) at or above which a pixel is *confident*.
        ttc_cone_deg: half-angle of the path cone about the heading, degrees.
        ttc_min_pixels: the shortest time to contact is the ``ttc_min_pixels``-th smallest
            over the confident cone pixels (one noisy pixel is not an obstacle), count.
    """

    width: int = 320
    height: int = 240
    preset: str = "medium"
    baseline_frames: int = 3
    window_px: int = 15
    local_step: int = 2
    flow_noise_px: float = 0.05
    min_texture: float = 4.0
    local_variance_scale: float = 30.0
    fb_max_px: float = 0.3
    heading_min_sin: float = 0.05
    max_disagreement: float = 4.0
    rel_sigma: float = 0.1
    min_confidence: float = 0.5
    ttc_cone_deg: float = 10.0
    ttc_min_pixels: int = 20

    def __post_init__(self) -> None:
        for name, low in (
            ("width", 16),
            ("height", 16),
            ("ttc_min_pixels", 1),
            ("baseline_frames", 1),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InvalidInputError(f"dense {name} must be an integer >= {low}, got {value!r}")
        w = self.window_px
        if isinstance(w, bool) or not isinstance(w, int) or w < 3 or w % 2 == 0:
            raise InvalidInputError(f"dense window_px must be an odd integer >= 3, got {w!r}")
        if self.local_step not in (1, 2):
            raise InvalidInputError(f"dense local_step must be 1 or 2, got {self.local_step!r}")
        if self.preset not in DIS_PRESETS:
            raise InvalidInputError(
                f"dense preset must be one of {sorted(DIS_PRESETS)}, got {self.preset!r}"
            )
        for name in ("flow_noise_px", "fb_max_px", "heading_min_sin", "max_disagreement"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InvalidInputError(f"dense {name} must be positive and finite, got {value!r}")
        for name in ("min_texture", "rel_sigma", "local_variance_scale"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InvalidInputError(f"dense {name} must be positive and finite, got {value!r}")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise InvalidInputError(
                f"dense min_confidence must be in [0, 1], got {self.min_confidence!r}"
            )
        if not 0.0 < self.ttc_cone_deg < 90.0:
            raise InvalidInputError(
                f"dense ttc_cone_deg must be in (0, 90), got {self.ttc_cone_deg!r}"
            )


@dataclass(frozen=True)
class TimeToContact:
    """Time to contact inside the path cone for one frame.

    Attributes:
        image: (h, w) float32 ``1/L`` (s) of the confident approaching pixels inside the
            path cone, NaN elsewhere.
        seconds: the shortest time to contact in the cone (the ``ttc_min_pixels``-th
            smallest value of ``image``), s; NaN when there is none.
        pixel: (2,) (u, v) of that pixel in the *input* image (distorted), or None.
        bearing: (3,) unit bearing of that pixel (camera optical frame), or None.
        pixels_in_cone: number of working pixels inside the cone, count.
        confident_in_cone: confident approaching pixels inside the cone, count.
    """

    image: F32
    seconds: float
    pixel: F64 | None
    bearing: F64 | None
    pixels_in_cone: int
    confident_in_cone: int


@dataclass(frozen=True)
class DenseResult:
    """Dense OWL images of one frame, on the ``(h, w)`` working grid.

    Attributes:
        stamp_ns: the current image's stamp, ns.
        looming: (h, w) float32 fused L at the current stamp, 1/s (NaN where invalid).
        omega: (h, w, 3) float32 perceived rotation at the current stamp, 1/s, camera frame.
        range_over_speed: (h, w) float32 r/|t|, s (NaN where invalid).
        depth_over_speed: (h, w) float32 z/|t| (optical-axis component of the scaled
            point), s (NaN where invalid).
        points: (h, w, 3) float32 scaled points ``e * r/|t|``, s.
        confidence: (h, w) float32 in [0, 1] (0 where invalid).
        confident: (h, w) bool, confidence >= ``min_confidence`` and a valid r/|t|.
        textured: (h, w) bool, structure-tensor eigenvalue >= ``min_texture``.
        looming_local: (h, w) float32 L of the local rule (mid time), 1/s.
        looming_heading: (h, w) float32 L of the heading route (mid time), 1/s.
        flow: (h, w, 2) float32 DIS flow from the current to the previous image, working px.
        ttc: :class:`TimeToContact`, or None without a heading.
        timings: seconds per step ("resize", "flow", "derotate", "local", "fuse", "total").
        reasons: why pixels or the whole frame are missing (empty when none).
    """

    stamp_ns: int
    looming: F32
    omega: F32
    range_over_speed: F32
    depth_over_speed: F32
    points: F32
    confidence: F32
    confident: BoolArray
    textured: BoolArray
    looming_local: F32
    looming_heading: F32
    flow: F32
    ttc: TimeToContact | None
    timings: dict[str, float] = field(default_factory=dict)
    reasons: tuple[str, ...] = ()

    @property
    def confident_fraction(self) -> float:
        """Confident pixels over textured pixels (0..1; NaN when nothing is textured)."""
        n = int(np.count_nonzero(self.textured))
        if n == 0:
            return math.nan
        return float(np.count_nonzero(self.confident & self.textured)) / n


class _Grid:
    """The working grid's geometry, precomputed once per camera and working size.

    Attributes (all (h, w) float32 unless noted):
        bearings: (h, w, 3) unit bearings of the working pixel centres.
        basis_a, basis_b: (h, w, 3) orthonormal tangent basis at each bearing.
        e2inv: (h, w, 2, 2) inverse of the bearing's derivative wrt (u, v) working pixels,
            in the tangent basis (maps a tangent offset in radians to working pixels).
        pix_angle: (h, w) angular size of a working pixel, rad (sqrt of |det|).
        full_px: (h, w, 2) float64 the working pixel centres in input-image pixels.
    """

    def __init__(self, camera: CameraModel, width: int, height: int) -> None:
        sx = camera.width / width
        sy = camera.height / height
        u = (np.arange(width) + 0.5) * sx - 0.5
        v = (np.arange(height) + 0.5) * sy - 0.5
        uu, vv = np.meshgrid(u, v)
        self.full_px: F64 = np.stack([uu, vv], axis=-1)
        e = camera.pixel_to_bearing(self.full_px)  # (h, w, 3) float64, NaN outside
        # derivative of the bearing per working pixel (one-sided at the borders)
        e_u = np.gradient(e, axis=1)
        e_v = np.gradient(e, axis=0)
        helper = np.zeros_like(e)
        idx = np.argmin(np.abs(np.nan_to_num(e, nan=1.0)), axis=-1)
        np.put_along_axis(helper, idx[..., None], 1.0, axis=-1)
        a = np.cross(helper, e)
        a /= np.linalg.norm(a, axis=-1, keepdims=True)
        b = np.cross(e, a)
        m = np.empty((*e.shape[:2], 2, 2))
        m[..., 0, 0] = np.sum(a * e_u, axis=-1)
        m[..., 0, 1] = np.sum(a * e_v, axis=-1)
        m[..., 1, 0] = np.sum(b * e_u, axis=-1)
        m[..., 1, 1] = np.sum(b * e_v, axis=-1)
        det = m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
        ok = np.isfinite(det) & (np.abs(det) > 0)
        sdet = np.where(ok, det, 1.0)
        inv = np.empty_like(m)
        inv[..., 0, 0] = m[..., 1, 1] / sdet
        inv[..., 1, 1] = m[..., 0, 0] / sdet
        inv[..., 0, 1] = -m[..., 0, 1] / sdet
        inv[..., 1, 0] = -m[..., 1, 0] / sdet
        inv[~ok] = np.nan
        self.bearings: F32 = e.astype(np.float32)
        self.basis_a: F32 = a.astype(np.float32)
        self.basis_b: F32 = b.astype(np.float32)
        self.e2inv: F32 = inv.astype(np.float32)
        self.pix_angle: F32 = np.sqrt(np.abs(np.where(ok, det, np.nan))).astype(np.float32)
        self.width = width
        self.height = height


def _dot(a: F32, b: F32) -> F32:
    """Per-pixel dot product of (..., 3) arrays -> (...)."""
    out: F32 = a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]
    return out


def _cross(a: F32, b: F32) -> F32:
    """Per-pixel cross product of (..., 3) arrays (faster than np.cross on images)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.float32)
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def _texture(img: npt.NDArray[np.uint8]) -> F32:
    """(h, w) smallest eigenvalue of the 5x5 box-averaged structure tensor, (grey/px)^2."""
    g = img.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    sxx = cv2.boxFilter(gx * gx, -1, (5, 5))
    syy = cv2.boxFilter(gy * gy, -1, (5, 5))
    sxy = cv2.boxFilter(gx * gy, -1, (5, 5))
    half_tr = 0.5 * (sxx + syy)
    disc = np.sqrt(np.maximum(0.25 * (sxx - syy) ** 2 + sxy * sxy, 0.0))
    out: F32 = (half_tr - disc).astype(np.float32)
    return out


class _LocalFit:
    """Weighted affine fit ``f(p + d) ~ f0 + F_u d_u + F_v d_v`` over a square window.

    Moments of the weights and of the weighted field with the offsets, each one
    separable box/ramp filter over the whole image (float64 for the residual's sake).
    """

    def __init__(self, window: int) -> None:
        half = window // 2
        ramp = np.arange(-half, half + 1, dtype=np.float64)
        self.ones = np.ones(window)
        self.ramp = ramp
        self.ramp2 = ramp * ramp
        self.window = window

    def _sep(self, img: F64, kx: F64, ky: F64) -> F64:
        out = cv2.sepFilter2D(img, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_CONSTANT)
        return np.asarray(out, dtype=np.float64)

    def fit(self, f: F64, w: F64) -> tuple[F64, F64, F64, F64]:
        """Fit the (h, w, 3) field ``f`` with (h, w) weights ``w`` (0 = unused).

        Returns:
            grad_u, grad_v: (h, w, 3) derivative of f per working pixel;
            sigma2: (h, w) residual variance of one tangent component of f (inf where
            the window has fewer than 6 weighted pixels or a degenerate layout);
            count: (h, w) sum of the weights in the window.
        """
        one, r, r2 = self.ones, self.ramp, self.ramp2
        m0 = self._sep(w, one, one)
        mx = self._sep(w, r, one)
        my = self._sep(w, one, r)
        mxx = self._sep(w, r2, one)
        myy = self._sep(w, one, r2)
        mxy = self._sep(w, r, r)
        # inverse of the symmetric 3x3 moment matrix, by cofactors
        c00 = mxx * myy - mxy * mxy
        c01 = my * mxy - mx * myy
        c02 = mx * mxy - my * mxx
        c11 = m0 * myy - my * my
        c12 = mx * my - m0 * mxy
        c22 = m0 * mxx - mx * mx
        det = m0 * c00 + mx * c01 + my * c02
        ok = (m0 >= 6.0) & (det > 1e-9 * np.maximum(m0, 1.0) ** 3)
        sdet = np.where(ok, det, 1.0)
        grad_u = np.empty(f.shape)
        grad_v = np.empty(f.shape)
        ssr = self._sep(w * np.sum(f * f, axis=-1), one, one)
        for c in range(3):
            wf = w * f[..., c]
            g0 = self._sep(wf, one, one)
            gx = self._sep(wf, r, one)
            gy = self._sep(wf, one, r)
            b0 = (c00 * g0 + c01 * gx + c02 * gy) / sdet
            bx = (c01 * g0 + c11 * gx + c12 * gy) / sdet
            by = (c02 * g0 + c12 * gx + c22 * gy) / sdet
            grad_u[..., c] = bx
            grad_v[..., c] = by
            ssr -= b0 * g0 + bx * gx + by * gy
        dof = np.maximum(m0 - 3.0, 1.0)
        sigma2 = np.where(ok, np.maximum(ssr, 0.0) / (2.0 * dof), np.inf)
        grad_u[~ok] = np.nan
        grad_v[~ok] = np.nan
        return grad_u, grad_v, sigma2, m0


def _local_gradient(
    f: F32, weight: F32, local_fit: _LocalFit, step: int
) -> tuple[F32, F32, F32, F32]:
    """The local affine fit of the (h, w, 3) field ``f`` with (h, w) weights, on a grid
    ``step`` times coarser (block-weighted means), brought back to (h, w).

    Returns:
        grad_u, grad_v: (h, w, 3) derivative of f per working pixel;
        sigma2: (h, w) residual variance of one tangent component of (block-mean) f;
        frac: (h, w) fraction of the window's weight the fit had (1e-3..1).
    """
    h, w = weight.shape
    wb: Any = weight
    fb: Any = f
    if step > 1:
        size = (w // step, h // step)
        wb = cv2.resize(weight, size, interpolation=cv2.INTER_AREA)
        fw = cv2.resize(f * weight[..., None], size, interpolation=cv2.INTER_AREA)
        fb = fw / np.maximum(wb, 1e-6)[..., None]
    wd = np.asarray(wb, dtype=np.float64)
    fit_u, fit_v, fit_s2, count = local_fit.fit(np.asarray(fb, dtype=np.float64), wd)
    n_win = local_fit.window
    gu: Any = fit_u
    gv: Any = fit_v
    s2: Any = fit_s2
    frac: Any = np.clip(count / (n_win * n_win), 1e-3, 1.0)
    if step > 1:
        up = (w, h)
        gu = cv2.resize(fit_u, up, interpolation=cv2.INTER_LINEAR) / step
        gv = cv2.resize(fit_v, up, interpolation=cv2.INTER_LINEAR) / step
        finite_s2 = np.where(np.isfinite(fit_s2), fit_s2, 1e30)
        s2 = cv2.resize(finite_s2, up, interpolation=cv2.INTER_LINEAR)
        frac = cv2.resize(frac, up, interpolation=cv2.INTER_LINEAR)
    return (
        np.asarray(gu, dtype=np.float32),
        np.asarray(gv, dtype=np.float32),
        np.asarray(s2, dtype=np.float32),
        np.asarray(frac, dtype=np.float32),
    )


def _resize(img: npt.NDArray[np.uint8], width: int, height: int) -> npt.NDArray[np.uint8]:
    if img.shape == (height, width):
        return img
    out = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
    return np.asarray(out, dtype=np.uint8)


def _lookup(image: F32, x: F32, y: F32) -> F32:
    """Bilinear lookup of a (h, w, c) float32 image at (h, w) positions, NaN outside."""
    out = cv2.remap(
        image,
        x,
        y,
        interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(math.nan, math.nan, math.nan, math.nan),
    )
    return np.asarray(out, dtype=np.float32)


def dense_owl(
    grid: _Grid,
    options: DenseOptions,
    dis: cv2.DISOpticalFlow,
    local_fit: _LocalFit,
    prev: npt.NDArray[np.uint8],
    cur: npt.NDArray[np.uint8],
    dt_s: float,
    rotation: F64,
    heading: F64 | None,
    heading_sigma_rad: float,
    stamp_ns: int,
) -> DenseResult:
    """One frame of the dense stage on working images (see the module docstring).

    Args:
        grid: the working grid's geometry.
        options: settings.
        dis: a DIS flow instance.
        local_fit: the window's filters.
        prev, cur: (h, w) uint8 previous and current working images.
        dt_s: frame interval, s (> 0).
        rotation: (3, 3) rotation taking previous-frame bearings to the current frame
            (gyro, bias removed); identity without gyro.
        heading: (3,) unit heading at the current stamp from the sparse engine, or None.
        heading_sigma_rad: its 1-sigma, rad.
        stamp_ns: the current stamp, ns.

    Returns:
        :class:`DenseResult`.
    """
    timings: dict[str, float] = {}
    reasons: list[str] = []
    h, w = cur.shape
    t0 = time.perf_counter()
    none: Any = None
    back = np.asarray(dis.calc(cur, prev, none), dtype=np.float32)
    fwd = np.asarray(dis.calc(prev, cur, none), dtype=np.float32)
    timings["flow"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    xs = np.arange(w, dtype=np.float32)[None, :]
    ys = np.arange(h, dtype=np.float32)[:, None]
    px = xs + back[..., 0]
    py = ys + back[..., 1]
    fwd_at = _lookup(fwd, px, py)
    fb = np.hypot(back[..., 0] + fwd_at[..., 0], back[..., 1] + fwd_at[..., 1])
    e_now = grid.bearings
    e_prev = _lookup(grid.bearings, px, py)
    rot = np.asarray(rotation, dtype=np.float32)
    e_prev = (e_prev.reshape(-1, 3) @ rot.T).reshape(h, w, 3)
    e_mid = e_now + e_prev
    e_mid /= np.sqrt(_dot(e_mid, e_mid))[..., None]
    inv_dt = np.float32(1.0 / dt_s)
    f = (e_now - e_prev) * inv_dt
    f -= _dot(f, e_mid)[..., None] * e_mid
    omega = _cross(f, e_mid)
    tex = _texture(cur)
    textured = tex >= options.min_texture
    finite = np.isfinite(fb) & np.all(np.isfinite(f), axis=-1)
    # flow noise -> noise of each tangent component of f, 1/s
    sigma_f = options.flow_noise_px * grid.pix_angle * inv_dt
    timings["derotate"] = time.perf_counter() - t0

    # ---- local rule
    t0 = time.perf_counter()
    weight = (textured & finite & (fb < 2.0 * options.fb_max_px)).astype(np.float32)
    f0 = np.where(finite[..., None], f, 0.0).astype(np.float32)
    grad_u, grad_v, s2_fit, frac = _local_gradient(f0, weight, local_fit, options.local_step)
    a, b = grid.basis_a, grid.basis_b
    gu, gv = grad_u, grad_v
    f2 = np.stack([_dot(f, a), _dot(f, b)], axis=-1)
    # gradient wrt working pixels in the tangent basis, then per radian: J = F2 E2^-1
    fa_u, fa_v, fb_u, fb_v = _dot(gu, a), _dot(gv, a), _dot(gu, b), _dot(gv, b)
    ei = grid.e2inv
    j00 = fa_u * ei[..., 0, 0] + fa_v * ei[..., 1, 0]
    j01 = fa_u * ei[..., 0, 1] + fa_v * ei[..., 1, 1]
    j10 = fb_u * ei[..., 0, 0] + fb_v * ei[..., 1, 0]
    j11 = fb_u * ei[..., 0, 1] + fb_v * ei[..., 1, 1]
    fx, fy = f2[..., 0], f2[..., 1]
    f_norm2 = fx * fx + fy * fy
    # n = rot90(f)/|f|: n^T J n = (fy^2 j00 - fx fy (j01 + j10) + fx^2 j11) / |f|^2
    eps2 = (3.0 * sigma_f) ** 2
    l_local = (
        fy * fy * j00 - fx * fy * (j01 + j10) + fx * fx * j11 + eps2 * 0.5 * (j00 + j11)
    ) / (f_norm2 + eps2)
    s2 = np.maximum(s2_fit, sigma_f * sigma_f)
    # variance of a gradient of the window fit, per radian (uniform-window approximation,
    # inflated by the fraction of the window the fit could not use)
    n_win = local_fit.window
    step = options.local_step
    s_uu = n_win * (n_win * n_win - 1) * n_win / 12.0 * step * step
    var_local = s2 / (np.float32(s_uu) * grid.pix_angle**2 * frac)
    local_ok = np.isfinite(l_local) & np.isfinite(var_local)
    timings["local"] = time.perf_counter() - t0

    # ---- heading route and fusion
    t0 = time.perf_counter()
    reasons_heading = heading is None
    if heading is not None:
        hv = np.asarray(heading, dtype=np.float32)
        exh = _cross(e_mid, hv[None, None, :])
        sin2 = _dot(exh, exh)
        cos = e_mid @ hv
        route_ok = finite & (sin2 > options.heading_min_sin**2)
        safe2 = np.where(route_ok, sin2, 1.0)
        speed = _dot(omega, exh) / safe2
        l_head = speed * cos
        var_head = s2 * cos * cos / safe2 + (speed * np.float32(heading_sigma_rad)) ** 2 / safe2
        var_head = np.where(route_ok, var_head, np.inf)
        l_head = np.where(route_ok, l_head, np.nan)
        both = local_ok & route_ok
        gap = np.abs(np.where(both, l_local - l_head, 0.0))
        # in combined sigmas; a disagreement lowers the confidence (a mover, an outlier)
        disagree = gap / np.sqrt(
            np.where(both, var_local * options.local_variance_scale + var_head, 1.0)
        )
        use_head = route_ok
    else:
        l_head = np.full((h, w), np.nan, dtype=np.float32)
        var_head = np.full((h, w), np.inf, dtype=np.float32)
        use_head = np.zeros((h, w), dtype=bool)
        disagree = np.zeros((h, w), dtype=np.float32)
        reasons.append("no heading from the sparse engine: L from the local rule only")
    wl = np.where(local_ok, 1.0 / np.maximum(var_local * options.local_variance_scale, 1e-30), 0.0)
    wh = np.where(use_head, 1.0 / np.maximum(var_head, 1e-30), 0.0)
    wsum = wl + wh
    fused_ok = wsum > 0
    safe_w = np.where(fused_ok, wsum, 1.0)
    l_mid = (wl * np.nan_to_num(l_local) + wh * np.nan_to_num(l_head)) / safe_w
    var_l = 1.0 / safe_w
    omega2 = _dot(omega, omega)
    tor2 = l_mid * l_mid + omega2
    ok = fused_ok & finite & (tor2 > 0)
    tor = np.sqrt(np.where(ok, tor2, 1.0))
    ros_mid = 1.0 / tor
    # the pixel's own heading, then the scaled point moved from the mid time to now
    h_i = (l_mid[..., None] * e_mid + _cross(omega, e_mid)) / tor[..., None]
    p_now = e_mid * ros_mid[..., None] - h_i * np.float32(0.5 * dt_s)
    ros_now = np.sqrt(_dot(p_now, p_now))
    ok &= _dot(p_now, e_now) > 0
    safe_ros = np.where(ok, ros_now, 1.0)
    l_now = _dot(h_i, e_now) / safe_ros
    omega_now = _cross(e_now, h_i) / safe_ros[..., None]
    p_out = e_now * ros_now[..., None]

    # ---- confidence
    q_tex = tex / (tex + np.float32(options.min_texture))
    q_fb = 1.0 / (1.0 + (fb / np.float32(options.fb_max_px)) ** 2)
    q_fit = 1.0 / (1.0 + s2_fit / (9.0 * sigma_f * sigma_f))
    rel = np.minimum(np.sqrt(var_l) / tor, np.float32(1e6))
    q_prec = 1.0 / (1.0 + (rel / np.float32(options.rel_sigma)) ** 2)
    q_agree = 1.0 / (1.0 + (disagree / np.float32(options.max_disagreement)) ** 2)
    conf = np.where(ok, q_tex * q_fb * q_fit * q_prec * q_agree, 0.0).astype(np.float32)
    conf = np.nan_to_num(conf, nan=0.0)
    confident = ok & (conf >= options.min_confidence)
    timings["fuse"] = time.perf_counter() - t0
    if not ok.any():
        reasons.append("no pixel has a valid r/|t| (no translation signal)")

    nan = np.float32(np.nan)
    looming_img = np.where(ok, l_now, nan).astype(np.float32)
    result_ttc = None
    if heading is not None and not reasons_heading:
        result_ttc = _ttc(grid, options, looming_img, confident, np.asarray(heading))
    return DenseResult(
        stamp_ns=int(stamp_ns),
        looming=looming_img,
        omega=np.where(ok[..., None], omega_now, nan).astype(np.float32),
        range_over_speed=np.where(ok, ros_now, nan).astype(np.float32),
        depth_over_speed=np.where(ok, p_out[..., 2], nan).astype(np.float32),
        points=np.where(ok[..., None], p_out, nan).astype(np.float32),
        confidence=conf,
        confident=confident,
        textured=textured,
        looming_local=np.where(local_ok, l_local, nan).astype(np.float32),
        looming_heading=np.asarray(l_head, dtype=np.float32),
        flow=back,
        ttc=result_ttc,
        timings=timings,
        reasons=tuple(reasons),
    )


def _ttc(
    grid: _Grid, options: DenseOptions, looming: F32, confident: BoolArray, heading: F64
) -> TimeToContact:
    h = heading / np.linalg.norm(heading)
    cos = grid.bearings @ h.astype(np.float32)
    cone = cos >= math.cos(math.radians(options.ttc_cone_deg))
    approaching = cone & confident & (looming > 0)
    image = np.full(looming.shape, np.nan, dtype=np.float32)
    image[approaching] = 1.0 / looming[approaching]
    n = int(np.count_nonzero(approaching))
    if n == 0:
        return TimeToContact(image, math.nan, None, None, int(np.count_nonzero(cone)), 0)
    flat = np.flatnonzero(approaching)
    values = image.reshape(-1)[flat]
    k = min(options.ttc_min_pixels, n) - 1
    pick = int(np.argpartition(values, k)[k])
    index = flat[pick]
    row, col = divmod(int(index), looming.shape[1])
    return TimeToContact(
        image,
        float(values[pick]),
        grid.full_px[row, col].copy(),
        grid.bearings[row, col].astype(np.float64),
        int(np.count_nonzero(cone)),
        n,
    )


def time_to_contact(
    result: DenseResult, heading: npt.ArrayLike, options: DenseOptions, camera: CameraModel
) -> TimeToContact:
    """Time to contact of a dense result for a given heading and cone (see the module doc).

    Args:
        result: a :class:`DenseResult` on the working grid of ``options``.
        heading: (3,) heading, camera optical frame (normalised here).
        options: its ``ttc_cone_deg`` and ``ttc_min_pixels`` are used.
        camera: the input camera model.

    Returns:
        :class:`TimeToContact`.
    """
    hv = np.asarray(heading, dtype=np.float64)
    if hv.shape != (3,) or not np.all(np.isfinite(hv)) or not np.linalg.norm(hv) > 0:
        raise InvalidInputError(f"heading must be a finite non-zero (3,) vector, got {hv!r}")
    grid = _Grid(camera, options.width, options.height)
    return _ttc(grid, options, result.looming, result.confident, hv)


class DenseOwl:
    """The dense stage for one camera: keeps the previous working image.

    Args:
        camera: the input images' camera model.
        options: settings.
    """

    def __init__(self, camera: CameraModel, options: DenseOptions | None = None) -> None:
        if not isinstance(camera, CameraModel):
            raise InvalidInputError(f"camera must be a CameraModel, got {type(camera).__name__}")
        self.camera = camera
        self.options = opts = options if options is not None else DenseOptions()
        self.grid = _Grid(camera, opts.width, opts.height)
        self._dis = cv2.DISOpticalFlow.create(DIS_PRESETS[opts.preset])
        self._fit = _LocalFit(max(3, (opts.window_px // opts.local_step) | 1))
        # (stamp_ns, working image), newest last, at most baseline_frames
        self._ring: list[tuple[int, npt.NDArray[np.uint8]]] = []

    @property
    def previous_stamp_ns(self) -> int | None:
        """Stamp of the image the next call measures the flow against, ns: the one
        ``baseline_frames - 1`` calls back (fewer right after a reset), None before the
        first call."""
        if not self._ring:
            return None
        k = max(len(self._ring) - self.options.baseline_frames, 0)
        return self._ring[k][0]

    def reset(self) -> None:
        """Forget the kept images."""
        self._ring = []

    def process(
        self,
        image: npt.NDArray[np.uint8],
        stamp_ns: int,
        rotation: npt.ArrayLike | None,
        heading: npt.ArrayLike | None,
        heading_sigma_rad: float = 0.0,
    ) -> DenseResult | None:
        """Dense OWL between the image of ``previous_stamp_ns`` and this one; keeps this one.

        Args:
            image: (H, W) uint8 input image of the camera's size.
            stamp_ns: its stamp, ns.
            rotation: (3, 3) rotation taking bearings at ``previous_stamp_ns`` (read it
                before this call) to this stamp (gyro, bias removed), or None for identity
                (no gyro).
            heading: (3,) unit heading at this stamp from the sparse engine, or None.
            heading_sigma_rad: the heading's 1-sigma, rad (inf is taken as 0.1).

        Returns:
            :class:`DenseResult`, or None for the first frame and after a stamp that did
            not move forward (the kept images are then dropped).

        Raises:
            InvalidInputError: wrong image shape or dtype, malformed rotation or heading.
        """
        t_start = time.perf_counter()
        img = np.asarray(image)
        cam = self.camera
        if img.ndim != 2 or img.dtype != np.uint8 or img.shape != (cam.height, cam.width):
            raise InvalidInputError(
                f"dense image must be a ({cam.height}, {cam.width}) uint8 array, "
                f"got shape {img.shape} dtype {img.dtype}"
            )
        opts = self.options
        cur = _resize(img, opts.width, opts.height)
        t_resize = time.perf_counter() - t_start
        stamp = int(stamp_ns)
        if self._ring and stamp <= self._ring[-1][0]:
            self._ring = []
        prev_stamp = self.previous_stamp_ns
        prev = (
            self._ring[max(len(self._ring) - opts.baseline_frames, 0)][1] if self._ring else None
        )
        self._ring = [*self._ring, (stamp, cur)][-opts.baseline_frames :]
        if prev is None or prev_stamp is None:
            return None
        rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
            raise InvalidInputError(f"rotation must be a finite (3, 3) matrix, got {rot!r}")
        hv: F64 | None = None
        if heading is not None:
            hv = np.asarray(heading, dtype=np.float64)
            if hv.shape != (3,) or not np.all(np.isfinite(hv)) or not np.linalg.norm(hv) > 0:
                raise InvalidInputError(f"heading must be a finite non-zero (3,), got {hv!r}")
            hv = hv / np.linalg.norm(hv)
        sigma = float(heading_sigma_rad)
        if not math.isfinite(sigma):
            sigma = 0.1
        result = dense_owl(
            self.grid,
            opts,
            self._dis,
            self._fit,
            prev,
            cur,
            (int(stamp_ns) - prev_stamp) * 1e-9,
            rot,
            hv,
            sigma,
            int(stamp_ns),
        )
        result.timings["resize"] = t_resize
        result.timings["total"] = time.perf_counter() - t_start
        return result
