"""Camera-IMU rotation, time offset and gyro bias from an ordinary recording (no target).

The images show how the camera turned between consecutive frames; the gyro measures the
same turn in the IMU frame, on the IMU clock. With ``R`` the camera-to-IMU rotation
(``camera_to_imu_rotation_xyzw``: camera-frame vectors into the IMU frame), ``d`` the
time offset (``imu_time_offset``: IMU stamp = camera stamp + d for simultaneous events)
and ``b`` the gyro bias (IMU frame, rad/s), each frame interval ``[a_k, b_k]`` (camera
clock) gives, to first order in the interval's rotation (owl_core.gyro's convention,
``R_{1<-0} = so3_exp(-theta_cam)``)::

    R theta_cam_k  =  integral_{a_k + d}^{b_k + d} omega_imu(s) ds  -  b (b_k - a_k)

Steps (:func:`calibrate`):

1. **visual rotations** (:func:`interval_rotations`): per frame pair, a robust rotation
   fit on the tracked bearings (2-point RANSAC + Kabsch on the inliers); when the
   inliers' residual shows translation parallax well above the tracking noise, the
   rotation of the 5-point essential matrix (``cv2.findEssentialMat`` /
   ``cv2.recoverPose``) instead. Each interval carries a 1-sigma from its residuals.
2. **offset search** (:func:`search_offset`): the rate magnitudes ``|theta_cam_k|`` and
   ``|integral omega_imu|`` do not depend on ``R``; their weighted squared difference
   is minimised over a grid of offsets (coarse 2 ms steps, then 0.1 ms steps).
3. **Wahba / Kabsch** (:func:`wahba`) for ``R`` at that offset.
4. **joint refine**: ``scipy.optimize.least_squares`` (soft-L1 loss) of ``R``, ``d`` and
   ``b`` on the equation above, every interval weighted by its 1-sigma.
5. **uncertainty**: the larger, per value, of the residual covariance
   (``s^2 (J^T J)^-1``) and a moving-block bootstrap over one-second blocks (frame
   errors are correlated in time: the same features, the same translation).
6. **observability** (:func:`check_excitation`): rotation about a single axis leaves the
   rotation about that axis undetermined. With ``M`` the second moment of the camera
   angular rate (3 x 3, rad^2/s^2) and ``lambda_1 >= lambda_2 >= lambda_3`` its
   eigenvalues, :class:`NotExcitedError` is raised when ``sqrt(lambda_2)`` (the RMS
   rate about the second axis) is below ``min_second_axis_rate`` (default 0.1 rad/s).
   Why 0.1 rad/s: a rotation error ``phi`` about the dominant axis changes the predicted
   rate about the other axes by about ``phi sqrt(lambda_2)``; the visual rates carry
   systematic errors of a few 1e-4 rad/s (translation leaking into the rotation fit,
   tracking bias, rolling shutter), so ``phi`` stays within 0.3 deg (5e-3 rad) only
   when ``sqrt(lambda_2) >= 5e-4 / 5e-3 = 0.1`` rad/s.

Units: seconds (the offset is reported in seconds), radians, rad/s; stamps are integer
nanoseconds. Everything is vectorised over features and intervals; the only Python loops
run over frames (one rotation fit each) and over bootstrap replicas.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from owl_core.camera import CameraModel
from owl_core.errors import CalibrationError, InvalidInputError
from owl_core.geometry import matrix_to_quat_xyzw, so3_exp, so3_log
from owl_core.gyro import GyroBuffer
from owl_core.tracker import FeatureTracker, TrackerOptions
from owl_core.types import GyroSamples, ImageFrame

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

__all__ = [
    "CalibrationOptions",
    "CalibrationResult",
    "IntervalRotations",
    "NotExcitedError",
    "calibrate",
    "check_excitation",
    "gyro_increments",
    "interval_rotations",
    "rotation_from_bearings",
    "search_offset",
    "track_rotations",
    "wahba",
]

#: Camera-frame axes and the motion that turns the camera about each (REP 103 optical).
_AXIS_MOTION = (
    "tilt (pitch: nod the camera up and down, about its x axis)",
    "pan (yaw: turn the camera left and right, about its y axis)",
    "roll (about the optical axis)",
)


class NotExcitedError(CalibrationError):
    """The recording's rotation does not excite at least two axes enough to decide.

    Attributes:
        rms_rates: (3,) RMS angular rate about the principal axes, rad/s, descending.
        axes: (3, 3) the principal axes (rows), camera frame.
        advice: what motion to record instead (one line).
    """

    def __init__(self, message: str, rms_rates: FloatArray, axes: FloatArray, advice: str):
        super().__init__(message)
        self.rms_rates = rms_rates
        self.axes = axes
        self.advice = advice


@dataclass(frozen=True)
class CalibrationOptions:
    """Settings of :func:`calibrate`.

    Attributes:
        max_offset_s: the offset search covers [-max_offset_s, +max_offset_s], s (> 0).
        pixel_noise_px: 1-sigma tracking noise, pixels (floor of each interval's sigma and
            the scale of the inlier threshold).
        inlier_px: RANSAC inlier threshold, pixels.
        min_inliers: frame pairs with fewer inliers are not used, count (>= 3).
        parallax_factor: an inlier RMS residual above this many times the tracking noise
            switches a frame pair to the essential-matrix rotation, dimensionless.
        min_second_axis_rate: minimum RMS rate about the second principal axis, rad/s
            (see the module docstring).
        min_intervals: fewer usable frame intervals -> CalibrationError, count.
        bootstrap: moving-block bootstrap replicas (0 = covariance only), count.
        block_s: bootstrap block length, s.
        max_features: features tracked per frame, count.
        exact_gyro: repeat the refine with the exact (Magnus) gyro rotation of each
            interval (the second-order term of a turning axis); False = first order only
            (faster, for the live check).
        seed: seed of RANSAC and bootstrap (results are deterministic).
    """

    max_offset_s: float = 0.2
    pixel_noise_px: float = 0.3
    inlier_px: float = 2.0
    min_inliers: int = 15
    parallax_factor: float = 3.0
    min_second_axis_rate: float = 0.1
    min_intervals: int = 20
    bootstrap: int = 40
    block_s: float = 1.0
    max_features: int = 300
    exact_gyro: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        for name in (
            "max_offset_s",
            "pixel_noise_px",
            "inlier_px",
            "parallax_factor",
            "min_second_axis_rate",
            "block_s",
        ):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise InvalidInputError(f"{name} must be positive and finite, got {value!r}")
        for name, low in (
            ("min_inliers", 3),
            ("min_intervals", 3),
            ("bootstrap", 0),
            ("max_features", 10),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InvalidInputError(f"{name} must be an integer >= {low}, got {value!r}")


@dataclass(frozen=True)
class IntervalRotations:
    """Camera rotations seen in the images between frame pairs, K intervals.

    Attributes:
        t0_ns: (K,) int64 first camera stamp of each interval, ns.
        t1_ns: (K,) int64 second camera stamp, ns (> t0_ns).
        theta: (K, 3) float64 camera-frame rotation increment, rad:
            ``R_{1<-0} = so3_exp(-theta)`` maps bearings at t0 to bearings at t1, so
            ``theta ~ integral of the camera angular velocity`` over the interval.
        sigma: (K,) float64 1-sigma of each component of ``theta``, rad.
        inliers: (K,) int64 features supporting each rotation.
        essential: (K,) bool, True where the essential-matrix rotation was used.
    """

    t0_ns: IntArray
    t1_ns: IntArray
    theta: FloatArray
    sigma: FloatArray
    inliers: IntArray
    essential: npt.NDArray[np.bool_]

    def __len__(self) -> int:
        return int(self.t0_ns.shape[0])

    def subset(self, keep: npt.ArrayLike) -> IntervalRotations:
        """The intervals selected by ``keep`` (bool mask or indices)."""
        k = np.asarray(keep)
        return IntervalRotations(
            self.t0_ns[k],
            self.t1_ns[k],
            self.theta[k],
            self.sigma[k],
            self.inliers[k],
            self.essential[k],
        )


@dataclass(frozen=True)
class CalibrationResult:
    """What :func:`calibrate` found, with 1-sigma uncertainties.

    Attributes:
        camera_to_imu: (3, 3) rotation taking camera-frame vectors into the IMU frame.
        camera_to_imu_xyzw: (4,) the same as a quaternion (x, y, z, w).
        rotation_sigma_rad: (3,) 1-sigma of the rotation about the IMU x, y, z axes, rad.
        time_offset_s: IMU stamp minus camera stamp for simultaneous events, s.
        time_offset_sigma_s: its 1-sigma, s.
        gyro_bias: (3,) gyro bias, IMU frame, rad/s.
        gyro_bias_sigma: (3,) its 1-sigma per axis, rad/s.
        coarse_offset_s: the offset of the magnitude search (step 2), s.
        intervals_used: frame intervals in the fit, count.
        residual_rms: RMS of the whitened residuals at the solution (about 1 when the
            interval sigmas are right), dimensionless.
        rms_rates: (3,) RMS camera angular rate about the principal axes, rad/s.
    """

    camera_to_imu: FloatArray
    camera_to_imu_xyzw: FloatArray
    rotation_sigma_rad: FloatArray
    time_offset_s: float
    time_offset_sigma_s: float
    gyro_bias: FloatArray
    gyro_bias_sigma: FloatArray
    coarse_offset_s: float
    intervals_used: int
    residual_rms: float
    rms_rates: FloatArray


# ----------------------------------------------------------------- visual rotations


def _kabsch(e0: FloatArray, e1: FloatArray, w: FloatArray | None = None) -> FloatArray:
    """Rotations R minimising sum w |e1 - R e0|^2, batched.

    Args:
        e0, e1: (..., N, 3) unit vectors.
        w: (..., N) weights or None.

    Returns:
        (..., 3, 3) rotations.
    """
    a = e1 if w is None else e1 * w[..., None]
    b = np.einsum("...ni,...nj->...ij", a, e0)
    u, _, vt = np.linalg.svd(b)
    det = np.linalg.det(u @ vt)
    d = np.ones((*det.shape, 3))
    d[..., 2] = np.sign(np.where(det == 0, 1.0, det))
    out: FloatArray = (u * d[..., None, :]) @ vt
    return out


def rotation_from_bearings(
    e0: npt.ArrayLike,
    e1: npt.ArrayLike,
    threshold_rad: float,
    rng: np.random.Generator,
    hypotheses: int = 64,
) -> tuple[FloatArray, npt.NDArray[np.bool_], float]:
    """Robust rotation-only fit ``e1 ~ R e0``: 2-point RANSAC, then Kabsch on the inliers.

    Args:
        e0: (N, 3) unit bearings at the first frame.
        e1: (N, 3) unit bearings of the same features at the second frame.
        threshold_rad: inlier threshold on ``|e1 - R e0|``, rad.
        rng: random generator of the samples.
        hypotheses: RANSAC samples, count.

    Returns:
        (R (3, 3) = R_{1<-0}, inlier mask (N,), RMS inlier residual in rad).

    Raises:
        InvalidInputError: shapes differ or N < 2.
    """
    a = np.asarray(e0, dtype=np.float64)
    b = np.asarray(e1, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape != b.shape or a.shape[0] < 2:
        raise InvalidInputError(
            f"bearings must be two (N, 3) arrays with N >= 2, got {a.shape} and {b.shape}"
        )
    n = a.shape[0]
    i = rng.integers(0, n, size=hypotheses)
    j = (i + rng.integers(1, n, size=hypotheses)) % n
    idx = np.stack([i, j], axis=1)
    rots = _kabsch(a[idx], b[idx])  # (H, 3, 3)
    res = np.linalg.norm(b[None] - np.einsum("hij,nj->hni", rots, a), axis=2)  # (H, N)
    best = int(np.argmax(np.sum(res < threshold_rad, axis=1)))
    inl = res[best] < threshold_rad
    rot = rots[best]
    for _ in range(2):
        if np.count_nonzero(inl) < 2:
            break
        rot = _kabsch(a[inl], b[inl])
        r = np.linalg.norm(b - a @ rot.T, axis=1)
        inl = r < threshold_rad
    r = np.linalg.norm(b - a @ rot.T, axis=1)
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else math.inf
    return rot, inl, rms


#: cv2.recoverPose's default distance threshold: points triangulated farther than this many
#: baselines count as at infinity (their depth sign is unreliable).
_POSE_DISTANCE = 50.0


def _recover_pose(
    e_mat: FloatArray, p0: FloatArray, p1: FloatArray, mask: npt.NDArray[np.bool_]
) -> tuple[int, FloatArray, FloatArray, npt.NDArray[np.bool_]]:
    """``cv2.recoverPose``'s cheirality check, vectorised: of the four poses of the
    essential matrix ``e_mat`` (3, 3) (R1 or R2, +t or -t), the one that puts the most of
    the ``mask`` (N,) points in front of both cameras and nearer than 50 baselines.

    Each point is triangulated as ``cv2.triangulatePoints`` does (the DLT rows of both
    views from ``p0``, ``p1`` (N, 2) normalised coordinates, the right singular vector of
    the smallest singular value), in one batched numpy SVD per rotation (the poses with
    +t and -t share it) instead of one OpenCV call per pose (about 9 ms for 120 points in
    OpenCV 4.13, an eighth of that here). Returns (points passing, R (3, 3), unit t (3,),
    their mask (N,)); of equal counts the earlier pose wins, in OpenCV's order.
    """
    r1, r2, t = (np.asarray(a, dtype=np.float64) for a in cv2.decomposeEssentialMat(e_mat))
    t = t.reshape(3)
    x0, y0 = p0[:, 0], p0[:, 1]
    x1, y1 = p1[:, :1], p1[:, 1:2]
    zero, one = np.zeros_like(x0), np.ones_like(x0)
    found: list[tuple[int, FloatArray, FloatArray, npt.NDArray[np.bool_]]] = []
    for rot in (r1, r2):
        pose = np.concatenate([rot, t[:, None]], axis=1)  # (3, 4)
        # DLT rows (N, 4, 4): x P[2] - P[0], y P[2] - P[1] for P0 = [I | 0] and P1 = pose
        rows = np.stack(
            [
                np.stack([-one, zero, x0, zero], axis=1),
                np.stack([zero, -one, y0, zero], axis=1),
                x1 * pose[2] - pose[0],
                y1 * pose[2] - pose[1],
            ],
            axis=1,
        )
        # the homogeneous solution: the right singular vector of the smallest value
        q = np.linalg.svd(rows)[2][:, 3]  # (N, 4)
        with np.errstate(divide="ignore", invalid="ignore"):
            point = q[:, :3] / q[:, 3:]
        depth_sign = q[:, 2] * q[:, 3]
        d0 = point[:, 2]
        d1 = point @ rot[2] + t[2]
        # with -t the rows' last column changes sign, so the solution's homogeneous
        # coordinate does: the point and both depths change sign
        for sign in (1.0, -1.0):
            a, b = sign * d0, sign * d1
            front = sign * depth_sign > 0
            good = mask & front & (a < _POSE_DISTANCE) & (b > 0) & (b < _POSE_DISTANCE)
            found.append((int(np.count_nonzero(good)), rot, sign * t, good))
    found = [found[0], found[2], found[1], found[3]]  # OpenCV's order: R1 t, R2 t, R1 -t, ...
    return max(found, key=lambda item: item[0])  # the first of equal counts


def _essential_rotation(
    e0: FloatArray, e1: FloatArray, threshold_rad: float
) -> tuple[FloatArray, npt.NDArray[np.bool_], float] | None:
    """Rotation of the 5-point essential matrix (RANSAC) on bearings in front of the camera:
    (R_{1<-0}, inlier mask (N,), RMS epipolar angle of the inliers, rad), or None."""
    front = (e0[:, 2] > 0.05) & (e1[:, 2] > 0.05)
    if np.count_nonzero(front) < 8:
        return None
    p0 = e0[front, :2] / e0[front, 2:]
    p1 = e1[front, :2] / e1[front, 2:]
    e_mat, mask = cv2.findEssentialMat(
        p0, p1, focal=1.0, pp=(0.0, 0.0), method=cv2.RANSAC, prob=0.999, threshold=threshold_rad
    )
    if e_mat is None or e_mat.shape != (3, 3):
        return None
    count, rot, tv, inl_f = _recover_pose(
        np.asarray(e_mat, dtype=np.float64), p0, p1, mask.reshape(-1) > 0
    )
    if count < 8:
        return None
    n = np.cross(tv[None, :], e0[front] @ rot.T)  # epipolar-plane normals
    nn = np.linalg.norm(n, axis=1)
    ang = np.abs(np.einsum("ni,ni->n", n, e1[front])) / np.maximum(nn, 1e-12)
    inl = np.zeros(e0.shape[0], dtype=bool)
    inl[np.flatnonzero(front)[inl_f]] = True
    rms = float(np.sqrt(np.mean(ang[inl_f] ** 2))) if inl_f.any() else math.inf
    return np.asarray(rot, dtype=np.float64), inl, rms


def interval_rotations(
    pairs: Iterable[tuple[int, int, FloatArray, FloatArray]],
    focal_px: float,
    options: CalibrationOptions | None = None,
) -> IntervalRotations:
    """Camera rotation increments from matched bearings of consecutive frames.

    Args:
        pairs: per frame pair ``(t0_ns, t1_ns, e0 (N, 3), e1 (N, 3))``: unit bearings of
            the same features at the two camera stamps (camera frame).
        focal_px: focal length, pixels (converts pixel thresholds to angles).
        options: settings (noise, thresholds, seed).

    Returns:
        The :class:`IntervalRotations` of the pairs with at least ``min_inliers``
        inliers, in the given order.
    """
    opts = options if options is not None else CalibrationOptions()
    rng = np.random.default_rng(opts.seed)
    noise = opts.pixel_noise_px / focal_px
    thr = opts.inlier_px / focal_px
    t0s: list[int] = []
    t1s: list[int] = []
    thetas: list[FloatArray] = []
    sigmas: list[float] = []
    counts: list[int] = []
    ess: list[bool] = []
    for t0, t1, e0, e1 in pairs:  # one robust fit per frame pair
        if e0.shape[0] < opts.min_inliers or t1 <= t0:
            continue
        rot, inl, rms = rotation_from_bearings(e0, e1, thr, rng)
        used_essential = False
        if rms > opts.parallax_factor * noise or np.count_nonzero(inl) < 0.5 * e0.shape[0]:
            found = _essential_rotation(e0, e1, thr)
            if found is not None and np.count_nonzero(found[1]) >= opts.min_inliers:
                rot, inl, rms = found
                used_essential = True
        m = int(np.count_nonzero(inl))
        if m < opts.min_inliers:
            continue
        # components of a rotation fitted to m bearings: sigma ~ residual / sqrt(m)
        # (x sqrt(3) for the essential rotation, which also carries the translation)
        sigma = max(rms, noise) / math.sqrt(m) * (math.sqrt(3.0) if used_essential else 1.0)
        t0s.append(int(t0))
        t1s.append(int(t1))
        thetas.append(-so3_log(rot))
        sigmas.append(sigma)
        counts.append(m)
        ess.append(used_essential)
    return IntervalRotations(
        np.asarray(t0s, dtype=np.int64),
        np.asarray(t1s, dtype=np.int64),
        np.asarray(thetas, dtype=np.float64).reshape(-1, 3),
        np.asarray(sigmas, dtype=np.float64),
        np.asarray(counts, dtype=np.int64),
        np.asarray(ess, dtype=bool),
    )


def track_rotations(
    frames: Iterable[ImageFrame],
    camera: CameraModel,
    options: CalibrationOptions | None = None,
) -> IntervalRotations:
    """Track features through ``frames`` and fit each consecutive pair's rotation.

    Args:
        frames: grey images in stamp order (stamps strictly increasing).
        camera: the camera model (distortion included).
        options: settings (``max_features`` and the fit's thresholds).

    Returns:
        :func:`interval_rotations` of the tracked pairs.
    """
    opts = options if options is not None else CalibrationOptions()
    span = 1  # consecutive frames: history column 0 (current) and 1 (previous)
    tracker = FeatureTracker(TrackerOptions(max_features=opts.max_features, history_len=span + 1))

    def pairs() -> Iterable[tuple[int, int, FloatArray, FloatArray]]:
        for frame in frames:
            tracks = tracker.track(frame.image, frame.stamp_ns)
            stamps = tracks.stamps_ns
            if stamps.shape[0] <= span or stamps[span] < 0:
                continue
            h = tracks.history
            ok = np.all(np.isfinite(h[:, 0]), axis=1) & np.all(np.isfinite(h[:, span]), axis=1)
            if np.count_nonzero(ok) < opts.min_inliers:
                continue
            e1 = camera.pixel_to_bearing(h[ok, 0])
            e0 = camera.pixel_to_bearing(h[ok, span])
            good = np.all(np.isfinite(e0), axis=1) & np.all(np.isfinite(e1), axis=1)
            yield int(stamps[span]), int(stamps[0]), e0[good], e1[good]

    return interval_rotations(pairs(), max(camera.fx, camera.fy), opts)


# ---------------------------------------------------------------------------- gyro


def _clean_gyro(gyro: GyroSamples) -> tuple[IntArray, FloatArray]:
    t = np.asarray(gyro.stamp_ns, dtype=np.int64).reshape(-1)
    w = np.asarray(gyro.angular_velocity, dtype=np.float64)
    if w.shape != (t.shape[0], 3):
        raise InvalidInputError(
            f"gyro angular_velocity must have shape ({t.shape[0]}, 3), got {w.shape}"
        )
    ok = np.all(np.isfinite(w), axis=1)
    t, w = t[ok], w[ok]
    order = np.argsort(t, kind="stable")
    t, w = t[order], w[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    if np.count_nonzero(keep) < 2:
        raise CalibrationError(f"need at least 2 distinct gyro samples, got {t.shape[0]}")
    return t[keep], w[keep]


class _GyroIntegral:
    """Exact integral of the piecewise-linear gyro rate between any two IMU times."""

    def __init__(self, gyro: GyroSamples) -> None:
        self.t_ns, self.w = _clean_gyro(gyro)
        self.t0 = int(self.t_ns[0])
        self.ts = (self.t_ns - self.t0).astype(np.float64) * 1e-9
        h = np.diff(self.ts)
        piece = 0.5 * (self.w[:-1] + self.w[1:]) * h[:, None]
        self.cum = np.concatenate([np.zeros((1, 3)), np.cumsum(piece, axis=0)])

    def span_s(self) -> tuple[float, float]:
        return 0.0, float(self.ts[-1])

    def at(self, s: FloatArray) -> FloatArray:
        """Integral from the first sample to times s (IMU clock, s after t0), (..., 3)."""
        i = np.clip(np.searchsorted(self.ts, s, side="right") - 1, 0, self.ts.shape[0] - 2)
        h = s - self.ts[i]
        span = self.ts[i + 1] - self.ts[i]
        dw = self.w[i + 1] - self.w[i]
        out: FloatArray = (
            self.cum[i] + self.w[i] * h[..., None] + dw * (0.5 * h * h / span)[..., None]
        )
        return out


def gyro_increments(
    gyro: GyroSamples, t0_ns: npt.ArrayLike, t1_ns: npt.ArrayLike, offset_s: npt.ArrayLike
) -> FloatArray:
    """Integral of the measured rate over camera intervals shifted by candidate offsets.

    Args:
        gyro: the samples (IMU frame, IMU clock); need not be sorted.
        t0_ns: (K,) interval starts, camera clock, ns.
        t1_ns: (K,) interval ends, camera clock, ns.
        offset_s: (D,) or scalar candidate offsets (IMU stamp - camera stamp), s.

    Returns:
        (D, K, 3) (or (K, 3) for a scalar offset) integrals of omega_imu, rad (IMU frame).
    """
    g = _GyroIntegral(gyro)
    return _increments(g, np.asarray(t0_ns), np.asarray(t1_ns), np.asarray(offset_s, float))


def _increments(g: _GyroIntegral, t0: IntArray, t1: IntArray, d: FloatArray) -> FloatArray:
    a = (np.asarray(t0, dtype=np.int64) - g.t0).astype(np.float64) * 1e-9
    b = (np.asarray(t1, dtype=np.int64) - g.t0).astype(np.float64) * 1e-9
    dd = d[..., None]
    return g.at(b + dd) - g.at(a + dd)


# -------------------------------------------------------------------- the estimates


def search_offset(
    rot: IntervalRotations, gyro: GyroSamples, max_offset_s: float
) -> tuple[float, FloatArray, FloatArray]:
    """Offset minimising the weighted squared difference of rotation magnitudes.

    ``|theta_cam_k|`` against ``|integral omega_imu|`` over the shifted interval: both are
    independent of the camera-IMU rotation (the bias is neglected here; the refine
    estimates it). Coarse grid of 2 ms steps over ``[-max_offset_s, max_offset_s]``, then
    0.1 ms steps within 4 ms of the best coarse point.

    Returns:
        (best offset in s, the coarse grid (D,) in s, its costs (D,)).

    Raises:
        CalibrationError: no interval is covered by the gyro at every offset tried.
    """
    g = _GyroIntegral(gyro)
    lo, hi = g.span_s()
    a = (rot.t0_ns - g.t0).astype(np.float64) * 1e-9
    b = (rot.t1_ns - g.t0).astype(np.float64) * 1e-9
    inside = (a - max_offset_s >= lo) & (b + max_offset_s <= hi)
    if np.count_nonzero(inside) < 3:
        raise CalibrationError(
            f"the gyro covers only {int(np.count_nonzero(inside))} of {len(rot)} frame "
            f"intervals over the offset search +-{max_offset_s} s"
        )
    sub = rot.subset(inside)
    mag = np.linalg.norm(sub.theta, axis=1)
    w = 1.0 / sub.sigma**2

    def cost(grid: FloatArray) -> FloatArray:
        inc = _increments(g, sub.t0_ns, sub.t1_ns, grid)
        diff = np.linalg.norm(inc, axis=2) - mag[None]
        out: FloatArray = np.sum(w * np.minimum(diff**2, (10 * sub.sigma) ** 2), axis=1)
        return out

    coarse = np.arange(-max_offset_s, max_offset_s + 1e-12, 0.002)
    c = cost(coarse)
    best = float(coarse[int(np.argmin(c))])
    fine = np.arange(best - 0.004, best + 0.004 + 1e-12, 0.0001)
    cf = cost(fine)
    k = int(np.argmin(cf))
    out = float(fine[k])
    if 0 < k < fine.shape[0] - 1:  # parabola through the three best
        y0, y1, y2 = cf[k - 1], cf[k], cf[k + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            out += 0.5 * (y0 - y2) / den * 1e-4
    return out, coarse, c


def wahba(theta_cam: FloatArray, theta_imu: FloatArray, weights: FloatArray) -> FloatArray:
    """Rotation R minimising ``sum w_k |theta_imu_k - R theta_cam_k|^2`` (Kabsch/SVD).

    Args:
        theta_cam: (K, 3) camera-frame rotation increments, rad.
        theta_imu: (K, 3) IMU-frame increments, rad.
        weights: (K,) weights (e.g. 1 / sigma^2).

    Returns:
        (3, 3) rotation taking camera-frame vectors into the IMU frame.
    """
    return _kabsch(np.asarray(theta_cam), np.asarray(theta_imu), np.asarray(weights))


def check_excitation(
    rot: IntervalRotations, min_second_axis_rate: float
) -> tuple[FloatArray, FloatArray]:
    """RMS camera angular rate about the principal axes; raise when not excited.

    Returns:
        ((3,) RMS rates descending, rad/s; (3, 3) principal axes as rows, camera frame).

    Raises:
        NotExcitedError: ``sqrt(lambda_2) < min_second_axis_rate`` (module docstring).
    """
    dt = (rot.t1_ns - rot.t0_ns).astype(np.float64) * 1e-9
    rate = rot.theta / dt[:, None]
    m = rate.T @ rate / max(rate.shape[0], 1)
    lam, vec = np.linalg.eigh(m)
    order = np.argsort(lam)[::-1]
    rms = np.sqrt(np.maximum(lam[order], 0.0))
    axes = vec[:, order].T
    if rms[1] < min_second_axis_rate:
        main = axes[0]
        # the camera axis most perpendicular to the dominant one (pan or tilt preferred)
        other = int(np.argmin(np.abs(main[:2]))) if abs(main[2]) < 0.9 else 1
        dom = int(np.argmax(np.abs(main)))
        advice = (
            f"record again turning the camera about a second axis: add {_AXIS_MOTION[other]} "
            f"to the {_AXIS_MOTION[dom].split(' (')[0]}, at least "
            f"{min_second_axis_rate:g} rad/s RMS about each"
        )
        raise NotExcitedError(
            f"rotation about one axis only: RMS rate {rms[0]:.3f} rad/s about camera axis "
            f"[{main[0]:.2f}, {main[1]:.2f}, {main[2]:.2f}], {rms[1]:.3f} and {rms[2]:.3f} "
            f"rad/s about the others (need >= {min_second_axis_rate:g} about two axes); " + advice,
            rms,
            axes,
            advice,
        )
    return rms, axes


def _second_order(
    sub: IntervalRotations, g: _GyroIntegral, d: float, bias: FloatArray
) -> FloatArray:
    """(K, 3) exact gyro rotation vector minus the integral of the rate, IMU frame, rad.

    The rotation of a turning axis is not the integral of the rate (the rates do not
    commute); the difference, second order in the interval's rotation, is computed once
    per refine at the current estimate with the exact Magnus integration of
    :class:`~owl_core.gyro.GyroBuffer` (one call per interval) and held fixed.
    """
    buf = GyroBuffer(imu_time_offset_ns=round(d * 1e9), capacity_s=1e9)
    buf.add(GyroSamples(g.t_ns, g.w))
    mats = np.array(
        [
            buf.relative_rotation(int(a), int(b), bias)
            for a, b in zip(sub.t0_ns, sub.t1_ns, strict=True)
        ]
    ).reshape(-1, 3, 3)
    exact = -so3_log(mats)
    dt = (sub.t1_ns - sub.t0_ns).astype(np.float64) * 1e-9
    inc = _increments(g, sub.t0_ns, sub.t1_ns, np.asarray(d)) - np.outer(dt, bias)
    out: FloatArray = exact - inc
    return out


def _refine(
    sub: IntervalRotations,
    g: _GyroIntegral,
    r0: FloatArray,
    d0: float,
    b0: FloatArray,
    corr: FloatArray | None = None,
) -> tuple[FloatArray, float, FloatArray, FloatArray, FloatArray, float]:
    """Joint least squares of (rotation, offset, bias): returns (R, d, b, x, cov, rms).

    ``corr`` (K, 3): the :func:`_second_order` terms added to the gyro side (None = 0).
    """
    dt = (sub.t1_ns - sub.t0_ns).astype(np.float64) * 1e-9
    extra = np.zeros((len(sub), 3)) if corr is None else corr
    a = (sub.t0_ns - g.t0).astype(np.float64) * 1e-9
    b = (sub.t1_ns - g.t0).astype(np.float64) * 1e-9
    inv_sigma = 1.0 / sub.sigma

    def residual(x: FloatArray) -> FloatArray:
        r = so3_exp(x[:3]) @ r0
        d = d0 + x[3] * 1e-3
        inc = g.at(b + d) - g.at(a + d) - np.outer(dt, x[4:]) + extra
        res = (sub.theta @ r.T - inc) * inv_sigma[:, None]
        out: FloatArray = res.reshape(-1)
        return out

    x0 = np.concatenate([np.zeros(3), [0.0], b0])
    sol = least_squares(residual, x0, loss="soft_l1", f_scale=3.0, x_scale="jac")
    x = sol.x
    jac = sol.jac
    m, p = jac.shape
    res = residual(x)
    s2 = float(np.sum(res**2) / max(m - p, 1))
    try:
        cov = np.linalg.inv(jac.T @ jac) * s2
    except np.linalg.LinAlgError:
        cov = np.full((p, p), np.inf)
    rms = float(np.sqrt(np.mean(res**2)))
    return so3_exp(x[:3]) @ r0, d0 + x[3] * 1e-3, x[4:].copy(), x, cov, rms


def calibrate(
    rot: IntervalRotations,
    gyro: GyroSamples,
    options: CalibrationOptions | None = None,
) -> CalibrationResult:
    """Camera-to-IMU rotation, time offset and gyro bias (see the module docstring).

    Args:
        rot: the visual rotations (:func:`track_rotations` or :func:`interval_rotations`).
        gyro: the gyro samples (IMU frame, IMU clock, rad/s).
        options: settings.

    Returns:
        A :class:`CalibrationResult`.

    Raises:
        NotExcitedError: the rotation does not excite two axes (message says what to record).
        CalibrationError: too few usable intervals, or the gyro does not cover them.
    """
    opts = options if options is not None else CalibrationOptions()
    if len(rot) < opts.min_intervals:
        raise CalibrationError(
            f"only {len(rot)} frame intervals with a usable rotation (need "
            f">= {opts.min_intervals}): too few frames, too little texture or the gyro "
            "does not overlap the images"
        )
    rms_rates, _ = check_excitation(rot, opts.min_second_axis_rate)
    g = _GyroIntegral(gyro)
    d_coarse, _, _ = search_offset(rot, gyro, opts.max_offset_s)
    lo, hi = g.span_s()
    a = (rot.t0_ns - g.t0).astype(np.float64) * 1e-9
    b = (rot.t1_ns - g.t0).astype(np.float64) * 1e-9
    margin = 0.02
    inside = (a + d_coarse - margin >= lo) & (b + d_coarse + margin <= hi)
    sub = rot.subset(inside)
    if len(sub) < opts.min_intervals:
        raise CalibrationError(
            f"the gyro covers only {len(sub)} frame intervals at offset {d_coarse:.4f} s "
            f"(need >= {opts.min_intervals})"
        )
    inc = _increments(g, sub.t0_ns, sub.t1_ns, np.asarray(d_coarse))
    r0 = wahba(sub.theta, inc, 1.0 / sub.sigma**2)
    # gross outliers (independent motion, failed fits) out before the refine
    err = np.linalg.norm(inc - sub.theta @ r0.T, axis=1)
    keep = err < max(6.0 * float(np.median(err)), 1e-9)
    if np.count_nonzero(keep) >= opts.min_intervals:
        sub = sub.subset(keep)
        inc = inc[keep]
        r0 = wahba(sub.theta, inc, 1.0 / sub.sigma**2)
    r_est, d_est, b_est, _, cov, rms = _refine(sub, g, r0, d_coarse, np.zeros(3))
    if abs(d_est) > opts.max_offset_s:
        raise CalibrationError(
            f"the refined time offset {d_est:.4f} s left the search range "
            f"+-{opts.max_offset_s} s (coarse {d_coarse:.4f} s): images and gyro do not "
            "agree on any offset"
        )
    a = (sub.t0_ns - g.t0).astype(np.float64) * 1e-9
    b = (sub.t1_ns - g.t0).astype(np.float64) * 1e-9
    sub = sub.subset((a + d_est - margin >= lo) & (b + d_est + margin <= hi))
    if len(sub) < opts.min_intervals:
        raise CalibrationError(
            f"the gyro covers only {len(sub)} frame intervals at offset {d_est:.4f} s "
            f"(need >= {opts.min_intervals})"
        )
    corr = np.zeros((len(sub), 3))
    if opts.exact_gyro:
        corr = _second_order(sub, g, d_est, b_est)
        r_est, d_est, b_est, _, cov, rms = _refine(sub, g, r_est, d_est, b_est, corr)
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    sig_rot, sig_d, sig_b = sig[:3].copy(), float(sig[3]) * 1e-3, sig[4:].copy()
    if opts.bootstrap > 0:
        boot = _bootstrap(sub, g, r_est, d_est, b_est, corr, opts)
        if boot is not None:
            sig_rot = np.maximum(sig_rot, boot[:3])
            sig_d = max(sig_d, float(boot[3]))
            sig_b = np.maximum(sig_b, boot[4:])
    return CalibrationResult(
        camera_to_imu=r_est,
        camera_to_imu_xyzw=matrix_to_quat_xyzw(r_est),
        rotation_sigma_rad=sig_rot,
        time_offset_s=float(d_est),
        time_offset_sigma_s=sig_d,
        gyro_bias=b_est,
        gyro_bias_sigma=sig_b,
        coarse_offset_s=d_coarse,
        intervals_used=len(sub),
        residual_rms=rms,
        rms_rates=rms_rates,
    )


def _bootstrap(
    sub: IntervalRotations,
    g: _GyroIntegral,
    r_est: FloatArray,
    d_est: float,
    b_est: FloatArray,
    corr: FloatArray,
    opts: CalibrationOptions,
) -> FloatArray | None:
    """Moving-block bootstrap std of (rotation about IMU x y z (rad), offset (s), bias)."""
    rng = np.random.default_rng(opts.seed + 1)
    t = (sub.t0_ns - sub.t0_ns[0]).astype(np.float64) * 1e-9
    block = np.floor(t / opts.block_s).astype(np.int64)
    nblocks = int(block.max()) + 1
    if nblocks < 3:
        return None
    members = [np.flatnonzero(block == k) for k in range(nblocks)]
    samples = []
    for _ in range(opts.bootstrap):  # one small least-squares fit per replica
        pick = rng.integers(0, nblocks, size=nblocks)
        idx = np.concatenate([members[k] for k in pick])
        if idx.shape[0] < opts.min_intervals:
            continue
        r, d, b, _, _, _ = _refine(sub.subset(idx), g, r_est, d_est, b_est, corr[idx])
        samples.append(np.concatenate([so3_log(r @ r_est.T), [d - d_est], b - b_est]))
    if len(samples) < 3:
        return None
    out: FloatArray = np.std(np.asarray(samples), axis=0, ddof=1)
    return out
