"""Dense OWL: per-pixel looming L, perceived rotation omega, r/|t| and time to contact.

The sparse engine (:mod:`owl_core.engine`) measures the heading and the gyro bias from
~1000 tracked features; this stage reuses both (it adds no estimate of either) and turns
a dense optical flow into OWL images at a working resolution ``(h, w)``. One frame is a
chain of stages, each a function returning a small record:

1. **flow** (:func:`_flow`): OpenCV DIS dense flow (``cv2.DISOpticalFlow``, preset
   configurable) from the current to the previous working image (so every output is on
   the current pixel grid), and back, for a forward-backward consistency check.
2. **derotate** (:func:`_derotate`): the bearing of each working pixel comes from a
   bearing map precomputed once through the camera model (distortion included); the
   bearing a pixel had in the previous frame is looked up in that map at the flowed
   position (bilinear) and rotated into the current camera frame with the gyro rotation
   over the frame interval (bias removed by the caller). ``f = (e_now - R e_prev) / dt``,
   made tangent at the mid bearing ``e_mid``, is the derotated bearing rate there, and
   ``omega = f x e_mid`` (owl-math.md), so ``|omega| = |f|``. With a rolling shutter
   (:class:`Readout`) each of the two bearings is rotated from its own row's time into the
   camera frame at the current stamp, and ``dt`` is the time between the two rows.
3. **looming**, two routes (owl-math.md), fused by inverse variance:

   - local rule (:func:`_local_rule`): a weighted affine fit of ``f`` (3 components)
     against the pixel offset over a ``window_px`` square (box/ramp filters on a grid
     ``local_step`` times coarser: no per-pixel Python loop) gives the field's gradient
     ``J`` on the tangent plane; ``L = n^T J n`` with ``n`` perpendicular to ``f``
     (immune to a leftover rotation, which only adds curl; ``trace(J)/2`` where ``f``
     vanishes, at the focus of expansion). The fit residual gives its variance;
   - heading route (:func:`_heading_route`): ``L = s cos(alpha)`` with
     ``s = omega.(e x h)/|e x h|^2 = -f.h / sin^2(alpha)`` (= ``|omega| cot(alpha)`` for
     a static point), the heading ``h`` from the sparse engine.

4. **scaled range** (:func:`_fuse`): ``r/|t| = 1/|ToR|``, ``|ToR| = sqrt(L^2 + |omega|^2)``
   at the mid time, brought to the current stamp by moving the scaled point
   ``p = e_mid/|ToR|`` by ``-h_i dt/2`` (``h_i = (L e_mid + omega x e_mid)/|ToR|
   = (L e_mid - f)/|ToR|``, the pixel's own heading). Since ``f`` is perpendicular to
   ``e_mid`` and ``e_now = e_mid cos(theta/2) + (dt/2) f`` (theta the angle the pixel
   moved), ``r/|t|`` now, ``L`` now and the check that the point is still in front need
   no 3-vector arithmetic; ``z/|t|``, the scaled points and ``omega`` now are computed
   only when asked for (:class:`DenseResult` properties).
5. **confidence** (:func:`_confidence`, 0..1 per pixel): texture (smallest eigenvalue of
   the structure tensor) times the agreement of the two L routes over one plus the
   predicted relative variance of r/|t| (from the variance of L, whose local-rule part
   comes from the fit's residual, and from the forward-backward flow disagreement taken
   as the flow's error); a pixel is *confident* at or above ``min_confidence``.
6. **time to contact** (:func:`_ttc`): ``1/L`` inside the path cone (bearings within
   ``ttc_cone_deg`` of the heading), over textured pixels only (dense flow fills a
   textureless sky from the edges of what lies in front of it, and the L read there is
   not measured), L first averaged over ``ttc_window_px`` squares with
   inverse-variance weights (the k-th smallest of noisy per-pixel values is biased short),
   each window read at ``ttc_lower_sigmas`` of its sigma below its average (the k-th
   smallest of many noisy averages is biased short too), and the shortest (its
   ``ttc_min_pixels``-th smallest value).

Everything is vectorised over pixels (numpy and OpenCV filters) and works in float32 on
per-component planes (``(3, h, w)`` arrays: contiguous, so numpy's SIMD loops run on
them). Units: seconds, radians, pixels; the output images are ``(h, w)`` float32 with NaN
where invalid.

Threads: the global affine fit takes float64 dot products over the working plane, large
enough for OpenBLAS to run them on its thread pool, whose idle threads then busy-wait for
the next call (about 70 % of a core in the node, docs/performance.md). The product's
entry points run BLAS on one thread; a process of your own that runs this stage every
frame should too (``OPENBLAS_NUM_THREADS=1``, or threadpoolctl's ``threadpool_limits(1,
"blas")``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
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
    "ImagePair",
    "Readout",
    "TimeToContact",
    "dense_owl",
    "time_to_contact",
]

#: DIS presets by name: (OpenCV preset, gradient-descent iterations, variational
#: refinement iterations), None keeping OpenCV's value. ``balanced`` is OpenCV's medium
#: (finest scale 1, patch 8, stride 3) with 8 instead of 25 descent and 3 instead of 5
#: refinement iterations: the same r/|t| accuracy and coverage on the dense benchmark,
#: about 25 % less flow time.
DIS_PRESETS: dict[str, tuple[int, int | None, int | None]] = {
    "ultrafast": (cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, None, None),
    "fast": (cv2.DISOPTICAL_FLOW_PRESET_FAST, None, None),
    "balanced": (cv2.DISOPTICAL_FLOW_PRESET_MEDIUM, 8, 3),
    "medium": (cv2.DISOPTICAL_FLOW_PRESET_MEDIUM, None, None),
}

#: variance standing for "no estimate" (finite, so bilinear resampling needs no NaN care)
_NO_VARIANCE = np.float32(1e30)
#: a variance at or above this comes (partly) from a window without an estimate
_MAX_VARIANCE = np.float32(1e20)


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
        fb_max_px: pixels whose forward-backward flow disagreement exceeds 2x this are
            left out of the local fit, working pixels.
        fb_refinement_iterations: variational refinement iterations of the forward flow,
            which serves only the forward-backward check (the backward flow, the one
            measured, keeps the preset's), at most the preset's (ultrafast has none);
            None: the preset's. With 1 instead of the balanced
            preset's 3 the forward flow differs from OpenCV's medium one by 0.08 px
            (median) instead of 0.03, and the dense stage takes 5 % less CPU (0: 9 %); on
            the bench's six static scenes the confident share went from 71.4 to 70.6 %
            of the textured pixels (0: 67.8 %) and the r/|t| errors from 2.57 / 9.10 to
            2.55 / 8.99 % (0: 2.50 / 8.82 %), count (>= 0) or None.
        heading_min_sin: no heading-route L closer than asin(this) to the focus of
            expansion (or its antipode), dimensionless.
        max_disagreement: a pixel whose two L routes differ by this many combined sigmas
            has its confidence halved (something moving, or an outlier).
        rel_sigma: predicted relative 1-sigma of r/|t| (from the variance of L and the
            forward-backward flow disagreement taken as the flow's error) at which the
            precision factor of the confidence is halved, dimensionless.
        min_confidence: confidence (0..1) at or above which a pixel is *confident*.
        ttc_cone_deg: half-angle of the path cone about the heading, degrees.
        ttc_min_pixels: the shortest time to contact is the ``ttc_min_pixels``-th smallest
            over the cone pixels (one noisy pixel is not an obstacle), count.
        ttc_window_px: L is averaged (inverse-variance weights) over a square of this side
            before the time to contact is read from it: the k-th smallest of noisy
            values is biased short by about 2 sigma for k = 20 of ~1000 cone pixels,
            working pixels (odd, >= 1).
        ttc_lower_sigmas: each window's time to contact is read at ``L - z sigma``, with
            ``sigma`` the window average's 1-sigma from its inverse-variance weights
            (pixels taken as independent) and ``z`` this value. The k-th largest of N
            noisy averages lies about ``Phi^-1(1 - k/N)`` of their sigmas above the truth
            (2 for 20 of 1000), so ranking by ``L - z sigma`` takes back that selection
            bias, which window averaging alone leaves wherever many windows see the same
            range (a fronto-parallel face: 14 % short on the bench's cube). DIS errors are
            shared over its patches, so the independent-pixel sigma understates the
            average's; 8 was chosen on the bench's six static scenes (0, 3, 6, 8, 10, 12
            and 20 tried; 0 restores the plain average), dimensionless (>= 0).
    """

    width: int = 320
    height: int = 240
    preset: str = "balanced"
    baseline_frames: int = 3
    window_px: int = 15
    local_step: int = 2
    flow_noise_px: float = 0.05
    min_texture: float = 4.0
    local_variance_scale: float = 30.0
    fb_max_px: float = 0.3
    fb_refinement_iterations: int | None = 1
    heading_min_sin: float = 0.05
    max_disagreement: float = 4.0
    rel_sigma: float = 0.09
    min_confidence: float = 0.5
    ttc_cone_deg: float = 10.0
    ttc_min_pixels: int = 20
    ttc_window_px: int = 25
    ttc_lower_sigmas: float = 8.0

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
        for name, low in (("window_px", 3), ("ttc_window_px", 1)):
            w = getattr(self, name)
            if isinstance(w, bool) or not isinstance(w, int) or w < low or w % 2 == 0:
                raise InvalidInputError(f"dense {name} must be an odd integer >= {low}, got {w!r}")
        fb_iter = self.fb_refinement_iterations
        if fb_iter is not None and (
            isinstance(fb_iter, bool) or not isinstance(fb_iter, int) or fb_iter < 0
        ):
            raise InvalidInputError(
                f"dense fb_refinement_iterations must be an integer >= 0 or None, got {fb_iter!r}"
            )
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
        if not (math.isfinite(self.ttc_lower_sigmas) and self.ttc_lower_sigmas >= 0):
            raise InvalidInputError(
                f"dense ttc_lower_sigmas must be finite and >= 0, got {self.ttc_lower_sigmas!r}"
            )
        if not 0.0 < self.ttc_cone_deg < 90.0:
            raise InvalidInputError(
                f"dense ttc_cone_deg must be in (0, 90), got {self.ttc_cone_deg!r}"
            )


@dataclass(frozen=True)
class TimeToContact:
    """Time to contact inside the path cone for one frame.

    Attributes:
        image: (h, w) float32 ``1/(L - z sigma)`` (s) at the textured pixels inside the
            path cone, L averaged over the textured pixels of ``ttc_window_px`` squares,
            sigma that average's 1-sigma and z ``ttc_lower_sigmas``, where the average is
            approaching, known to 10 % and ``L - z sigma > 0``; NaN elsewhere.
        seconds: the shortest time to contact in the cone (the ``ttc_min_pixels``-th
            smallest value of ``image``), s; NaN when there is none.
        pixel: (2,) (u, v) of that pixel in the *input* image (distorted), or None.
        bearing: (3,) unit bearing of that pixel (camera optical frame), or None.
        pixels_in_cone: number of working pixels inside the cone, count.
        confident_in_cone: pixels of ``image`` (approaching, precise), count.
    """

    image: F32
    seconds: float
    pixel: F64 | None
    bearing: F64 | None
    pixels_in_cone: int
    confident_in_cone: int


@dataclass(frozen=True)
class _Mid:
    """What the outputs computed on demand derive from (all on the working grid).

    Attributes:
        bearings: (h, w, 3) float32 current bearings (the grid's, not a copy).
        e_mid: (3, h, w) float32 unit bearing at the middle of the baseline.
        f: (3, h, w) float32 derotated bearing rate there, 1/s (perpendicular to e_mid).
        looming: (h, w) float32 fused L at the middle of the baseline, 1/s.
        var_l: (h, w) float32 its variance, 1/s^2.
        tor: (h, w) float32 ``|ToR|`` there, 1/s (1 where invalid).
    """

    bearings: F32
    e_mid: F32
    f: F32
    looming: F32
    var_l: F32
    tor: F32


@dataclass(frozen=True)
class DenseResult:
    """Dense OWL images of one frame, on the ``(h, w)`` working grid.

    ``omega``, ``depth_over_speed`` and ``points`` are computed (once) when first read,
    so a caller that publishes only some images pays only for those.

    Attributes:
        stamp_ns: the current image's stamp, ns.
        looming: (h, w) float32 fused L at the current stamp, 1/s (NaN where invalid).
        range_over_speed: (h, w) float32 r/|t|, s (NaN where invalid).
        confidence: (h, w) float32 in [0, 1] (0 where invalid).
        confident: (h, w) bool, confidence >= ``min_confidence`` and a valid r/|t|.
        textured: (h, w) bool, structure-tensor eigenvalue >= ``min_texture``.
        looming_local: (h, w) float32 L of the local rule (mid time), 1/s (NaN where
            the fit had no estimate).
        looming_heading: (h, w) float32 L of the heading route (mid time), 1/s (NaN
            without a heading or near the focus of expansion).
        flow: (h, w, 2) float32 DIS flow from the current to the previous image, working px.
        ttc: :class:`TimeToContact`, or None without a heading.
        mid: the mid-baseline quantities the on-demand outputs derive from.
        timings: seconds per step ("resize", "flow", "derotate", "local", "fuse",
            "total"), wall clock.
        reasons: why pixels or the whole frame are missing (empty when none).
    """

    stamp_ns: int
    looming: F32
    range_over_speed: F32
    confidence: F32
    confident: BoolArray
    textured: BoolArray
    looming_local: F32
    looming_heading: F32
    flow: F32
    ttc: TimeToContact | None
    mid: _Mid
    timings: dict[str, float] = field(default_factory=dict)
    reasons: tuple[str, ...] = ()

    @property
    def confident_fraction(self) -> float:
        """Confident pixels over textured pixels (0..1; NaN when nothing is textured)."""
        n = int(np.count_nonzero(self.textured))
        if n == 0:
            return math.nan
        return float(np.count_nonzero(self.confident & self.textured)) / n

    @cached_property
    def points(self) -> F32:
        """(h, w, 3) float32 scaled points ``e * r/|t|`` at the current stamp, s (NaN
        where invalid)."""
        out: F32 = self.mid.bearings * self.range_over_speed[..., None]
        return out

    @cached_property
    def depth_over_speed(self) -> F32:
        """(h, w) float32 z/|t| (optical-axis component of the scaled point), s (NaN
        where invalid)."""
        out: F32 = self.mid.bearings[..., 2] * self.range_over_speed
        return out

    @cached_property
    def omega(self) -> F32:
        """(h, w, 3) float32 perceived rotation at the current stamp, 1/s, camera frame
        (NaN where invalid): ``e_now x h_i / (r/|t|)`` with the pixel's own heading
        ``h_i = (L e_mid - f)/|ToR|``."""
        m = self.mid
        h_i = (m.looming * m.e_mid - m.f) / m.tor
        e = np.moveaxis(m.bearings, -1, 0)
        out = np.empty_like(m.bearings)
        out[..., 0] = e[1] * h_i[2] - e[2] * h_i[1]
        out[..., 1] = e[2] * h_i[0] - e[0] * h_i[2]
        out[..., 2] = e[0] * h_i[1] - e[1] * h_i[0]
        out /= self.range_over_speed[..., None]
        return out


class _Grid:
    """The working grid's geometry, precomputed once per camera and working size.

    Attributes:
        bearings: (h, w, 3) float32 unit bearings of the working pixel centres (NaN
            where the camera model has none).
        lookup: (h, w, 3) float32 the same with 0 in place of NaN (a bilinear lookup
            touching such a pixel, or the outside, gives a bearing shorter than 1).
        e: (3, h, w) float32 the bearings as planes (0 where invalid).
        valid: (h, w) bool, the camera model gives the pixel a bearing.
        basis_a, basis_b: (3, h, w) float32 orthonormal tangent basis at each bearing.
        e2inv: (4, h, w) float32 inverse of the bearing's derivative wrt (u, v) working
            pixels in the tangent basis, entries (00, 01, 10, 11) (maps a tangent offset
            in radians to working pixels).
        pix_angle: (h, w) float32 angular size of a working pixel, rad (sqrt of |det|).
        xs, ys: (h, w) float32 column and row index of each pixel.
        xc, yc: (h, w) float32 the same from the grid's centre.
        full_px: (h, w, 2) float64 the working pixel centres in input-image pixels.
        row_fraction: (h, w) float32 each centre's input-image row over the input height
            (a rolling shutter sees it that fraction of the readout after the stamp).
    """

    def __init__(self, camera: CameraModel, width: int, height: int) -> None:
        sx = camera.width / width
        sy = camera.height / height
        u = (np.arange(width) + 0.5) * sx - 0.5
        v = (np.arange(height) + 0.5) * sy - 0.5
        uu, vv = np.meshgrid(u, v)
        self.full_px: F64 = np.stack([uu, vv], axis=-1)
        self.row_fraction: F32 = (vv / camera.height).astype(np.float32)
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
        m00 = np.sum(a * e_u, axis=-1)
        m01 = np.sum(a * e_v, axis=-1)
        m10 = np.sum(b * e_u, axis=-1)
        m11 = np.sum(b * e_v, axis=-1)
        det = m00 * m11 - m01 * m10
        ok = np.isfinite(det) & (np.abs(det) > 0)
        sdet = np.where(ok, det, 1.0)
        inv = np.stack([m11 / sdet, -m01 / sdet, -m10 / sdet, m00 / sdet])
        self.valid: BoolArray = ok & np.all(np.isfinite(e), axis=-1)
        self.bearings: F32 = e.astype(np.float32)
        self.lookup: F32 = np.where(self.valid[..., None], e, 0.0).astype(np.float32)
        self.e: F32 = _planes(self.lookup)
        self.basis_a: F32 = _planes(np.where(self.valid[..., None], a, 0.0))
        self.basis_b: F32 = _planes(np.where(self.valid[..., None], b, 0.0))
        self.e2inv: F32 = np.where(self.valid, inv, 0.0).astype(np.float32)
        self.pix_angle: F32 = np.sqrt(np.abs(np.where(self.valid, det, 1.0))).astype(np.float32)
        ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
        self.xs: F32 = xs
        self.ys: F32 = ys
        self.xc: F32 = xs - np.float32(0.5 * (width - 1))
        self.yc: F32 = ys - np.float32(0.5 * (height - 1))
        self.width = width
        self.height = height
        for value in vars(self).values():  # shared by every DenseOwl of this camera (cached)
            if isinstance(value, np.ndarray):
                value.setflags(write=False)


@lru_cache(maxsize=4)
def _grid(camera: CameraModel, width: int, height: int) -> _Grid:
    """The working grid of a camera model (cached: per-camera maps are computed once)."""
    return _Grid(camera, width, height)


def _planes(image: Any) -> F32:
    """(h, w, c) image -> (c, h, w) contiguous float32 planes."""
    return np.ascontiguousarray(np.moveaxis(np.asarray(image, dtype=np.float32), -1, 0))


def _dot(a: F32, b: F32) -> F32:
    """Per-pixel dot product of (3, h, w) planes -> (h, w)."""
    out: F32 = a[0] * b[0]
    out += a[1] * b[1]
    out += a[2] * b[2]
    return out


def _dot_const(a: F32, v: F64) -> F32:
    """Per-pixel dot product of (3, h, w) planes with a constant 3-vector -> (h, w)."""
    out: F32 = a[0] * np.float32(v[0])
    out += a[1] * np.float32(v[1])
    out += a[2] * np.float32(v[2])
    return out


def _texture(img: npt.NDArray[np.uint8]) -> F32:
    """(h, w) smallest eigenvalue of the 5x5 box-averaged structure tensor, (grey/px)^2."""
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    sxx = cv2.boxFilter(gx * gx, -1, (5, 5))
    syy = cv2.boxFilter(gy * gy, -1, (5, 5))
    sxy = cv2.boxFilter(gx * gy, -1, (5, 5))
    half_tr = 0.5 * (sxx + syy)
    diff = 0.5 * (sxx - syy)
    disc = np.sqrt(diff * diff + sxy * sxy)
    out: F32 = half_tr - disc
    return out


class _LocalFit:
    """Weighted affine fit ``f(p + d) ~ f0 + F_u d_u + F_v d_v`` over a square window.

    Moments of the weights and of the weighted field with the offsets, each one
    separable box/ramp filter over the whole image, in the input's float type.
    """

    def __init__(self, window: int) -> None:
        half = window // 2
        ramp = np.arange(-half, half + 1, dtype=np.float64)
        self.ones = np.ones(window)
        self.ramp = ramp
        self.ramp2 = ramp * ramp
        self.window = window

    def fit(self, f: Any, w: Any) -> tuple[Any, Any, Any, Any]:
        """Fit the (c, h, w) field ``f`` (planes) with (h, w) weights ``w`` (0 = unused).

        Returns (in the dtype of ``f``, float32 or float64):
            grad_u, grad_v: (c, h, w) derivative of f per pixel;
            sigma2: (h, w) residual variance of one of two (tangent) components of f
            (inf where the window has fewer than 6 weighted pixels or a degenerate
            layout);
            count: (h, w) sum of the weights in the window.
        """
        depth = cv2.CV_32F if f.dtype == np.float32 else cv2.CV_64F
        one, r, r2 = (k.astype(f.dtype) for k in (self.ones, self.ramp, self.ramp2))

        def sep(img: Any, kx: Any, ky: Any) -> Any:
            return cv2.sepFilter2D(img, depth, kx, ky, borderType=cv2.BORDER_CONSTANT)

        w = w.astype(f.dtype, copy=False)
        m0, mx, my = sep(w, one, one), sep(w, r, one), sep(w, one, r)
        mxx, myy, mxy = sep(w, r2, one), sep(w, one, r2), sep(w, r, r)
        # inverse of the symmetric 3x3 moment matrix, by cofactors
        c00 = mxx * myy - mxy * mxy
        c01 = my * mxy - mx * myy
        c02 = mx * mxy - my * mxx
        c11 = m0 * myy - my * my
        c12 = mx * my - m0 * mxy
        c22 = m0 * mxx - mx * mx
        det = m0 * c00 + mx * c01 + my * c02
        ok = (m0 >= 6.0) & (det > 1e-9 * np.maximum(m0, 1.0) ** 3)
        inv_det = 1.0 / np.where(ok, det, 1.0)
        grad_u = np.empty_like(f)
        grad_v = np.empty_like(f)
        ssr = sep(w * np.sum(f * f, axis=0), one, one)
        for c in range(f.shape[0]):
            wf = w * f[c]
            g0, gx, gy = sep(wf, one, one), sep(wf, r, one), sep(wf, one, r)
            b0 = (c00 * g0 + c01 * gx + c02 * gy) * inv_det
            bx = (c01 * g0 + c11 * gx + c12 * gy) * inv_det
            by = (c02 * g0 + c12 * gx + c22 * gy) * inv_det
            grad_u[c] = bx
            grad_v[c] = by
            ssr -= b0 * g0 + bx * gx + by * gy
        dof = np.maximum(m0 - 3.0, 1.0)
        sigma2 = np.where(ok, np.maximum(ssr, 0.0) / (2.0 * dof), np.inf).astype(f.dtype)
        grad_u[:, ~ok] = np.nan
        grad_v[:, ~ok] = np.nan
        return grad_u, grad_v, sigma2, m0


def _resize(img: npt.NDArray[np.uint8], width: int, height: int) -> npt.NDArray[np.uint8]:
    if img.shape == (height, width):
        return img
    out = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
    return np.asarray(out, dtype=np.uint8)


# ------------------------------------------------------------------------------ stages


@dataclass(frozen=True)
class _Flow:
    """Stage 1, the flow.

    Attributes:
        back: (h, w, 2) float32 DIS flow from the current to the previous image, px.
        map_x, map_y: (h, w) float32 where each current pixel was in the previous image.
        fb2: (h, w) float32 squared forward-backward disagreement, px^2 (about 2e6
            where the flow leaves the image).
    """

    back: F32
    map_x: F32
    map_y: F32
    fb2: F32


def _flow(
    grid: _Grid,
    dis: cv2.DISOpticalFlow,
    dis_check: cv2.DISOpticalFlow,
    prev: npt.NDArray[np.uint8],
    cur: Any,
) -> _Flow:
    """DIS flow current -> previous (``dis``) and previous -> current (``dis_check``, only
    for the check), and their disagreement."""
    none: Any = None
    back = np.asarray(dis.calc(cur, prev, none), dtype=np.float32)
    fwd = np.asarray(dis_check.calc(prev, cur, none), dtype=np.float32)
    map_x = grid.xs + back[..., 0]
    map_y = grid.ys + back[..., 1]
    outside = (1e3, 1e3, 1e3, 1e3)  # px: a disagreement nothing passes
    fwd_at = cv2.remap(fwd, map_x, map_y, cv2.INTER_LINEAR, None, cv2.BORDER_CONSTANT, outside)
    loop = back + fwd_at
    loop *= loop
    return _Flow(back, map_x, map_y, loop[..., 0] + loop[..., 1])


@dataclass(frozen=True)
class _Field:
    """Stage 2, the derotated field at the middle of the baseline.

    Attributes:
        e_mid: (3, h, w) float32 unit mid bearing.
        f: (3, h, w) float32 derotated bearing rate, tangent at ``e_mid``, 1/s.
        f2: (h, w) float32 ``|f|^2 = |omega|^2``, 1/s^2.
        valid: (h, w) bool, the pixel and where it flowed from both have a bearing.
        sigma_f: (h, w) float32 1-sigma of one tangent component of f from the flow
            noise, 1/s.
    """

    e_mid: F32
    f: F32
    f2: F32
    valid: BoolArray
    sigma_f: F32


def _derotate(
    grid: _Grid,
    flow: _Flow,
    rotation: F64,
    dt_s: float,
    flow_noise_px: float,
    readout: Readout | None = None,
) -> _Field:
    """Earlier bearings looked up where the flow points, rotated into the current frame;
    the secant rate made tangent at the mid bearing (see the module docstring). With a
    rolling shutter (``readout``) both bearings are rotated from their own rows' times
    into the camera frame at the current stamp, and each pixel's interval is the stamps'
    plus the readout times of its two rows' difference."""
    looked = cv2.remap(
        grid.lookup, flow.map_x, flow.map_y, cv2.INTER_LINEAR, None, cv2.BORDER_CONSTANT, 0.0
    )
    h, w = grid.height, grid.width
    inv_dt: F32 | np.float32
    if readout is None:
        rot = np.asarray(rotation, dtype=np.float32)
        e_prev = (rot @ looked.reshape(-1, 3).T).reshape(3, h, w)  # planes, current frame
        e_cur = grid.e
        inv_dt = np.float32(1.0 / dt_s)
    else:
        row_prev: F32 = np.asarray(
            cv2.remap(
                grid.row_fraction, flow.map_x, flow.map_y, cv2.INTER_LINEAR, None,
                cv2.BORDER_REPLICATE,
            ),
            dtype=np.float32,
        )  # fmt: skip
        planes: F32 = np.asarray(looked, dtype=np.float32).reshape(-1, 3).T.reshape(3, h, w)
        e_prev = _rotate_from_rows(readout.prev, row_prev, planes)
        e_cur = _rotate_from_rows(readout.cur, grid.row_fraction, grid.e)
        gap = np.float32(dt_s) + (grid.row_fraction - row_prev) * np.float32(readout.readout_s)
        inv_dt = (1.0 / np.maximum(gap, np.float32(1e-6))).astype(np.float32)
    # a bilinear lookup of unit bearings is shorter than 1 by < 1e-5; one touching the
    # outside (0) or an invalid bearing by far more
    valid = (_dot(e_prev, e_prev) > 0.999) & grid.valid
    e_mid = e_cur + e_prev
    e_mid *= 1.0 / np.sqrt(_dot(e_mid, e_mid) + np.float32(1e-30))
    f = e_cur - e_prev
    f -= _dot(f, e_mid) * e_mid
    f *= inv_dt
    f[:, ~valid] = 0.0
    sigma_f = grid.pix_angle * (np.float32(flow_noise_px) * inv_dt)
    return _Field(e_mid, f, _dot(f, f), valid, sigma_f)


def _rotate_from_rows(table: F64, fraction: F32, planes: F32) -> F32:
    """Bearings ``planes`` (3, h, w) seen at row fractions ``fraction`` (h, w) rotated by
    the row-time rotations ``table`` (M + 1, 3, 3), interpolated linearly between its rows:
    (3, h, w) float32. The nine matrix entries are gathered as planes and applied as nine
    plane products (a fifth of an einsum over (h, w, 3, 3): 4 ms at 320x240).
    :meth:`owl_core.rolling_shutter.ReadoutRotations.to_stamp` does the same exactly per
    point (an SO(3) exponential each), for the sparse tracks; over a whole grid it took
    64 ms, and the linear chord differs from it by under 2e-6 here."""
    m = table.shape[0] - 1
    tab = np.asarray(table, dtype=np.float32).reshape(m + 1, 9).T  # (9, M + 1)
    step = tab[:, 1:] - tab[:, :-1]
    x = np.clip(fraction, 0.0, 1.0) * np.float32(m)
    j = np.minimum(x.astype(np.intp), m - 1)
    rot = np.take(tab[:, :-1], j, axis=1)  # (9, h, w): row-major entries of each matrix
    rot += np.take(step, j, axis=1) * (x - j)
    out: F32 = np.empty_like(planes)
    for i in range(3):  # output components: three planes, not a per-pixel loop
        np.multiply(rot[3 * i], planes[0], out=out[i])
        out[i] += rot[3 * i + 1] * planes[1]
        out[i] += rot[3 * i + 2] * planes[2]
    return out


@dataclass(frozen=True)
class _Local:
    """Stage 3a, the local rule, on the working grid.

    Attributes:
        looming: (h, w) float32 L at the mid time, 1/s (0 where ``ok`` is false).
        var: (h, w) float32 its variance from the window residual, 1/s^2.
        s2_fit: (h, w) float32 the fit's residual variance of one tangent component of
            f, 1/s^2 (1e30 where the window had no fit).
        ok: (h, w) bool, the window had a fit.
    """

    looming: F32
    var: F32
    s2_fit: F32
    ok: BoolArray


def _local_rule(
    fit_grid: _Grid,
    local_fit: _LocalFit,
    field: _Field,
    weight: F32,
    step: int,
    noise_px: float,
    inv_dt: float,
) -> _Local:
    """The local rule ``L = n^T J n`` from a weighted affine fit of ``f`` over a window
    on ``fit_grid`` (``step`` times coarser than the working grid: block-weighted means
    of f), brought back to the working grid."""
    h, w = weight.shape
    wb: Any = weight
    fb: Any = field.f
    if step > 1:
        size = (fit_grid.width, fit_grid.height)
        wb = cv2.resize(weight, size, interpolation=cv2.INTER_AREA)
        inv_wb = 1.0 / np.maximum(wb, np.float32(1e-6))
        fb = np.stack([cv2.resize(c * weight, size, interpolation=cv2.INTER_AREA) for c in fb])
        fb *= inv_wb
    # a global weighted affine field taken out first: the fit and its residual do not
    # change, the float32 sums lose less to cancellation
    centred, affine = _minus_global_affine(fit_grid, fb, wb)
    grad_u, grad_v, s2_fit, count = local_fit.fit(centred, wb)
    grad_u += affine[:, 0, None, None].astype(np.float32)
    grad_v += affine[:, 1, None, None].astype(np.float32)
    a, b, ei = fit_grid.basis_a, fit_grid.basis_b, fit_grid.e2inv
    fa_u, fa_v, fb_u, fb_v = _dot(grad_u, a), _dot(grad_v, a), _dot(grad_u, b), _dot(grad_v, b)
    # gradient per fit-grid pixel in the tangent basis, then per radian: J = F2 E2^-1
    j00 = fa_u * ei[0] + fa_v * ei[2]
    j01 = fa_u * ei[1] + fa_v * ei[3]
    j10 = fb_u * ei[0] + fb_v * ei[2]
    j11 = fb_u * ei[1] + fb_v * ei[3]
    fx, fy = _dot(fb, a), _dot(fb, b)
    # angle of one working pixel here, and the flow noise in f it gives
    pix = fit_grid.pix_angle * np.float32(1.0 / step)
    sigma_f = pix * np.float32(noise_px * inv_dt)
    eps2 = 9.0 * sigma_f * sigma_f
    # n = rot90(f)/|f|: n^T J n = (fy^2 j00 - fx fy (j01 + j10) + fx^2 j11) / |f|^2
    num = fy * fy * j00 - fx * fy * (j01 + j10) + fx * fx * j11 + 0.5 * eps2 * (j00 + j11)
    looming = num / (fx * fx + fy * fy + eps2)
    # J is the gradient wrt the *current* position; the mid position moved by -f dt/2,
    # so J_mid = J (I - J dt/2)^-1 ~ J + J^2 dt/2, and n^T J^2 n ~ L^2 (J ~ L I + f g^T)
    looming *= 1.0 + looming * np.float32(0.5 / inv_dt)
    # variance of a gradient of the window fit, per radian (uniform-window approximation,
    # inflated by the fraction of the window the fit could not use)
    n_win = local_fit.window
    s_uu = np.float32(n_win * (n_win * n_win - 1) * n_win / 12.0 * step * step)
    frac = np.clip(count / np.float32(n_win * n_win), 1e-3, 1.0)
    var = np.maximum(s2_fit, sigma_f * sigma_f) / (s_uu * pix * pix * frac)
    ok = np.isfinite(looming) & np.isfinite(var)
    looming = np.where(ok, looming, 0.0).astype(np.float32)
    var = np.where(ok, var, _NO_VARIANCE).astype(np.float32)
    s2_fit = np.where(np.isfinite(s2_fit), s2_fit, _NO_VARIANCE).astype(np.float32)
    if step > 1:
        up = (w, h)
        looming, var, s2_fit = (
            cv2.resize(x, up, interpolation=cv2.INTER_LINEAR) for x in (looming, var, s2_fit)
        )
    return _Local(looming, var, s2_fit, var < _MAX_VARIANCE)


def _minus_global_affine(grid: _Grid, f: F32, w: F32) -> tuple[F32, F64]:
    """(c, h, w) planes minus a weighted least-squares affine fit over the whole grid, and
    that fit's (c, 2) gradient per pixel (d/du, d/dv). The split is exact whatever the
    fit's own accuracy: a gradient of the rest plus the fit's is the field's gradient."""
    xs, ys = grid.xc.ravel(), grid.yc.ravel()
    wx, wy = (w * grid.xc).ravel(), (w * grid.yc).ravel()
    w1 = w.ravel()
    m = np.array(
        [
            [w1.sum(), wx.sum(), wy.sum()],
            [wx.sum(), wx @ xs, wx @ ys],
            [wy.sum(), wy @ xs, wy @ ys],
        ],
        dtype=np.float64,
    )
    grads = np.zeros((f.shape[0], 2))
    rhs = np.array([[w1 @ c.ravel(), wx @ c.ravel(), wy @ c.ravel()] for c in f], np.float64)
    try:
        coef = np.linalg.solve(m, rhs.T).T.astype(np.float32)
    except np.linalg.LinAlgError:
        return f, grads
    if not np.all(np.isfinite(coef)):
        return f, grads
    out = np.empty_like(f)
    for c in range(f.shape[0]):
        out[c] = f[c] - coef[c, 0] - coef[c, 1] * grid.xc - coef[c, 2] * grid.yc
    return out, coef[:, 1:].astype(np.float64)


@dataclass(frozen=True)
class _Route:
    """Stage 3b, the heading route.

    Attributes:
        looming: (h, w) float32 L at the mid time, 1/s (finite; meaningless where not ok).
        var: (h, w) float32 its variance, 1/s^2.
        ok: (h, w) bool, far enough from the focus of expansion and a valid field.
    """

    looming: F32
    var: F32
    ok: BoolArray


def _heading_route(
    field: _Field, s2: F32, heading: F64, heading_sigma_rad: float, min_sin: float
) -> _Route:
    """``L = -f.h cos(alpha) / sin^2(alpha)`` and its variance from the fit residual
    ``s2`` (per tangent component of f) and the heading's 1-sigma."""
    cos = _dot_const(field.e_mid, heading)
    sin2 = 1.0 - cos * cos
    floor = np.float32(min_sin * min_sin)
    ok = field.valid & (sin2 > floor)
    inv_sin2 = 1.0 / np.maximum(sin2, floor)
    speed = _dot_const(field.f, heading)
    speed *= -inv_sin2
    looming = speed * cos
    sigma = speed * np.float32(heading_sigma_rad)
    var = (s2 * cos * cos + sigma * sigma) * inv_sin2
    return _Route(looming, var, ok)


@dataclass(frozen=True)
class _Fused:
    """Stage 4, the two routes fused and brought to the current stamp.

    Attributes:
        l_mid: (h, w) float32 fused L at the mid time, 1/s.
        var_l: (h, w) float32 its variance, 1/s^2.
        tor: (h, w) float32 ``|ToR|`` at the mid time, 1/s (1 where not ok).
        looming: (h, w) float32 L at the current stamp, 1/s.
        range_over_speed: (h, w) float32 r/|t| at the current stamp, s.
        disagree2: (h, w) float32 squared difference of the two routes in combined
            sigmas (0 where either is missing).
        flow_gain2: (h, w) float32 squared gain from an error of ``|f|`` to the relative
            error of ``|ToR|``, s^2: ``((w_h L L_h / |f| + |f|) / |ToR|^2)^2`` with ``w_h``
            the heading route's share of the fusion (``1/|f|^2`` when it carries L, about
            ``|f|^2/L^4``, small, near the focus of expansion where the local rule does).
        ok: (h, w) bool, a valid r/|t|.
    """

    l_mid: F32
    var_l: F32
    tor: F32
    looming: F32
    range_over_speed: F32
    disagree2: F32
    flow_gain2: F32
    ok: BoolArray


def _fuse(
    field: _Field,
    local: _Local,
    route: _Route | None,
    scale: float,
    dt_s: float,
    speed_rate: float = 0.0,
) -> _Fused:
    """Inverse-variance fusion of the two L routes; r/|t| and L at the current stamp, in
    units of the current speed (``speed_rate``: ``d ln|t|/dt``, 1/s)."""
    var_local = local.var * np.float32(scale)
    wl: F32 = local.ok / var_local
    wh: Any = np.float32(0.0)
    l_head: Any = np.float32(0.0)
    disagree2: F32 = np.zeros_like(wl)
    fused_ok = local.ok
    if route is not None:
        wh = route.ok / route.var
        both = local.ok & route.ok
        gap = local.looming - route.looming
        disagree2 = both * (gap * gap) / (var_local + route.var)
        fused_ok = local.ok | route.ok
        l_head = np.where(route.ok, route.looming, 0.0).astype(np.float32)
    wsum = wl + wh
    ok = fused_ok & field.valid
    var_l: F32 = 1.0 / (wsum + ~fused_ok)
    l_mid: F32 = (wl * local.looming + wh * l_head) * var_l
    tor2 = l_mid * l_mid + field.f2
    ok &= tor2 > 0
    tor: F32 = np.sqrt(tor2 + ~ok)
    # the scaled point e_mid/|ToR| moved by -h_i dt/2 (module docstring); with
    # c = e_mid.e_now = sqrt(1 - |f|^2 dt^2/4) and f.e_now = |f|^2 dt/2
    half = np.float32(0.5 * dt_s)
    f2h = field.f2 * half
    c = np.sqrt(np.maximum(1.0 - f2h * half, 0.0))
    k = 1.0 - l_mid * half
    # in units of the speed at the mid time; |t_mid| / |t_now| = exp(-s dt/2) takes it to
    # the current speed (an accelerating camera: the same range is fewer seconds away)
    ros_now = np.sqrt(k * k + f2h * half) / tor
    ros_now *= np.float32(math.exp(-speed_rate * 0.5 * dt_s))
    ok &= k * c + f2h * half > 0  # p_now . e_now > 0: still in front
    looming = (l_mid * c - f2h) / (tor * np.where(ok, ros_now, 1.0))
    tor2 += ~ok
    gain = (wh * var_l * l_mid * l_head + field.f2) / tor2
    gain2 = gain * gain / (field.f2 + np.float32(1e-20))
    return _Fused(l_mid, var_l, tor, looming, ros_now, disagree2, gain2, ok)


def _confidence(
    options: DenseOptions, tex: F32, fb2: F32, field: _Field, fused: _Fused
) -> tuple[F32, BoolArray]:
    """Per-pixel confidence (0..1, 0 where not ok) and the confident mask.

    ``q_tex q_agree / (1 + v / rel_sigma^2)``: texture ``tex/(tex + min_texture)``, the
    agreement of the two L routes ``1/(1 + (d/max_disagreement)^2)`` (d in combined
    sigmas: a mover, an outlier) and the predicted relative variance of r/|t|,
    ``v = var(L)/|ToR|^2 + gain^2 var(|f|)`` with ``var(|f|)`` from the forward-backward
    disagreement (half its square: the errors of two flows add), in 1/s.
    """
    o = options
    px_per_s2 = field.sigma_f * field.sigma_f * np.float32(1.0 / o.flow_noise_px**2)
    with np.errstate(over="ignore"):  # no estimate: inf, confidence 0
        rel_var = fused.var_l / (fused.tor * fused.tor)
        rel_var += 0.5 * fb2 * px_per_s2 * fused.flow_gain2
        den = 1.0 + rel_var * np.float32(1.0 / o.rel_sigma**2)
        den *= 1.0 + fused.disagree2 * np.float32(1.0 / o.max_disagreement**2)
        den *= tex + np.float32(o.min_texture)
    conf = tex / den
    conf[~fused.ok] = 0.0
    np.nan_to_num(conf, copy=False, nan=0.0)
    return conf, fused.ok & (conf >= o.min_confidence)


def _ttc(
    grid: _Grid,
    options: DenseOptions,
    looming: F32,
    var_l: F32,
    heading: F64,
    textured: BoolArray,
) -> TimeToContact:
    """``1/(L - z sigma)`` in the path cone, L averaged over ``ttc_window_px`` squares
    with weights ``1/var(L)`` (valid ``textured`` pixels only), ``sigma = 1/sqrt(sum of
    weights)``, z ``ttc_lower_sigmas``; and the ``ttc_min_pixels``-th shortest of the
    approaching textured cone pixels whose average is known to 10 % (1-sigma).

    Textured only: DIS fills a textureless region with flow from its edges, and the L read
    there follows whatever borders it (on the cube scene the grey sky just above the cube
    read 1.8 to 3.8 s to contact against the cube's 5 to 6 s in 13 of 38 frames)."""
    h = heading / np.linalg.norm(heading)
    cone = _dot_const(grid.e, h) >= np.float32(math.cos(math.radians(options.ttc_cone_deg)))
    valid = np.isfinite(looming) & textured
    weight = np.where(valid, 1.0 / var_l, 0.0).astype(np.float32)
    box = (options.ttc_window_px, options.ttc_window_px)
    wsum = cv2.boxFilter(weight, -1, box, normalize=False)
    lsum = cv2.boxFilter(weight * np.where(valid, looming, 0.0), -1, box, normalize=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = lsum / wsum
        # 1-sigma of the average (independent pixels: optimistic) under 10 % of it
        lower = mean - np.float32(options.ttc_lower_sigmas) / np.sqrt(wsum)
        approaching = cone & valid & (mean > 0) & (wsum * mean * mean > 100.0) & (lower > 0)
    image = np.full(looming.shape, np.nan, dtype=np.float32)
    image[approaching] = 1.0 / lower[approaching]
    n = int(np.count_nonzero(approaching))
    if n == 0:
        return TimeToContact(image, math.nan, None, None, int(np.count_nonzero(cone)), 0)
    flat = np.flatnonzero(approaching)
    values = image.reshape(-1)[flat]
    k = min(options.ttc_min_pixels, n) - 1
    pick = int(np.argpartition(values, k)[k])
    row, col = divmod(int(flat[pick]), looming.shape[1])
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
    grid = _grid(camera, options.width, options.height)
    return _ttc(grid, options, result.looming, result.mid.var_l, hv, result.textured)


# ---------------------------------------------------------------------------- a frame


@dataclass(frozen=True)
class _Setup:
    """What one camera's dense stage keeps between frames (built by :class:`DenseOwl`).

    Attributes:
        grid: the working grid.
        fit_grid: the local fit's grid (``local_step`` times coarser, or ``grid``).
        options: settings.
        dis: the DIS flow instance of the measured (backward) flow.
        dis_check: the one of the forward flow of the check (may be ``dis``).
        local_fit: the window's filters.
    """

    grid: _Grid
    fit_grid: _Grid
    options: DenseOptions
    dis: cv2.DISOpticalFlow
    dis_check: cv2.DISOpticalFlow
    local_fit: _LocalFit


def dense_owl(
    setup: _Setup,
    prev: npt.NDArray[np.uint8],
    cur: npt.NDArray[np.uint8],
    dt_s: float,
    rotation: F64,
    heading: F64 | None,
    heading_sigma_rad: float,
    stamp_ns: int,
    speed_rate: float = 0.0,
    readout: Readout | None = None,
) -> DenseResult:
    """One frame of the dense stage on working images: the chain of stages of the module
    docstring.

    Args:
        setup: grids, settings, flow instance and fit filters.
        prev, cur: (h, w) uint8 previous and current working images.
        dt_s: frame interval, s (> 0).
        rotation: (3, 3) rotation taking previous-frame bearings to the current frame
            (gyro, bias removed); identity without gyro.
        heading: (3,) unit heading at the current stamp from the sparse engine, or None.
        heading_sigma_rad: its 1-sigma, rad.
        stamp_ns: the current stamp, ns.
        speed_rate: ``d ln|t|/dt`` at the current stamp from the sparse engine, 1/s (0:
            a constant speed): r/|t| and L are measured at the middle of the baseline, in
            units of the speed there, and brought to the current speed.

    Returns:
        :class:`DenseResult`.
    """
    o, grid = setup.options, setup.grid
    clock = _Clock()
    flow = _flow(grid, setup.dis, setup.dis_check, prev, cur)
    clock.lap("flow")
    field = _derotate(grid, flow, rotation, dt_s, o.flow_noise_px, readout)
    tex = _texture(cur)
    textured = tex >= o.min_texture
    clock.lap("derotate")
    weight = (textured & field.valid & (flow.fb2 < 4.0 * o.fb_max_px**2)).astype(np.float32)
    local = _local_rule(
        setup.fit_grid, setup.local_fit, field, weight, o.local_step, o.flow_noise_px, 1 / dt_s
    )
    clock.lap("local")
    s2 = np.maximum(local.s2_fit, field.sigma_f * field.sigma_f)
    route = None
    reasons: list[str] = []
    if heading is not None:
        route = _heading_route(field, s2, heading, heading_sigma_rad, o.heading_min_sin)
    else:
        reasons.append("no heading from the sparse engine: L from the local rule only")
    fused = _fuse(field, local, route, o.local_variance_scale, dt_s, speed_rate)
    conf, confident = _confidence(o, tex, flow.fb2, field, fused)
    if not fused.ok.any():
        reasons.append("no pixel has a valid r/|t| (no translation signal)")
    nan = np.float32(np.nan)
    looming = np.where(fused.ok, fused.looming, nan)
    ttc = None if heading is None else _ttc(grid, o, looming, fused.var_l, heading, textured)
    clock.lap("fuse")
    return DenseResult(
        stamp_ns=int(stamp_ns),
        looming=looming,
        range_over_speed=np.where(fused.ok, fused.range_over_speed, nan),
        confidence=conf,
        confident=confident,
        textured=textured,
        looming_local=np.where(local.ok, local.looming, nan),
        looming_heading=(
            np.where(route.ok, route.looming, nan)
            if route is not None
            else np.full(cur.shape, nan, dtype=np.float32)
        ),
        flow=flow.back,
        ttc=ttc,
        mid=_Mid(grid.bearings, field.e_mid, field.f, fused.l_mid, fused.var_l, fused.tor),
        timings=clock.laps,
        reasons=tuple(reasons),
    )


def _dis(preset: int, descent: int | None, refinement: int | None) -> cv2.DISOpticalFlow:
    """A DIS instance of an OpenCV preset with its iterations overridden (None: keep)."""
    dis = cv2.DISOpticalFlow.create(preset)
    if descent is not None:
        dis.setGradientDescentIterations(descent)
    if refinement is not None:
        dis.setVariationalRefinementIterations(refinement)
    return dis


class _Clock:
    """Wall-clock laps of the stages, s."""

    def __init__(self) -> None:
        self.laps: dict[str, float] = {}
        self._t = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = now - self._t
        self._t = now


class DenseOwl:
    """The dense stage for one camera: keeps the previous working images.

    Args:
        camera: the input images' camera model.
        options: settings.
    """

    def __init__(self, camera: CameraModel, options: DenseOptions | None = None) -> None:
        if not isinstance(camera, CameraModel):
            raise InvalidInputError(f"camera must be a CameraModel, got {type(camera).__name__}")
        self.camera = camera
        self.options = opts = options if options is not None else DenseOptions()
        preset, descent, refinement = DIS_PRESETS[opts.preset]
        dis = _dis(preset, descent, refinement)
        dis_check = dis
        fb_iter = opts.fb_refinement_iterations
        if fb_iter is not None and fb_iter < dis.getVariationalRefinementIterations():
            dis_check = _dis(preset, descent, fb_iter)
        step = opts.local_step
        self.grid = _grid(camera, opts.width, opts.height)
        fit_grid = (
            self.grid if step == 1 else _grid(camera, opts.width // step, opts.height // step)
        )
        window = max(3, (opts.window_px // step) | 1)
        self._setup = _Setup(self.grid, fit_grid, opts, dis, dis_check, _LocalFit(window))
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
        speed_rate: float = 0.0,
        readout: Readout | None = None,
    ) -> DenseResult | None:
        """Dense OWL between the image of ``previous_stamp_ns`` and this one; keeps this one.

        ``take`` then ``measure``: the two halves can run in different threads (the
        first keeps the images, the second owns the flow instance).

        Args:
            image: (H, W) uint8 input image of the camera's size.
            stamp_ns: its stamp, ns.
            rotation: (3, 3) rotation taking bearings at ``previous_stamp_ns`` (read it
                before this call) to this stamp (gyro, bias removed), or None for identity
                (no gyro).
            heading: (3,) unit heading at this stamp from the sparse engine, or None.
            heading_sigma_rad: the heading's 1-sigma, rad (inf is taken as 0.1).
            speed_rate: ``d ln|t|/dt`` at this stamp from the sparse engine
                (:attr:`~owl_core.types.FrameResult.speed_rate`), 1/s; 0 for a constant
                speed (non-finite values are taken as 0).
            readout: a rolling shutter's row rotations for this pair (:class:`Readout`);
                then each pixel is derotated from its own row's time and its flow divided
                by the time between its two rows, and ``rotation`` is not used.

        Returns:
            :class:`DenseResult`, or None for the first frame and after a stamp that did
            not move forward (the kept images are then dropped).

        Raises:
            InvalidInputError: wrong image shape or dtype, malformed rotation or heading.
        """
        pair = self.take(image, stamp_ns)
        if pair is None:
            return None
        return self.measure(pair, rotation, heading, heading_sigma_rad, speed_rate, readout)

    def take(self, image: npt.NDArray[np.uint8], stamp_ns: int) -> ImagePair | None:
        """Keep this image (resized to the working grid); the pair to measure, or None for
        the first image and after a stamp that did not move forward (the kept images are
        then dropped).

        Raises:
            InvalidInputError: wrong image shape or dtype.
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
        return ImagePair(prev_stamp, prev, stamp, cur, time.perf_counter() - t_start)

    def measure(
        self,
        pair: ImagePair,
        rotation: npt.ArrayLike | None,
        heading: npt.ArrayLike | None,
        heading_sigma_rad: float = 0.0,
        speed_rate: float = 0.0,
        readout: Readout | None = None,
    ) -> DenseResult:
        """Dense OWL of an image pair from :meth:`take` (see :meth:`process`).

        Raises:
            InvalidInputError: malformed rotation or heading.
        """
        t_start = time.perf_counter()
        rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
            raise InvalidInputError(f"rotation must be a finite (3, 3) matrix, got {rot.tolist()}")
        hv: F64 | None = None
        if heading is not None:
            hv = np.asarray(heading, dtype=np.float64)
            if hv.shape != (3,) or not np.all(np.isfinite(hv)) or not np.linalg.norm(hv) > 0:
                raise InvalidInputError(f"heading must be a finite non-zero (3,), got {hv!r}")
            hv = hv / np.linalg.norm(hv)
        sigma = float(heading_sigma_rad)
        if not math.isfinite(sigma):
            sigma = 0.1
        dt = (pair.stamp_ns - pair.prev_stamp_ns) * 1e-9
        rate = float(speed_rate) if math.isfinite(speed_rate) else 0.0
        result = dense_owl(
            self._setup, pair.prev, pair.cur, dt, rot, hv, sigma, pair.stamp_ns, rate, readout
        )
        result.timings["resize"] = pair.resize_s
        result.timings["total"] = time.perf_counter() - t_start + pair.resize_s
        return result


@dataclass(frozen=True)
class Readout:
    """A rolling shutter's rows of an image pair, each seen at its own time.

    Input-image row ``v`` of an image is seen at its stamp plus ``(v / H) readout_s`` (the
    convention of :mod:`owl_core.rolling_shutter`). The tables hold the gyro rotations
    from ``M + 1`` evenly spaced row times of each image into the camera frame at the
    current stamp (:func:`owl_core.rolling_shutter.readout_rotations` of the two stamps
    gives them); between table rows the rotation is interpolated linearly (M = 8 over a
    30 ms readout at 2 rad/s: steps of 7.5 mrad, chords within 7 microradians).

    Attributes:
        readout_s: readout time, s (> 0).
        prev, cur: (M + 1, 3, 3) rotations taking a bearing seen at row fraction ``j / M``
            of the previous / the current image into the camera frame at the current stamp.
    """

    readout_s: float
    prev: F64
    cur: F64

    def __post_init__(self) -> None:
        ok = math.isfinite(self.readout_s) and 0.0 < self.readout_s < 1.0
        shapes = [np.shape(t) for t in (self.prev, self.cur)]
        good = all(len(sh) == 3 and sh[0] >= 2 and sh[1:] == (3, 3) for sh in shapes)
        if not (ok and good and shapes[0] == shapes[1]):
            raise InvalidInputError(
                f"readout must have readout_s in (0, 1) s and two (M + 1, 3, 3) tables, got "
                f"{self.readout_s!r} and {shapes}"
            )
        if not (np.all(np.isfinite(self.prev)) and np.all(np.isfinite(self.cur))):
            raise InvalidInputError("readout rotation tables must be finite")


@dataclass(frozen=True)
class ImagePair:
    """Two working images the dense stage measures the flow between.

    Attributes:
        prev_stamp_ns, stamp_ns: their stamps, ns (``prev_stamp_ns < stamp_ns``).
        prev, cur: (h, w) uint8 working images.
        resize_s: wall time the resize of ``cur`` took, s.
    """

    prev_stamp_ns: int
    prev: npt.NDArray[np.uint8]
    stamp_ns: int
    cur: npt.NDArray[np.uint8]
    resize_s: float
