"""Classical two-view baseline on the same tracks as OWL: heading and r/|t| from two frames.

Two estimators, both on pairs of unit bearings ``e0`` (older frame) and ``e1`` (current
frame) of the same tracks, ``interval_s`` apart:

* :func:`essential_two_view`: OpenCV's pipeline. ``cv2.findEssentialMat`` (5-point, RANSAC
  with local optimisation by default, ``BaselineOptions.robust``)
  on the undistorted normalised points ``(x/z, y/z)``, ``cv2.recoverPose`` (rotation and unit
  translation, cheirality), ``cv2.triangulatePoints``. OpenCV's convention is
  ``X1 = R X0 + t``; the camera moved along ``-t`` expressed in the current frame, so the
  heading is ``-t/|t|``. With ``|t| = 1`` the baseline is one unit = ``|v| * interval_s``, so a
  triangulated range ``r1`` (units of baseline) is ``r/|v| = r1 * interval_s`` seconds.
* :func:`gyro_two_view`: the gyro-aided variant. The older bearings are derotated with the
  gyro rotation ``R_{1<-0}``; the translation direction alone then satisfies the coplanarity
  constraint ``t . (e1 x R e0) = 0``: a 2-point RANSAC (``t = n_i x n_j``) and a least-squares
  refinement (smallest singular vector of the inliers' ``n_i``), sign chosen so that the
  derotated flow moves away from the heading (static points: ``(de/dt) . t <= 0``).
  With a rolling shutter (``TwoViewBaseline``'s ``row_rotations``) each bearing is first
  rotated from its own row's time into the camera orientation at the current stamp, as OWL
  does (:mod:`owl_core.rolling_shutter`), and the pair is solved with the identity rotation.

Both give per-point ``r/|t|`` for the current frame, an inlier mask (RANSAC outliers are the
baseline's "moving" points) and the heading in the current camera optical frame. Pure numpy
and OpenCV; no ROS. :class:`TwoViewBaseline` applies them to :class:`~owl_core.tracker.Tracks`
(the current frame against the one ``gap_frames`` earlier). :class:`FilteredBaseline` passes
a baseline's per-frame heading through the heading filter OWL itself uses, so that a
comparison does not credit OWL with its temporal filter.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import numpy.typing as npt

from owl_core import heading_filter as hf
from owl_core.camera import CameraModel
from owl_core.errors import InvalidInputError
from owl_core.rolling_shutter import ReadoutRotations
from owl_core.tracker import Tracks
from owl_core.types import PointFlag

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

__all__ = [
    "BaselineFrame",
    "BaselineOptions",
    "FilteredBaseline",
    "TwoViewBaseline",
    "TwoViewEstimate",
    "essential_two_view",
    "gyro_two_view",
    "triangulate_current",
]

#: Rotation provider for the gyro variant: (t0_ns, t1_ns) -> R_{1<-0} (3, 3), or None.
RotationFn = Callable[[int, int], FloatArray | None]
#: Row-time rotations for the gyro variant with a rolling shutter: (frame stamps (K,) int64
#: ns, stamp ns) -> :class:`~owl_core.rolling_shutter.ReadoutRotations` into the camera
#: frame at the stamp, or None where the gyro does not cover the frames' readouts.
RowRotationFn = Callable[[npt.NDArray[np.int64], int], ReadoutRotations | None]

#: ``cv2.recoverPose``'s ``distanceThresh``, in baselines: points triangulated farther
#: count as at infinity and do not vote in the cheirality check that chooses between t
#: and -t. OpenCV's default, 50, suits wide baselines; between consecutive frames of a
#: walk (5 cm at 1.5 m/s and 30 Hz) it is 2.5 m, and the few points nearer than that
#: decided the sign: on ``handheld`` at a 1-frame gap the default gave a heading on 23 of
#: 91 frames, every one reversed (179.6 deg). Far points' depth signs are noisy but right
#: on balance, so all of them vote: 90 of 91 headings, 0.20 deg median.
POSE_DISTANCE_BASELINES = 1e6

_ROBUST = {
    "usac_accurate": cv2.USAC_ACCURATE,
    "ransac": cv2.RANSAC,
    "magsac": cv2.USAC_MAGSAC,
    "lmeds": cv2.LMEDS,
}


@dataclass(frozen=True)
class BaselineOptions:
    """Settings of the two-view baseline.

    Attributes:
        method: "essential" (OpenCV 5-point + recoverPose) or "gyro" (gyro-derotated,
            translation direction only).
        robust: OpenCV's robust estimator for the essential matrix: "usac_accurate"
            (5-point RANSAC with local optimisation, cv2.USAC_ACCURATE), "ransac"
            (plain 5-point RANSAC, cv2.RANSAC: with sub-pixel flow it often stops at the
            first model within the threshold), "magsac" (cv2.USAC_MAGSAC) or "lmeds".
        gap_frames: the current frame is paired with the frame this many frames earlier
            (>= 1; fewer if the track history is shorter). A longer gap gives more parallax.
        threshold_px: RANSAC inlier threshold, pixels (converted to normalised units with
            the focal length, or to bearing units for the gyro variant).
        confidence: RANSAC confidence in (0, 1).
        max_iterations: RANSAC iterations (the essential matrix; hypotheses for the gyro
            variant), count.
        min_points: fewer correspondences than this -> no estimate, count (>= 5).
        min_parallax_deg: triangulated points whose two rays meet at less than this angle
            get no range (it would be noise), degrees.
        min_heading_parallax_px: no heading when the inliers' median parallax (the angle
            between a point's two rays once the pair's rotation is removed, times the focal
            length) is below this, pixels: a rotation alone explains the pair (the camera
            only turned, or moved too little for a direction), as a visual-odometry
            initialiser refuses a pair without parallax. 0 disables it.
        seed: seed of OpenCV's and numpy's RANSAC random generators.

    The defaults are the best of a sweep on the ``street`` and ``cube`` scenarios at 640x480
    (robust estimator x threshold 0.3/0.5/1 px x gap 2/4/7 frames): USAC_ACCURATE at 0.5 px
    over 4 frames is within a few hundredths of a degree of the best heading on both, while
    plain RANSAC is 3 to 10 times worse (0.4-1.9 deg median) and LMEDS 2 to 4 times.
    """

    method: str = "essential"
    robust: str = "usac_accurate"
    gap_frames: int = 4
    threshold_px: float = 0.5
    confidence: float = 0.999
    max_iterations: int = 1000
    min_points: int = 8
    min_parallax_deg: float = 0.05
    min_heading_parallax_px: float = 0.5
    seed: int = 0

    def __post_init__(self) -> None:
        if self.method not in ("essential", "gyro"):
            raise InvalidInputError(f"method must be 'essential' or 'gyro', got {self.method!r}")
        if self.robust not in _ROBUST:
            raise InvalidInputError(
                f"robust must be one of {', '.join(_ROBUST)}, got {self.robust!r}"
            )
        for name, low in (("gap_frames", 1), ("max_iterations", 1), ("min_points", 5)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InvalidInputError(f"{name} must be an integer >= {low}, got {value!r}")
        if not (math.isfinite(self.threshold_px) and self.threshold_px > 0):
            raise InvalidInputError(f"threshold_px must be positive, got {self.threshold_px!r}")
        if not 0 < self.confidence < 1:
            raise InvalidInputError(f"confidence must be in (0, 1), got {self.confidence!r}")
        if not (math.isfinite(self.min_heading_parallax_px) and self.min_heading_parallax_px >= 0):
            raise InvalidInputError(
                f"min_heading_parallax_px must be >= 0, got {self.min_heading_parallax_px!r}"
            )
        if not (math.isfinite(self.min_parallax_deg) and self.min_parallax_deg >= 0):
            raise InvalidInputError(
                f"min_parallax_deg must be >= 0, got {self.min_parallax_deg!r}"
            )


@dataclass(frozen=True)
class TwoViewEstimate:
    """Result of one two-view solve over N correspondences.

    Attributes:
        heading: (3,) unit translation direction in the current (second) camera frame, or
            None when there is no estimate.
        rotation: (3, 3) R_{1<-0} used (estimated, or the gyro's); identity if none.
        range_over_speed: (N,) r/|t| of each point in the current frame, seconds; NaN for
            outliers, points behind a camera and points with too little parallax.
        inliers: (N,) bool RANSAC inliers.
        reason: why there is no estimate ("" when there is one).
    """

    heading: FloatArray | None
    rotation: FloatArray
    range_over_speed: FloatArray
    inliers: BoolArray
    reason: str = ""


def _check_pairs(
    e0: npt.ArrayLike, e1: npt.ArrayLike, interval_s: float
) -> tuple[FloatArray, ...]:
    a = np.asarray(e0, dtype=np.float64)
    b = np.asarray(e1, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape != b.shape:
        raise InvalidInputError(
            f"e0 and e1 must both have shape (N, 3), got {a.shape} and {b.shape}"
        )
    if not (math.isfinite(interval_s) and interval_s > 0):
        raise InvalidInputError(f"interval_s must be positive, got {interval_s!r}")
    return a, b


def _empty(n: int, reason: str, rotation: FloatArray | None = None) -> TwoViewEstimate:
    return TwoViewEstimate(
        None,
        np.eye(3) if rotation is None else rotation,
        np.full(n, np.nan),
        np.zeros(n, dtype=bool),
        reason,
    )


def triangulate_current(
    e0: FloatArray,
    e1: FloatArray,
    rotation: FloatArray,
    heading: FloatArray,
    interval_s: float,
    min_parallax_deg: float = 0.0,
) -> FloatArray:
    """Range over speed of each point in the current frame by two-ray triangulation.

    The camera moved along the unit ``heading`` (current frame) by one unit of
    ``|v| interval_s``; OpenCV's ``cv2.triangulatePoints`` (linear DLT) gives the point in
    the older frame, ``X1 = R X0 + t`` with ``t = -heading``, and ``r/|v| = |X1| interval_s``.

    Args:
        e0: (N, 3) unit bearings in the older frame.
        e1: (N, 3) unit bearings in the current frame.
        rotation: (3, 3) R_{1<-0}.
        heading: (3,) unit translation direction, current frame.
        interval_s: time between the frames, seconds.
        min_parallax_deg: points whose rays meet at a smaller angle get NaN, degrees.

    Returns:
        (N,) float64 r/|t| in seconds; NaN behind either camera, below the parallax limit
        or for bearings behind the image plane.
    """
    n = e0.shape[0]
    out = np.full(n, np.nan)
    t = -np.asarray(heading, dtype=np.float64).reshape(3, 1)
    ok = (e0[:, 2] > 1e-9) & (e1[:, 2] > 1e-9)
    if not ok.any():
        return out
    x0 = (e0[ok, :2] / e0[ok, 2:]).T
    x1 = (e1[ok, :2] / e1[ok, 2:]).T
    p0 = np.hstack([np.eye(3), np.zeros((3, 1))])
    p1 = np.hstack([rotation, t])
    hom = cv2.triangulatePoints(p0, p1, x0, x1)  # (4, M)
    w = hom[3]
    finite = np.abs(w) > 1e-12
    x_old = np.where(finite, hom[:3] / np.where(finite, w, 1.0), np.nan).T  # (M, 3)
    x_cur = x_old @ rotation.T + t.T
    in_front = (x_old[:, 2] > 0) & (x_cur[:, 2] > 0)
    # parallax: angle between the two rays at the point, both in the current frame
    # the older camera centre in the current frame is t (X1 = R X0 + t with X0 = 0)
    ray0 = x_cur - t.T
    cos_par = np.einsum("ij,ij->i", ray0, x_cur) / (
        np.linalg.norm(ray0, axis=1) * np.linalg.norm(x_cur, axis=1) + 1e-300
    )
    parallax_ok = cos_par < math.cos(math.radians(min_parallax_deg)) if min_parallax_deg else True
    good = finite & in_front & parallax_ok
    ranges = np.where(good, np.linalg.norm(x_cur, axis=1) * interval_s, np.nan)
    out[ok] = ranges
    return out


def essential_two_view(
    e0: npt.ArrayLike,
    e1: npt.ArrayLike,
    interval_s: float,
    focal_px: float,
    options: BaselineOptions | None = None,
) -> TwoViewEstimate:
    """OpenCV two-view estimate: 5-point essential matrix (RANSAC), recoverPose, triangulation.

    Args:
        e0: (N, 3) unit bearings in the older frame (undistorted, any camera model).
        e1: (N, 3) unit bearings of the same points in the current frame.
        interval_s: time between the two frames, seconds (> 0).
        focal_px: focal length, pixels (converts ``threshold_px`` to normalised units).
        options: settings (``method`` is ignored).

    Returns:
        :class:`TwoViewEstimate`; heading in the current camera frame.
    """
    opts = options or BaselineOptions()
    a, b = _check_pairs(e0, e1, interval_s)
    n = a.shape[0]
    front = (a[:, 2] > 1e-6) & (b[:, 2] > 1e-6) & np.isfinite(a).all(1) & np.isfinite(b).all(1)
    if np.count_nonzero(front) < opts.min_points:
        return _empty(n, f"{int(np.count_nonzero(front))} correspondences < {opts.min_points}")
    idx = np.flatnonzero(front)
    x0 = np.ascontiguousarray(a[idx, :2] / a[idx, 2:])
    x1 = np.ascontiguousarray(b[idx, :2] / b[idx, 2:])
    cv2.setRNGSeed(opts.seed)
    emat, mask = cv2.findEssentialMat(
        x0,
        x1,
        focal=1.0,
        pp=(0.0, 0.0),
        method=_ROBUST[opts.robust],
        prob=opts.confidence,
        threshold=opts.threshold_px / focal_px,
        maxIters=opts.max_iterations,
    )
    if emat is None or emat.shape != (3, 3) or mask is None:
        return _empty(n, "findEssentialMat found no essential matrix")
    inl = mask.reshape(-1) > 0
    # recoverPose's own mask also drops points farther than its distance threshold: those
    # are valid correspondences, so the RANSAC mask defines the inliers. The threshold
    # also decides which points vote in the cheirality check that picks the sign of t;
    # see POSE_DISTANCE_BASELINES.
    n_front, r_cv, t_cv, _, _ = cv2.recoverPose(
        emat, x0, x1, np.eye(3), distanceThresh=POSE_DISTANCE_BASELINES, mask=mask.copy()
    )
    if np.count_nonzero(inl) < opts.min_points or int(n_front) == 0:
        return _empty(n, f"recoverPose kept {int(n_front)} of {int(np.count_nonzero(inl))}")
    t: FloatArray = np.asarray(t_cv, dtype=np.float64).reshape(3)
    heading = -t / np.linalg.norm(t)
    r_10: FloatArray = np.asarray(r_cv, dtype=np.float64)
    inliers = np.zeros(n, dtype=bool)
    inliers[idx[inl]] = True
    parallax = _median_parallax_px(np.cross(b[inliers], a[inliers] @ r_10.T), focal_px)
    if parallax < opts.min_heading_parallax_px:
        return _empty(n, _no_parallax(parallax, opts), r_10)
    range_over_speed = triangulate_current(a, b, r_10, heading, interval_s, opts.min_parallax_deg)
    range_over_speed[~inliers] = np.nan
    return TwoViewEstimate(heading, r_10, range_over_speed, inliers)


def _median_parallax_px(normals: FloatArray, focal_px: float) -> float:
    """Median norm of ``normals`` (K, 3) = ``e1 x (R e0)`` (the sine of each pair's angle
    once the rotation is removed), times ``focal_px``: the parallax, pixels."""
    sin = np.linalg.norm(normals, axis=1)
    return float(np.median(sin)) * focal_px if sin.size else 0.0


def _no_parallax(parallax_px: float, opts: BaselineOptions) -> str:
    return (
        f"too little parallax for a heading: median {parallax_px:.2f} px < "
        f"min_heading_parallax_px {opts.min_heading_parallax_px}"
    )


def _unit_rows(v: FloatArray) -> FloatArray:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(norm > 0, v / np.where(norm > 0, norm, 1.0), 0.0)


def gyro_two_view(
    e0: npt.ArrayLike,
    e1: npt.ArrayLike,
    rotation: npt.ArrayLike,
    interval_s: float,
    focal_px: float,
    options: BaselineOptions | None = None,
) -> TwoViewEstimate:
    """Gyro-aided two-view estimate: known rotation, translation direction only.

    ``n_i = e1_i x (R e0_i)`` must be orthogonal to the translation; a 2-point RANSAC over
    ``t = n_i x n_j`` (residual ``|t . n_i|``, in bearing units, against ``threshold_px /
    focal_px``), then the smallest right singular vector of the inliers' ``n_i``.

    Args:
        e0: (N, 3) unit bearings in the older frame.
        e1: (N, 3) unit bearings in the current frame.
        rotation: (3, 3) R_{1<-0} from the gyro (less whatever bias its provider removes).
        interval_s: time between the frames, seconds (> 0).
        focal_px: focal length, pixels.
        options: settings (``method`` is ignored).

    Returns:
        :class:`TwoViewEstimate`; heading in the current camera frame.
    """
    opts = options or BaselineOptions()
    a, b = _check_pairs(e0, e1, interval_s)
    r_10 = np.asarray(rotation, dtype=np.float64)
    if r_10.shape != (3, 3) or not np.isfinite(r_10).all():
        raise InvalidInputError(f"rotation must be a finite (3, 3) matrix, got {r_10.shape}")
    n = a.shape[0]
    usable = np.isfinite(a).all(1) & np.isfinite(b).all(1)
    if np.count_nonzero(usable) < opts.min_points:
        return _empty(n, f"{int(np.count_nonzero(usable))} correspondences < {opts.min_points}")
    idx = np.flatnonzero(usable)
    a_rot = a[idx] @ r_10.T
    normals = np.cross(b[idx], a_rot)  # (M, 3), |n| ~ derotated parallax angle
    m = idx.size
    thr = opts.threshold_px / focal_px
    rng = np.random.default_rng(opts.seed)
    hyp = min(opts.max_iterations, 2000)
    pairs = rng.integers(0, m, size=(hyp, 2))
    cand = _unit_rows(np.cross(normals[pairs[:, 0]], normals[pairs[:, 1]]))  # (hyp, 3)
    scores = np.abs(normals @ cand.T) < thr  # (M, hyp)
    counts = scores.sum(axis=0)
    counts[~np.any(cand != 0, axis=1)] = -1
    best = int(np.argmax(counts))
    inl = scores[:, best]
    if np.count_nonzero(inl) < opts.min_points:
        return _empty(n, f"RANSAC kept {int(np.count_nonzero(inl))} < {opts.min_points}", r_10)
    h = cand[best]
    for _ in range(3):  # refine on inliers, re-select inliers
        _, _, vt = np.linalg.svd(normals[inl], full_matrices=False)
        h = vt[-1]
        new_inl = np.abs(normals @ h) < thr
        if np.count_nonzero(new_inl) < opts.min_points or np.array_equal(new_inl, inl):
            break
        inl = new_inl
    parallax = _median_parallax_px(normals[inl], focal_px)
    if parallax < opts.min_heading_parallax_px:
        return _empty(n, _no_parallax(parallax, opts), r_10)
    flow = b[idx] - a_rot  # derotated displacement; static points move away from the FOE
    if np.median(flow[inl] @ h) > 0:
        h = -h
    inliers = np.zeros(n, dtype=bool)
    inliers[idx[inl]] = True
    range_over_speed = triangulate_current(a, b, r_10, h, interval_s, opts.min_parallax_deg)
    range_over_speed[~inliers] = np.nan
    return TwoViewEstimate(h / np.linalg.norm(h), r_10, range_over_speed, inliers)


@dataclass(frozen=True)
class BaselineFrame:
    """The baseline's output for one image, in the shape owl_eval scores. N points.

    Attributes:
        stamp_ns: the image stamp, ns.
        heading: (3,) unit heading, current camera frame, or None.
        pixels: (N, 2) current pixels of the tracks used.
        ids: (N,) uint32 track ids.
        range_over_speed: (N,) r/|t|, seconds (NaN where the point got no range).
        flags: (N,) uint8: PointFlag.MOVING on RANSAC outliers.
        interval_s: time between the two views, seconds (0 when none).
        timings: seconds per stage: "estimate" (the two-view solve, tracking excluded).
        reason: why there is no heading ("" when there is one).
    """

    stamp_ns: int
    heading: FloatArray | None
    pixels: FloatArray
    ids: npt.NDArray[np.uint32]
    range_over_speed: FloatArray
    flags: npt.NDArray[np.uint8]
    interval_s: float
    timings: dict[str, float] = field(default_factory=dict)
    reason: str = ""


class TwoViewBaseline:
    """Applies the two-view baseline to the tracker's :class:`Tracks`, frame by frame.

    Args:
        camera: the camera model (pixels -> bearings, focal length).
        options: settings; ``method`` selects OpenCV's essential matrix or the gyro variant.
        rotation: for the gyro variant, a callable (t0_ns, t1_ns) -> R_{1<-0} (3, 3) or None
            when the gyro does not cover the interval (e.g. ``GyroBuffer.relative_rotation``
            guarded by ``covers``).
        row_rotations: for the gyro variant with a rolling shutter, a callable (frame stamps,
            stamp) -> :class:`~owl_core.rolling_shutter.ReadoutRotations` (e.g.
            :func:`~owl_core.rolling_shutter.readout_rotations` guarded by ``covers``):
            each bearing is derotated from its own row's time (row ``v`` of a frame
            stamped ``s`` seen at ``s + (v / height) T``) instead of its frame's stamp.
            None: a global shutter (or a baseline that ignores the readout).
    """

    def __init__(
        self,
        camera: CameraModel,
        options: BaselineOptions | None = None,
        rotation: RotationFn | None = None,
        row_rotations: RowRotationFn | None = None,
    ) -> None:
        self.camera = camera
        self.options = options or BaselineOptions()
        if self.options.method == "gyro" and rotation is None and row_rotations is None:
            raise InvalidInputError("the gyro baseline needs a rotation provider, got None")
        self._rotation = rotation
        self._row_rotations = row_rotations if self.options.method == "gyro" else None
        self._focal = float(max(camera.fx, camera.fy))
        #: clock of ``timings["estimate"]``, s (``time.thread_time`` for CPU time)
        self.clock: Callable[[], float] = time.perf_counter

    def process(self, tracks: Tracks) -> BaselineFrame:
        """Two-view estimate between the current frame and ``gap_frames`` earlier.

        Every track present in both frames is used. Returns a frame without heading (and
        the reason) when the history is too short, too few tracks span it, or no gyro.
        """
        t_start = self.clock()
        opts = self.options
        stamps = np.asarray(tracks.stamps_ns)
        stamp = int(stamps[0])
        hist = np.asarray(tracks.history)
        valid_cols = np.flatnonzero(stamps[: opts.gap_frames + 1] >= 0)
        gap = int(valid_cols.max()) if valid_cols.size else 0

        def nothing(reason: str, interval: float = 0.0) -> BaselineFrame:
            return BaselineFrame(
                stamp,
                None,
                np.zeros((0, 2)),
                np.zeros(0, dtype=np.uint32),
                np.zeros(0),
                np.zeros(0, dtype=np.uint8),
                interval,
                {"estimate": self.clock() - t_start},
                reason,
            )

        if gap < 1:
            return nothing("first frame: no earlier view")
        both = np.isfinite(hist[:, 0]).all(1) & np.isfinite(hist[:, gap]).all(1)
        if np.count_nonzero(both) < opts.min_points:
            return nothing(f"{int(np.count_nonzero(both))} tracks span {gap} frames")
        interval = (stamp - int(stamps[gap])) * 1e-9
        e1 = self.camera.pixel_to_bearing(hist[both, 0])
        e0 = self.camera.pixel_to_bearing(hist[both, gap])
        if self._row_rotations is not None:
            grid = self._row_rotations(np.array([stamp, int(stamps[gap])], dtype=np.int64), stamp)
            if grid is None:
                return nothing("the gyro does not cover the readouts", interval)
            height = float(self.camera.height)
            e1 = grid.to_stamp(0, hist[both, 0][:, 1] / height, e1)
            e0 = grid.to_stamp(1, hist[both, gap][:, 1] / height, e0)
            est = gyro_two_view(e0, e1, np.eye(3), interval, self._focal, opts)
        elif opts.method == "gyro":
            r_10 = self._rotation(int(stamps[gap]), stamp) if self._rotation else None
            if r_10 is None:
                return nothing("the gyro does not cover the interval", interval)
            est = gyro_two_view(e0, e1, r_10, interval, self._focal, opts)
        else:
            est = essential_two_view(e0, e1, interval, self._focal, opts)
        flags = np.where(est.inliers, 0, int(PointFlag.MOVING)).astype(np.uint8)
        return BaselineFrame(
            stamp,
            est.heading,
            np.asarray(hist[both, 0], dtype=np.float64),
            np.asarray(tracks.ids)[both].astype(np.uint32),
            est.range_over_speed,
            flags,
            interval,
            {"estimate": self.clock() - t_start},
            est.reason,
        )


class FilteredBaseline:
    """A two-view baseline's heading through the heading filter OWL uses.

    OWL's heading is a filtered one (:class:`~owl_core.heading_filter.TwoModelHeading`: a
    straight-path model that averages the last seconds and a turning one whose rate removes
    the lag, weighted by how well each predicts); a per-frame two-view estimate compared
    with it unfiltered credits OWL with the filter. This feeds each frame's two-view heading
    to the same filter with the same options: predicted between frames with the gyro's
    rotation, updated with the two-view heading as a measurement of the middle of its
    interval (``tau = -interval_s / 2``) with a constant 1-sigma ``sigma_rad`` (the two-view
    solve gives no uncertainty; a user tunes it once, as the bench's grid does).

    A frame whose two-view solve gave no heading gets none here either (the filter keeps its
    state); a step the gyro does not cover restarts the filter from the measurement.

    Args:
        sigma_rad: the measurement's 1-sigma angular uncertainty, rad (> 0).
        rotation: ``(t0_ns, t1_ns) -> R_{1<-0}`` (3, 3) camera frame, or None where the
            gyro does not cover the interval.
        options: the filter's settings (OWL's defaults).
    """

    def __init__(
        self, sigma_rad: float, rotation: RotationFn, options: hf.TwoModelOptions | None = None
    ) -> None:
        if not (math.isfinite(sigma_rad) and sigma_rad > 0):
            raise InvalidInputError(f"sigma_rad must be positive and finite, got {sigma_rad!r}")
        self.sigma_rad = float(sigma_rad)
        self._rotation = rotation
        self._filter = hf.TwoModelHeading(options or hf.TwoModelOptions())
        #: clock of the time added to ``timings["estimate"]``, s
        self.clock: Callable[[], float] = time.perf_counter

    def reset(self) -> None:
        """Forget the filter's state."""
        self._filter.reset()

    def step(self, frame: BaselineFrame) -> BaselineFrame:
        """The frame with its heading replaced by the filtered one (at the image time).

        Args:
            frame: the baseline's output for this image.

        Returns:
            a copy of ``frame``: heading filtered (None where the frame has none), the
            filter's time added to ``timings["estimate"]``; points and ranges unchanged.
        """
        t_start = self.clock()
        flt = self._filter
        heading = None
        if frame.heading is not None and np.all(np.isfinite(frame.heading)):
            last = flt.stamp_ns
            if last is not None:
                r_10 = self._rotation(last, frame.stamp_ns) if frame.stamp_ns > last else None
                if r_10 is None:
                    flt.reset()
                else:
                    flt.predict(frame.stamp_ns, r_10)
            tau = -0.5 * max(frame.interval_s, 0.0)
            flt.update(
                frame.stamp_ns, np.asarray(frame.heading, dtype=np.float64), tau, self.sigma_rad
            )
            heading = None if flt.heading is None else flt.heading.copy()
        timings = dict(frame.timings)
        timings["estimate"] = timings.get("estimate", 0.0) + self.clock() - t_start
        return replace(frame, heading=heading, timings=timings)
