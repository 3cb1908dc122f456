"""The OWL engine: images + gyro in, per-feature L, omega, RoT, scaled points and heading out.

Per frame (:meth:`OwlEngine.process`):

1. **track**: :class:`~owl_core.tracker.FeatureTracker` with LK initial positions predicted
   from the gyro rotation since the previous frame (fast rotations keep their tracks).
2. **integrate**: each track's last ``fit_frames`` positions become bearings
   (:class:`~owl_core.camera.CameraModel`, distortion included; each position is
   undistorted once and reused while it stays in the window), rotated into the current
   camera frame with the gyro rotations (current bias removed); a weighted polynomial fit of
   bearing against time gives the derotated bearing rate ``f`` at the current stamp and its
   noise, so neither ``f`` nor the neighbours' relative motion rests on two frames.
3. **heading**: :func:`~owl_core.heading.estimate_motion` finds the heading and the leftover
   rotation (gyro-bias error) jointly; :class:`~owl_core.heading.GyroBiasFilter` filters the
   bias; ``f`` is corrected by the leftover rotation. A camera that does not translate gives
   no points (the reason says so) while the bias keeps updating.
4. **looming**: L by the local deformation rule over each feature's image neighbours
   (``scipy.spatial.cKDTree``), L by the heading route, fused by variance; then ToR, RoT,
   r/|t|, scaled points; points whose coplanarity residual or whose two L routes disagree
   beyond their noise are flagged MOVING.

Everything is vectorised over features. Units: seconds, radians, pixels; time stamps are
integer nanoseconds.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from owl_core import heading as hd
from owl_core import heading_filter as hf
from owl_core import motion, windows
from owl_core import rolling_shutter as rs
from owl_core import speed_filter as sf
from owl_core import time_offset as to
from owl_core.camera import CameraModel
from owl_core.errors import InvalidInputError
from owl_core.geometry import quat_xyzw_to_matrix, so3_exp, so3_log
from owl_core.gyro import GyroBuffer
from owl_core.tracker import FeatureTracker, TrackerOptions, Tracks
from owl_core.types import FrameResult, GyroSamples, ImageFrame, PointFlag

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

__all__ = ["EngineOptions", "OwlEngine"]

#: 1-sigma of the configured IMU time offset for ``estimate_time_offset``, s.
TIME_OFFSET_SIGMA_S = 0.05
#: The online offset estimate replaces the configured one once its 1-sigma is below this, s.
TIME_OFFSET_APPLY_SIGMA_S = 0.005
#: ``observe_time_offset`` (the live calibration check) feeds the offset filter every this
#: many frames: the filter's heading fit costs about 5 ms per 640x480 frame.
OBSERVE_STRIDE = 3
#: 1-sigma of the prior on the leftover rotation in the offset filter's own heading fit
#: (wide: the leftover of a 50 ms offset at 3 rad/s^2 is 0.15 rad/s), rad/s.
_OFFSET_LEFTOVER_PRIOR = 0.5
#: Neighbours each track is compared with for the depth-edge weights (besides itself).
_EDGE_NEIGHBOURS = 8


@dataclass(frozen=True)
class EngineOptions:
    """Every setting of :class:`OwlEngine`, with units.

    Attributes:
        camera_to_imu_rotation_xyzw: (x, y, z, w) quaternion of the rotation taking
            camera-optical-frame vectors into the IMU frame (contract.md). Default identity.
        imu_time_offset_s: IMU stamp minus camera stamp for simultaneous events, seconds.
        rolling_shutter_readout_s: rolling-shutter readout time T, seconds (row 0 to the
            row after the last; 0 = global shutter). The row at pixel v is seen at
            ``stamp + (v / height) T``: each tracked position gets its row's time for the gyro
            rotation and the track fit, and every output refers to the stamp
            (:mod:`owl_core.rolling_shutter`). The gyro must then cover ``stamp + T``.
        estimate_time_offset: estimate a residual camera-IMU time offset online from the
            leftover rotation of each frame and apply it (:mod:`owl_core.time_offset`;
            from ``imu_time_offset_s``, 1-sigma :data:`TIME_OFFSET_SIGMA_S`; applied once
            its 1-sigma is below :data:`TIME_OFFSET_APPLY_SIGMA_S`, together with the bias
            estimated jointly with it). Off: the offset stays.
        observe_time_offset: run the same online filter without applying anything
            (derotation keeps the configured offset and rotation; outputs are unchanged),
            on every :data:`OBSERVE_STRIDE`-th frame; it also estimates the error of the
            configured rotation. :attr:`OwlEngine.online_calibration` gives both to the
            live calibration check (:mod:`owl_core.calib_check`). Implied by
            ``estimate_time_offset``.
        require_gyro: True: frames without gyro coverage produce no points (reason given).
            False: they are processed without derotation (the leftover rotation is then
            estimated from the flow alone) and every point is flagged NO_GYRO (and IMU_GAP
            when samples exist but do not cover the interval).
        max_features: features tracked, count (passed to the tracker).
        tracker: further tracker settings; its ``max_features`` is replaced by
            ``max_features`` and its ``history_len`` raised to ``fit_frames`` if needed.
        fit_frames: the most frames per track in the bearing-vs-time fit (>= 2; 2 =
            two-frame flow); all of them when ``fit_window_s`` is None.
        fit_window_s: the fit uses the frames within this many seconds of the image (at
            least 3, at most ``fit_frames``; :func:`owl_core.windows.fit_columns`): 5
            frames at 30 Hz, 3 at 10 Hz, 10 at 60 Hz. None: always ``fit_frames``.
        fit_turning_window_s: the window while the heading filter's turning model
            dominates (its weight at least ``fit_turning_weight``, judged on the last
            frame), s, at least 2 frames: 4 frames at 30 Hz, 3 at 20 Hz, 2 at 10 Hz. On a
            curving path the heading changes over the window and the fit's reference
            time lags the image by half of it; the filter's rate extrapolates that lag,
            and a shorter lag leaves less to extrapolate. 0.13 rather than 0.1: at 17 Hz
            (a handheld RealSense walk) 0.1 s holds only 2 frames, and those fits cost
            the walk 8 of its 167 frames' points and widened its heading's disagreement
            with the 5-point estimate; 0.13 s keeps 3 there (as ``fit_window_s``) and the
            same frames as 0.1 s at 10, 20 and 30 Hz. None: ``fit_window_s`` always.
        fit_turning_weight: the turning model's weight (0..1) from which
            ``fit_turning_window_s`` applies.
        fit_order: polynomial order of that fit: 1 (straight line; its slope lags by half
            the window) or 2 (quadratic, evaluated at the current stamp).
        min_track_frames: tracks seen in fewer frames than this (>= 2; at most the frames
            of the fit window) give no point.
        pixel_noise_px: 1-sigma tracking noise per image axis, pixels.
        neighbours: k nearest image neighbours used by the local looming rule, count.
        neighbour_radius_px: neighbours farther than this are not used, pixels.
        min_neighbours: fewer usable neighbours -> no L from the local rule, count (>= 3).
        looming_iterations: robust reweighting iterations of the local rule, count (>= 0).
        min_quality: points below this quality (0..1) are flagged LOW_QUALITY.
        quality_rel_sigma: relative 1-sigma of r/|t| (dimensionless) at which a point's
            quality is halved by its precision factor ``1 / (1 + (rel_sigma / this)^2)``;
            quality = local-fit quality x precision factor x coplanarity factor.
        min_tor: |ToR| at or below this (1/s) means no translation signal at the point.
        moving_sigma: a point whose coplanarity residual, or whose two L routes, differ by
            more than this many standard deviations is flagged MOVING.
        heading_min_sin: the heading route gives no L closer than asin(this) to the focus
            of expansion (or its antipode), dimensionless. Its variance grows as
            1/sin^2 there, so the fusion weighs it down before this cut-off matters.
        local_variance_scale: the local rule's L variance is multiplied by this in the
            fusion with the heading route (dimensionless, > 0). Measured against exact
            ranges on ``street@10hz``: 5 to 10 deg from the heading, where the two routes
            weigh alike, the route's L errors are 0.6 of its stated sigma (its rate noise is
            ``pixel_noise_px``, a ceiling) and the local rule's 0.95, so the stated ratio
            gave the local rule about three times the weight its errors earn; far from
            the focus of expansion the route's variance is 10 to 100 times smaller and the
            scale changes little. The fused variance is what the per-track range filter
            weighs each frame's r/|t| by.
        estimate_bias: estimate the gyro bias from the flow (jointly with the heading).
        initial_bias_imu: initial gyro bias, IMU frame, rad/s.
        bias_initial_sigma: 1-sigma of the initial bias, rad/s per axis.
        bias_random_walk: bias random-walk density, rad/s/sqrt(s).
        gyro_noise_density: gyro white-noise density, rad/s/sqrt(Hz) (prior on the
            leftover rotation of one fit window, together with the bias uncertainty).
        bias_inflation: divisor (>= 1) of each frame's bias information (consecutive fit
            windows share frames, so their errors are correlated).
        bias_scatter_window: frames over which the bias filter measures the scatter of the
            frames' leftover rotations beyond their claimed covariances (model errors of
            real sensors) and adds it to every measurement and to the heading fit's
            rotation prior, count; 0: trust the claims (see
            :class:`~owl_core.heading.GyroBiasFilter`).
        bias_observable_sigma: a frame updates the bias only in the directions in which it
            determines the leftover rotation to better than this 1-sigma, rad/s (the others
            stay put: a rotation the flow cannot tell from a translation); inf: all.
        no_gyro_rotation_sigma: prior 1-sigma of the camera rotation rate when frames are
            processed without gyro, rad/s.
        max_frame_gap_s: a larger gap between frames (or a stamp going backwards) resets
            the tracks, seconds.
        estimate_speed_change: measure the relative speed change d ln|t|/dt from frame to
            frame and use it to refer r/|t| to the speed at the current stamp (the track fits
            refer to about half a window earlier).
        speed_filter: options of the steady / changing pair of Kalman filters on the log
            speed that give the rate (:class:`~owl_core.speed_filter.TwoModelSpeed`).
        heading: options of the heading / leftover-rotation estimator.
        confirm_below_turning: the heading fit refines a warm start that RANSAC confirms
            alone (``heading.confirmed_warm_start``) only while the heading filter's
            turning model weighs less than this, in [0, 1] (above 1: always; 0: never).
            In a turn a second start can reach a lower-cost minimum that the last
            frame's heading does not lead to (car@10hz: heading median +2 % when it is
            skipped there), while on straight motion it costs a refinement for nothing.
        heading_filter: the Kalman filters (a straight and a turning path, weighted by
            their recent innovations) that bring each frame's heading to the image time
            (:mod:`owl_core.heading_filter`); None: a straight line through the last
            headings instead (the earlier finite-difference route).
        residual_memory_s: time constant of each track's running mean coplanarity
            residual (in flow-noise sigmas), s; None: no memory. A tracking error stays
            with its feature for its whole life (an occlusion edge, a patch that deforms
            or aliases), so it does not average out over frames as noise does.
        residual_memory_sigma: a track whose running mean residual is ``m`` enters the
            heading fit with the weight ``1 / (1 + (m / this)^2)`` (its flow noise there
            times ``sqrt(1 + (m / this)^2)``), dimensionless (flow-noise sigmas): a
            persistent error is down-weighted while it lasts, and a track that recovers
            regains its weight. Whether the camera translates is judged without it.
        edge_radius_px: tracks whose flow magnitude differs from a neighbour's within this
            radius (pixels) as across a depth edge enter the heading fit with a smaller
            weight (:func:`owl_core.heading.depth_edge_weights`: an LK window across the
            edge tracks a mix of two surfaces, an error the bias filter would take for a
            rotation); None: every track at full weight.
        edge_log_scale: the change of log range (= of log flow magnitude) between
            neighbours at which that weight is 1/2, dimensionless.
        edge_spread_factor: where the frame's typical difference between neighbours is
            larger than ``edge_log_scale / this`` (noisy flow), the scale follows it
            (``spread_factor`` of :func:`~owl_core.heading.depth_edge_weights`; 0: never),
            dimensionless.
        range_filter: filter each track's r/|t| over frames: the previous frame's scaled
            point, moved on by the elapsed time (minus the heading x dt, rescaled by the
            speed change, rotated with the gyro into this frame), predicts this frame's,
            and the two are fused in inverse range by their variances; L, omega, RoT and
            the point are rescaled to the fused r/|t| (the per-point heading is kept).
            Points near the focus of expansion, whose one-frame r/|t| is poor, gain most.
        range_process_rel: relative 1-sigma the prediction gains per sqrt(second)
            (heading and speed errors), 1/sqrt(s).
        range_gate: a measurement farther than this many combined sigmas from the
            prediction (an occlusion, a track that jumped) restarts the track's filter.
        seed: seed of the RANSAC random generator (results are deterministic).
    """

    camera_to_imu_rotation_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    imu_time_offset_s: float = 0.0
    rolling_shutter_readout_s: float = 0.0
    estimate_time_offset: bool = False
    observe_time_offset: bool = False
    require_gyro: bool = True
    max_features: int = 1000
    tracker: TrackerOptions = field(default_factory=TrackerOptions)
    fit_frames: int = 10
    fit_window_s: float | None = 0.15
    fit_turning_window_s: float | None = 0.13
    fit_turning_weight: float = 0.5
    fit_order: int = 1
    min_track_frames: int = 5
    pixel_noise_px: float = 0.15
    neighbours: int = 10
    neighbour_radius_px: float = 80.0
    min_neighbours: int = 5
    looming_iterations: int = 2
    min_quality: float = 0.3
    quality_rel_sigma: float = 0.1
    min_tor: float = 1e-6
    moving_sigma: float = 6.0
    moving_along_sigma: float | None = 4.0
    moving_route_sigma: float | None = 12.0
    heading_min_sin: float = 0.05
    local_variance_scale: float = 4.0
    estimate_bias: bool = True
    initial_bias_imu: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bias_initial_sigma: float = 0.02
    bias_random_walk: float = 1e-4
    gyro_noise_density: float = 2e-4
    bias_inflation: float = 3.0
    bias_scatter_window: int = 30
    bias_observable_sigma: float = math.inf
    no_gyro_rotation_sigma: float = 2.0
    max_frame_gap_s: float = 0.5
    estimate_speed_change: bool = True
    speed_filter: sf.TwoModelSpeedOptions = field(default_factory=sf.TwoModelSpeedOptions)
    heading: hd.HeadingOptions = field(default_factory=hd.HeadingOptions)
    confirm_below_turning: float = 0.5
    heading_filter: hf.TwoModelOptions | None = field(default_factory=hf.TwoModelOptions)
    residual_memory_s: float | None = 0.3
    residual_memory_sigma: float = 0.5
    edge_radius_px: float | None = 12.0
    edge_log_scale: float = 0.1
    edge_spread_factor: float = 1.4
    range_filter: bool = True
    range_process_rel: float = 0.05
    range_gate: float = 4.0
    seed: int = 0

    def __post_init__(self) -> None:
        q = tuple(self.camera_to_imu_rotation_xyzw)
        if len(q) != 4 or not all(math.isfinite(v) for v in q):
            raise InvalidInputError(
                f"camera_to_imu_rotation_xyzw must be 4 finite numbers, got {q}"
            )
        if not math.isfinite(self.imu_time_offset_s):
            raise InvalidInputError(
                f"imu_time_offset_s must be finite, got {self.imu_time_offset_s}"
            )
        readout = self.rolling_shutter_readout_s
        if not (isinstance(readout, int | float) and math.isfinite(readout) and 0 <= readout < 1):
            raise InvalidInputError(
                f"rolling_shutter_readout_s must be in [0, 1) s, got {readout!r}"
            )
        for name in ("confirm_below_turning", "fit_turning_weight"):
            turning = getattr(self, name)
            if not (isinstance(turning, int | float) and turning >= 0):
                raise InvalidInputError(f"{name} must be >= 0, got {turning!r}")
        ints = {
            "max_features": (self.max_features, 1),
            "fit_frames": (self.fit_frames, 2),
            "min_track_frames": (self.min_track_frames, 2),
            "neighbours": (self.neighbours, 3),
            "min_neighbours": (self.min_neighbours, 3),
            "looming_iterations": (self.looming_iterations, 0),
        }
        for name, (value, low) in ints.items():
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InvalidInputError(f"{name} must be an integer >= {low}, got {value!r}")
        if self.fit_order not in (1, 2):
            raise InvalidInputError(f"fit_order must be 1 or 2, got {self.fit_order!r}")
        if self.min_track_frames > self.fit_frames:
            raise InvalidInputError(
                f"min_track_frames ({self.min_track_frames}) must not exceed fit_frames "
                f"({self.fit_frames})"
            )
        if self.min_neighbours > self.neighbours:
            raise InvalidInputError(
                f"min_neighbours ({self.min_neighbours}) must not exceed neighbours "
                f"({self.neighbours})"
            )
        positive = (
            "pixel_noise_px",
            "neighbour_radius_px",
            "moving_sigma",
            "heading_min_sin",
            "local_variance_scale",
            "bias_initial_sigma",
            "gyro_noise_density",
            "no_gyro_rotation_sigma",
            "max_frame_gap_s",
            "quality_rel_sigma",
            "residual_memory_sigma",
            "edge_log_scale",
            "range_gate",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InvalidInputError(f"{name} must be positive and finite, got {value!r}")
        for name in (
            "min_quality",
            "min_tor",
            "bias_random_walk",
            "range_process_rel",
            "edge_spread_factor",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InvalidInputError(f"{name} must be >= 0 and finite, got {value!r}")
        for name in ("fit_window_s", "fit_turning_window_s"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise InvalidInputError(f"{name} must be positive or None, got {value!r}")
        if self.residual_memory_s is not None and not (
            math.isfinite(self.residual_memory_s) and self.residual_memory_s > 0
        ):
            raise InvalidInputError(
                f"residual_memory_s must be positive or None, got {self.residual_memory_s!r}"
            )
        if self.edge_radius_px is not None and not (
            math.isfinite(self.edge_radius_px) and self.edge_radius_px > 0
        ):
            raise InvalidInputError(
                f"edge_radius_px must be positive or None, got {self.edge_radius_px!r}"
            )
        if not (isinstance(self.bias_scatter_window, int) and 0 <= self.bias_scatter_window):
            raise InvalidInputError(
                f"bias_scatter_window must be an int >= 0, got {self.bias_scatter_window!r}"
            )
        if not self.bias_inflation >= 1.0:
            raise InvalidInputError(f"bias_inflation must be >= 1, got {self.bias_inflation!r}")
        if len(self.initial_bias_imu) != 3 or not all(
            math.isfinite(v) for v in self.initial_bias_imu
        ):
            raise InvalidInputError(
                f"initial_bias_imu must be 3 finite numbers, got {self.initial_bias_imu!r}"
            )


def _empty_result(
    stamp_ns: int,
    heading: FloatArray | None,
    heading_sigma: float,
    bias: FloatArray,
    timings: dict[str, float],
    reasons: list[str],
    dropped: dict[str, int],
    speed_rate: float,
) -> FrameResult:
    return FrameResult(
        stamp_ns=stamp_ns,
        pixels=np.zeros((0, 2)),
        bearings=np.zeros((0, 3)),
        looming=np.zeros(0),
        omega=np.zeros((0, 3)),
        rot=np.zeros((0, 4)),
        range_over_speed=np.zeros(0),
        points=np.zeros((0, 3)),
        quality=np.zeros(0),
        ids=np.zeros(0, dtype=np.uint32),
        flags=np.zeros(0, dtype=np.uint8),
        heading=heading,
        heading_sigma_rad=heading_sigma,
        gyro_bias=bias.copy(),
        timings=timings,
        reasons=tuple(reasons),
        dropped=dropped,
        speed_rate=speed_rate,
    )


@dataclass(frozen=True)
class TrackFit:
    """Per-track bearing-vs-time fit, N tracks.

    Attributes:
        bearing: (N, 3) unit bearing at ``tau_ref`` (current camera orientation).
        rate: (N, 3) derotated bearing rate at ``tau_ref``, tangent to ``bearing``, 1/s.
        tau_ref: (N,) time the fit refers to, relative to the current frame, s (<= 0):
            for a straight-line fit the track's time centroid ``c`` moved by
            ``m3 / (2 m2)`` of its frame times (where its slope is the velocity, free of the
            lag a constant-velocity assumption would cause, also on uneven or dropped
            frames; ``c`` itself on a regular grid), 0 for the quadratic fit.
        gain: (N,) standard deviation of ``rate`` per unit bearing noise, 1/s.
        valid: (N,) bool.
    """

    bearing: FloatArray
    rate: FloatArray
    tau_ref: FloatArray
    gain: FloatArray
    valid: BoolArray


def _match_ids(
    old_ids: npt.NDArray[np.uint32], ids: npt.NDArray[np.uint32]
) -> tuple[npt.NDArray[np.intp], BoolArray]:
    """For each of ``ids`` (N,), its row in ``old_ids`` (M,) and whether it is there:
    ((N,) rows, valid where found; (N,) bool). Vectorised (one sort, one search)."""
    if old_ids.shape[0] == 0:
        return np.zeros(ids.shape[0], dtype=np.intp), np.zeros(ids.shape[0], dtype=bool)
    order = np.argsort(old_ids, kind="stable")
    pos = np.minimum(np.searchsorted(old_ids[order], ids), old_ids.shape[0] - 1)
    rows = order[pos]
    return rows, old_ids[rows] == ids


def _small_rotation(a: FloatArray, b: FloatArray) -> FloatArray:
    """(3, 3) rotation taking unit vector a onto unit vector b about a x b."""
    axis = motion.cross(a, b)
    sin = float(np.linalg.norm(axis))
    cos = float(a @ b)
    if sin < 1e-15:
        return np.eye(3)
    k = axis / sin
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    out: FloatArray = np.eye(3) + sin * kx + (1.0 - cos) * (kx @ kx)
    return out


def fit_tracks(bearings: FloatArray, tau_s: FloatArray, mask: BoolArray, order: int) -> TrackFit:
    """Weighted polynomial fit of bearing against time per track (vectorised): the global
    shutter case of :func:`owl_core.rolling_shutter.fit_timed`, every entry of a column at
    its frame's time.

    Args:
        bearings: (N, W, 3) bearings of each track, already in the current camera frame.
        tau_s: (W,) time of each column relative to the current frame, seconds (<= 0).
        mask: (N, W) bool, valid entries.
        order: 1 (straight line, referred to the time its slope is exact at: see
            ``TrackFit.tau_ref``) or 2 (quadratic, referred to tau = 0; tracks with only 2
            points fall back to a line).

    Returns:
        :class:`TrackFit`; invalid tracks (fewer than two frames) hold NaN.
    """
    tau = np.broadcast_to(np.asarray(tau_s, dtype=np.float64), mask.shape)
    bearing, rate, tau_ref, gain, valid, _ = rs.fit_timed(
        bearings, tau, mask, order, np.asarray(tau_s, dtype=np.float64)
    )
    return TrackFit(bearing, rate, tau_ref, gain, valid)


@dataclass
class _MotionState:
    """What the engine carries from one frame to the next, besides the tracker, the gyro
    buffer and the bias filter; one :meth:`OwlEngine.reset` replaces it whole.

    Attributes:
        last_stamp: the previous frame's stamp, ns (None before the first).
        last_heading: (3,) the previous heading at its fit reference time (RANSAC seed).
        heading_history: recent fused headings: (stamp_ns, heading at its fit reference
            time, that time relative to stamp_ns in s); they bring the heading to now.
        speed_state: (stamp_ns, ids (N,), points (N, 3), headings (N, 3), their median
            reference time in s) of the previous frame, for the frame-to-frame speed change.
        bearing_cache: (stamp_ns, ids (N,), pixel history (N, W, 2), its unrotated
            bearings (N, W, 3)) of the previous frame: undistortion (Newton iterations for
            real lenses) then runs on each new position only, not on the whole history.
        residual_memory: (stamp_ns, ids (N,), running mean coplanarity residual (N,) in
            flow-noise sigmas) of the tracks of the last heading fit.
        range_state: (stamp_ns, ids (N,), filtered scaled points (N, 3) in that frame, s,
            their relative 1-sigma (N,), the heading (3,)) of the last frame, for
            ``range_filter``.
    """

    last_stamp: int | None = None
    last_heading: FloatArray | None = None
    heading_history: list[tuple[int, FloatArray, float]] = field(default_factory=list)
    speed_state: tuple[int, npt.NDArray[np.uint32], FloatArray, FloatArray, float] | None = None
    bearing_cache: tuple[int, npt.NDArray[np.uint32], FloatArray, FloatArray] | None = None
    residual_memory: tuple[int, npt.NDArray[np.uint32], FloatArray] | None = None
    range_state: tuple[int, npt.NDArray[np.uint32], FloatArray, FloatArray, FloatArray] | None = (
        None
    )


@dataclass(frozen=True)
class StageSkip:
    """A stage of :meth:`OwlEngine.process` ended the frame without points.

    Attributes:
        reason: why (becomes the last of ``FrameResult.reasons``).
        dropped: (counter, count) pairs for ``FrameResult.dropped``.
        timings: (stage, seconds) pairs of the stage that stopped.
        notes: reasons the stage noted before it stopped.
    """

    reason: str
    dropped: tuple[tuple[str, int], ...] = ()
    timings: tuple[tuple[str, float], ...] = ()
    notes: tuple[str, ...] = ()


@dataclass
class _FrameLog:
    """What one frame's stages report: reasons, dropped counts and stage times (s)."""

    reasons: list[str] = field(default_factory=list)
    dropped: dict[str, int] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)

    def add(
        self,
        timings: tuple[tuple[str, float], ...] = (),
        dropped: tuple[tuple[str, int], ...] = (),
        notes: tuple[str, ...] = (),
    ) -> None:
        self.timings.update(timings)
        self.dropped.update(dropped)
        self.reasons.extend(notes)


@dataclass(frozen=True)
class _Tracked:
    """Stage 1 (track): the tracker's output, the previous frame's stamp (ns, None for
    the first) and the gyro bias (3,), rad/s, the prediction used."""

    tracks: Tracks
    prev_ns: int | None
    bias: FloatArray
    timings: tuple[tuple[str, float], ...]
    dropped: tuple[tuple[str, int], ...]


@dataclass(frozen=True)
class _Integrated:
    """Stage 2 (integrate), for the N tracks with a fit: (W,) fit-window stamps, ns, and
    (W, 3, 3) rotations to now; unit bearings now ``e_now`` and at the reference time
    ``e`` (N, 3), derotated bearing rates ``f`` (N, 3), 1/s, with 1-sigma ``f_sigma``
    (N,); reference times ``tau_ref`` (N,), s (<= 0); pixels (N, 2); ids (N,);
    ``tau_rate`` (N,) the time the rates belong to, s, when not ``tau_ref`` (a rolling
    shutter, :func:`owl_core.rolling_shutter.fit_timed`)."""

    stamps: npt.NDArray[np.int64]
    rotations: FloatArray
    with_gyro: bool
    flags_all: np.uint8
    window_s: float
    e_now: FloatArray
    e: FloatArray
    f: FloatArray
    f_sigma: FloatArray
    tau_ref: FloatArray
    pixels: FloatArray
    ids: npt.NDArray[np.uint32]
    notes: tuple[str, ...]
    dropped: tuple[tuple[str, int], ...]
    timings: tuple[tuple[str, float], ...]
    tau_rate: FloatArray | None = None


@dataclass(frozen=True)
class _Headed:
    """Stage 3 (heading): the estimate, the unit heading at the fits' reference time and
    now (3,), its 1-sigma (rad), and the rates ``f`` (N, 3) with the leftover rotation
    removed."""

    est: hd.MotionEstimate
    heading_ref: FloatArray
    heading: FloatArray
    heading_sigma: float
    f: FloatArray
    timings: tuple[tuple[str, float], ...]


@dataclass(frozen=True)
class _Loomed:
    """Stage 4 (looming), per feature (N,): L now (1/s), omega now (N, 3), RoT (N, 4), r/|t|
    (s), points (N, 3), quality, flags, and which to keep."""

    looming: FloatArray
    omega: FloatArray
    rot: FloatArray
    range_over_speed: FloatArray
    points: FloatArray
    quality: FloatArray
    flags: npt.NDArray[np.uint8]
    keep: BoolArray
    notes: tuple[str, ...]
    dropped: tuple[tuple[str, int], ...]
    timings: tuple[tuple[str, float], ...]


class OwlEngine:
    """The OWL pipeline for one camera (see the module docstring).

    Args:
        camera: the camera model of the images.
        options: engine settings.
        gyro: a gyro buffer to keep (its samples survive a rebuilt engine; its rotation
            and offset are set from ``options``); None: a new, empty one.
    """

    def __init__(
        self,
        camera: CameraModel,
        options: EngineOptions | None = None,
        gyro: GyroBuffer | None = None,
    ) -> None:
        if not isinstance(camera, CameraModel):
            raise InvalidInputError(f"camera must be a CameraModel, got {type(camera).__name__}")
        self.camera = camera
        self.options = opts = options if options is not None else EngineOptions()
        tracker_opts = opts.tracker
        history = max(tracker_opts.history_len, opts.fit_frames)
        self._tracker_options = TrackerOptions(
            **{
                **tracker_opts.__dict__,
                "max_features": opts.max_features,
                "history_len": history,
            }
        )
        offset_ns = round(opts.imu_time_offset_s * 1e9)
        if gyro is None:
            gyro = GyroBuffer(opts.camera_to_imu_rotation_xyzw, offset_ns)
        else:
            gyro.set_calibration(opts.camera_to_imu_rotation_xyzw, offset_ns)
        self._gyro = gyro
        self._readout_ns = round(opts.rolling_shutter_readout_s * 1e9)
        self._r_ci = quat_xyzw_to_matrix(
            np.asarray(opts.camera_to_imu_rotation_xyzw, dtype=np.float64)
            / np.linalg.norm(opts.camera_to_imu_rotation_xyzw)
        )
        self._bias = hd.GyroBiasFilter(
            camera_to_imu=self._r_ci,
            initial_sigma=opts.bias_initial_sigma,
            random_walk=opts.bias_random_walk,
            initial_bias=opts.initial_bias_imu,
            adaptive_window=opts.bias_scatter_window,
        )
        self._tracker = FeatureTracker(self._tracker_options)
        self._clock: Callable[[], float] = time.perf_counter
        self._rng = np.random.default_rng(opts.seed)
        self._state = _MotionState()
        # this frame's image neighbours of its integrated tracks (_pixel_neighbours)
        self._neighbours_of: tuple[_Integrated, tuple[FloatArray, npt.NDArray[np.intp]]] | None = (
            None
        )
        self._heading_filter = hf.TwoModelHeading(opts.heading_filter or None)
        self._speed_filter = sf.TwoModelSpeed(opts.speed_filter)
        self._heading_unconfirmed = replace(opts.heading, confirmed_warm_start=False)
        self._offset_filter = (
            to.TimeOffsetFilter(
                opts.imu_time_offset_s,
                self._r_ci.T @ np.asarray(opts.initial_bias_imu, dtype=np.float64),
                to.TimeOffsetOptions(
                    initial_sigma_s=TIME_OFFSET_SIGMA_S,
                    bias_sigma=opts.bias_initial_sigma,
                    bias_random_walk=opts.bias_random_walk,
                    # observing, every OBSERVE_STRIDE-th frame: its fit window shares fewer
                    # frames with the previous one
                    inflation=(
                        opts.bias_inflation
                        if opts.estimate_time_offset
                        else max(1.0, opts.bias_inflation / OBSERVE_STRIDE)
                    ),
                ),
            )
            if opts.estimate_time_offset or opts.observe_time_offset
            else None
        )
        self._offset_rng = np.random.default_rng(opts.seed + 1)
        self._offset_frames = 0
        self._offset_prev_ns: int | None = None
        self._last_tracks: Tracks | None = None
        self.frames = 0

    @property
    def clock(self) -> Callable[[], float]:
        """Clock of the ``timings`` of each result (tracker included), s: wall time
        (``time.perf_counter``, the default) or e.g. ``time.thread_time`` for CPU time."""
        return self._clock

    @clock.setter
    def clock(self, fn: Callable[[], float]) -> None:
        self._clock = fn
        self._tracker.clock = fn

    # ------------------------------------------------------------------ inputs

    @property
    def gyro_bias(self) -> FloatArray:
        """(3,) current gyro-bias estimate, IMU frame, rad/s."""
        return np.asarray(self._bias.bias.copy(), dtype=np.float64)

    @property
    def gyro_bias_sigma(self) -> FloatArray:
        """(3,) 1-sigma of the bias estimate per IMU axis, rad/s."""
        return np.asarray(np.sqrt(np.diag(self._bias.cov)), dtype=np.float64)

    @property
    def last_tracks(self) -> Tracks | None:
        """The tracker's :class:`~owl_core.tracker.Tracks` of the latest :meth:`process`
        call (None before the first frame and after :meth:`reset`)."""
        return self._last_tracks

    @property
    def imu_time_offset_s(self) -> float:
        """The IMU time offset in use, s: the configured one, or the online estimate once
        applied (``estimate_time_offset``)."""
        return self._gyro.imu_time_offset_ns * 1e-9

    @property
    def imu_time_offset_sigma_s(self) -> float:
        """1-sigma of the online offset estimate in use, s (NaN unless
        ``estimate_time_offset``; an estimate only observed is in :attr:`online_calibration`)."""
        f = self._offset_filter
        if f is None or not self.options.estimate_time_offset:
            return math.nan
        return f.offset_sigma_s

    @property
    def online_calibration(self) -> to.OnlineCalibration | None:
        """The online offset filter's estimates (offset and extrinsic rotation error),
        whether applied or only observed (``estimate_time_offset`` or
        ``observe_time_offset``); None when it does not run."""
        f = self._offset_filter
        return f.snapshot() if f is not None else None

    @property
    def readout_ns(self) -> int:
        """Rolling-shutter readout time, ns (0: global shutter): a frame's last row is seen
        this long after its stamp, and the gyro must reach that far (:meth:`covers`)."""
        return self._readout_ns

    @property
    def gyro(self) -> GyroBuffer:
        """The gyro buffer (read it; feed it through :meth:`add_gyro`)."""
        return self._gyro

    def add_gyro(self, samples: GyroSamples) -> int:
        """Add gyro samples (IMU frame, IMU clock). Returns the number accepted.

        Samples older than the newest held one by more than ``max_frame_gap_s`` (a time
        jump backwards, e.g. a looping bag) clear the buffer first.
        """
        stamps = np.asarray(samples.stamp_ns)
        span = self._gyro.camera_span_ns
        if stamps.size and span is not None:
            newest_imu = span[1] + self._gyro.imu_time_offset_ns
            if int(stamps[0]) < newest_imu - round(self.options.max_frame_gap_s * 1e9):
                self._gyro.reset()
        return self._gyro.add(samples)

    def covers(self, stamp_ns: int) -> bool:
        """Whether the gyro covers the interval from the previous frame to ``stamp_ns``
        (just ``stamp_ns`` for the first frame), and to the last row's time with a rolling
        shutter (``stamp_ns`` + the readout)."""
        start = self._state.last_stamp if self._state.last_stamp is not None else int(stamp_ns)
        return self._gyro.covers(min(start, int(stamp_ns)), int(stamp_ns) + self._readout_ns)

    def reset(self, keep_gyro: bool = False) -> None:
        """Forget tracks, heading and the frame-to-frame state; without ``keep_gyro`` also
        the gyro samples, the bias estimate and the random state (a fresh engine).

        ``keep_gyro=True`` is what the engine itself does after a backwards stamp or a too
        long frame gap: the IMU history and the bias estimate stay valid.
        """
        self._tracker.reset()
        self._state = _MotionState()
        self._neighbours_of = None
        self._heading_filter.reset()
        self._speed_filter.reset()
        if not keep_gyro:
            self._last_tracks = None
            self._gyro.reset()
            self._bias.reset()
            self._rng = np.random.default_rng(self.options.seed)
            if self._offset_filter is not None:
                self._offset_filter.reset()
                self._offset_rng = np.random.default_rng(self.options.seed + 1)
                self._offset_frames = 0
                self._offset_prev_ns = None
                self._set_imu_time_offset(self.options.imu_time_offset_s)

    def _history_bearings(
        self,
        stamp: int,
        ids: npt.NDArray[np.uint32],
        hist: FloatArray,
        stamps: npt.NDArray[np.int64],
    ) -> FloatArray:
        """Unit bearings (N, W, 3) of the track positions ``hist`` (N, W, 2), pixels (NaN
        where a track did not exist), in each frame's own camera orientation.

        Positions the previous frame already converted (same track id, same pixels one
        column later) are taken from the cache; the rest (the new column, new tracks) are
        converted with :meth:`CameraModel.pixel_to_bearing`. ``stamps`` (W,) int64 are the
        history's frame stamps, ns; ``stamp`` the current one.
        """
        n, w = hist.shape[:2]
        need = np.ones((n, w), dtype=bool)
        out = np.empty((n, w, 3))
        cache = self._state.bearing_cache
        if cache is not None and w > 1 and stamps.shape[0] > 1 and cache[0] == int(stamps[1]):
            _, c_ids, c_pix, c_bear = cache
            cols = min(w - 1, c_pix.shape[1])
            if c_ids.shape[0] > 0 and cols > 0:
                rows, found = _match_ids(c_ids, ids)
                old = hist[:, 1 : 1 + cols]
                was = c_pix[rows, :cols]
                same = found & np.all((old == was) | (np.isnan(old) & np.isnan(was)), axis=(1, 2))
                out[same, 1 : 1 + cols] = c_bear[rows[same], :cols]
                need[same, 1 : 1 + cols] = False
        out[need] = self.camera.pixel_to_bearing(hist[need])
        self._state.bearing_cache = (stamp, ids, hist, out)
        return out

    def _update_speed_filter(
        self,
        stamp: int,
        ids: npt.NDArray[np.uint32],
        points: FloatArray,
        headings: FloatArray,
        static: BoolArray,
        tau_ref: FloatArray,
    ) -> None:
        """Feed the speed filter this frame's log speed change (natural log).

        A static point's scaled position (N, 3), s, in units of the speed at its fit's
        reference time ``tau_ref`` (N,), s, moved on by the elapsed time at constant speed
        predicts this frame's; the median log ratio of predicted to measured r/|t| is the
        log speed change between the two frames' reference times.
        """
        if not self.options.estimate_speed_change:
            return
        prev = self._state.speed_state
        s_ids, s_points = ids[static], points[static]
        tau = float(motion.median(tau_ref[static])) if s_ids.size else 0.0
        self._state.speed_state = (stamp, s_ids, s_points, headings[static], tau)
        increment: float | None = None
        dt_ref = 0.0
        if prev is not None:
            p_stamp, p_ids, p_points, p_headings, p_tau = prev
            dt = (stamp - p_stamp) * 1e-9
            dt_ref = dt + tau - p_tau
            rows, found = _match_ids(p_ids, s_ids)
            now_idx = np.flatnonzero(found)
            prev_idx = rows[now_idx]
            if dt > 0 and now_idx.size >= 20:
                predicted = motion.row_norms(p_points[prev_idx] - p_headings[prev_idx] * dt)
                measured = motion.row_norms(s_points[now_idx])
                good = (predicted > 0) & (measured > 0)
                if np.count_nonzero(good) >= 20:
                    increment = float(motion.median(np.log(predicted[good] / measured[good])))
        self._speed_filter.step(stamp, increment, dt_ref, tau)

    def _heading_now(
        self,
        stamp: int,
        heading_ref: FloatArray,
        tau_ref: float,
        sigma: float,
        stamps: npt.NDArray[np.int64],
        rotations: FloatArray,
    ) -> tuple[FloatArray, float]:
        """Bring the fused heading from its fit reference time to ``stamp``.

        The heading refers to the time centroid of the track fits (about half a fit window
        ago); on a curving path it has turned since. A straight line through the last
        headings (each rotated into the current camera frame with the gyro) against time,
        evaluated at the current stamp, removes that lag. Returns (heading, 1-sigma rad).
        """
        opts = self.options
        index = {int(s): k for k, s in enumerate(stamps) if s >= 0}
        times = [tau_ref]
        vectors = [heading_ref]
        for old_stamp, old_heading, old_tau in self._state.heading_history:
            k = index.get(old_stamp)
            if k is None or k == 0:
                continue
            times.append((old_stamp - stamp) * 1e-9 + old_tau)
            vectors.append(rotations[k] @ old_heading)
        kept = [
            item for item in self._state.heading_history if item[0] in index and item[0] != stamp
        ]
        self._state.heading_history = [(stamp, heading_ref, tau_ref), *kept[: opts.fit_frames - 2]]
        if len(times) < 3:
            return heading_ref, sigma
        t = np.asarray(times)
        h = np.asarray(vectors)
        t_mean = float(t.mean())
        sxx = float(np.sum((t - t_mean) ** 2))
        if sxx <= 0:
            return heading_ref, sigma
        slope = ((t - t_mean) @ h) / sxx
        now = h.mean(axis=0) - slope * t_mean
        norm = float(np.linalg.norm(now))
        if not norm > 0:
            return heading_ref, sigma
        # prediction variance of a straight-line fit at t = 0, each heading +-sigma
        factor = 1.0 / t.size + t_mean**2 / sxx
        return now / norm, sigma * math.sqrt(max(factor, 1.0))

    # ------------------------------------------------------------------ process

    def process(self, frame: ImageFrame) -> FrameResult:
        """Run the pipeline on one image (see the module docstring): a chain of stages,
        :meth:`_track`, :meth:`_integrate`, :meth:`_estimate_heading`, :meth:`_looming`
        and :meth:`_compose`; each returns a small frozen record, or a :class:`StageSkip`
        saying why the frame gives no points.

        Args:
            frame: the image (H, W) uint8 matching the camera size, integer-ns stamp.

        Returns:
            The frame's :class:`~owl_core.types.FrameResult`.

        Raises:
            InvalidInputError: wrong image shape or dtype.
        """
        t_start = self.clock()
        img = self._check_image(frame)
        stamp = int(frame.stamp_ns)
        log = _FrameLog()
        gap_reason = self._check_gap(stamp)
        if gap_reason is not None:
            log.reasons.append(gap_reason)
        tracked = self._track(img, stamp)
        log.add(tracked.timings, tracked.dropped)
        integrated = self._integrate(tracked, stamp)
        if isinstance(integrated, StageSkip):
            return self._skipped(stamp, integrated, log, t_start)
        log.add(integrated.timings, integrated.dropped, integrated.notes)
        headed = self._estimate_heading(integrated, tracked.prev_ns, stamp)
        if isinstance(headed, StageSkip):
            return self._skipped(stamp, headed, log, t_start)
        log.add(headed.timings)
        if self._offset_filter is not None:
            log.add(self._update_time_offset(integrated, headed, tracked, stamp))
        loomed = self._looming(integrated, headed, stamp)
        log.add(loomed.timings, loomed.dropped, loomed.notes)
        return self._compose(stamp, integrated, headed, loomed, log, t_start)

    def _check_image(self, frame: ImageFrame) -> npt.NDArray[np.uint8]:
        img = np.asarray(frame.image)
        if img.ndim != 2 or img.dtype != np.uint8:
            raise InvalidInputError(
                f"image must be a 2-D uint8 array, got shape {img.shape} dtype {img.dtype}"
            )
        if img.shape != (self.camera.height, self.camera.width):
            raise InvalidInputError(
                f"image shape {img.shape} does not match the camera "
                f"({self.camera.height}, {self.camera.width})"
            )
        return img

    def _check_gap(self, stamp: int) -> str | None:
        """Reset the tracks after a backwards stamp or a too long gap; returns why."""
        if self._state.last_stamp is None:
            return None
        gap = stamp - self._state.last_stamp
        reason = None
        if gap <= 0:
            reason = (
                f"time went backwards ({stamp} ns after {self._state.last_stamp} ns): tracks reset"
            )
        elif gap > self.options.max_frame_gap_s * 1e9:
            reason = f"frame gap {gap * 1e-9:.3f} s > max_frame_gap_s: tracks reset"
        if reason is not None:
            self.reset(keep_gyro=True)
        return reason

    def _skipped(self, stamp: int, skip: StageSkip, log: _FrameLog, t_start: float) -> FrameResult:
        log.add(skip.timings, skip.dropped, (*skip.notes, skip.reason))
        log.timings["total"] = self.clock() - t_start
        return _empty_result(
            stamp,
            None,
            math.inf,
            self._bias.bias,
            log.timings,
            log.reasons,
            log.dropped,
            self._speed_filter.rate,
        )

    def _track(self, img: npt.NDArray[np.uint8], stamp: int) -> _Tracked:
        """Stage 1: track features, predicted with the gyro's rotation since the last frame."""
        bias = self._bias.bias
        prev = self._state.last_stamp
        predict = None
        if (
            self._readout_ns
            and prev is not None
            and self._gyro.covers(prev, stamp + self._readout_ns)
        ):
            predict = self._row_time_predictor(prev, stamp, bias)
        elif prev is not None and self._gyro.covers(prev, stamp):
            r_rel = self._gyro.relative_rotation(prev, stamp, bias)
            cam = self.camera

            def predict(px: FloatArray) -> FloatArray:
                return cam.bearing_to_pixel(self._previous_bearings(prev, px) @ r_rel.T)

        t0 = self.clock()
        tracks = self._tracker.track(img, stamp, predict)
        self._last_tracks = tracks
        timings = [("track", self.clock() - t0)]
        timings += [(k, float(v)) for k, v in getattr(tracks, "timings", {}).items()]
        self._state.last_stamp = stamp
        self.frames += 1
        lost = tracks.lost_by_reason or {}
        dropped = tuple((f"lost_{k}", int(v)) for k, v in lost.items() if v)
        return _Tracked(tracks, prev, bias, tuple(timings), dropped)

    def _previous_bearings(self, prev: int, px: FloatArray) -> FloatArray:
        """Unit bearings (M, 3) of the previous frame's pixels ``px`` (M, 2): from the
        bearing cache when that frame converted exactly these pixels."""
        cache = self._state.bearing_cache
        if (
            cache is not None
            and cache[0] == prev
            and np.array_equal(cache[2][:, 0], px, equal_nan=True)
        ):
            e_prev: FloatArray = cache[3][:, 0]
            return e_prev
        return self.camera.pixel_to_bearing(px)

    def _row_time_predictor(
        self, prev: int, stamp: int, bias: FloatArray
    ) -> Callable[[FloatArray], FloatArray]:
        """The tracker's gyro prediction with a rolling shutter: each feature rotated from its
        row's time in the previous frame (stamp ``prev``) to its row's time in this one
        (predicted from its previous row, then once more from the predicted row)."""
        frames = np.array([stamp, prev], dtype=np.int64)
        grid = rs.readout_rotations(self._gyro, frames, stamp, self._readout_ns, bias)
        cam = self.camera
        height = float(cam.height)

        def predict(px: FloatArray) -> FloatArray:
            fraction = px[:, 1] / height
            e_stamp = grid.to_stamp(1, fraction, self._previous_bearings(prev, px))
            for _ in range(2):
                out = cam.bearing_to_pixel(grid.from_stamp(0, fraction, e_stamp))
                fraction = np.where(np.isfinite(out[:, 1]), out[:, 1] / height, fraction)
            return out

        return predict

    def _derotate_rows(
        self,
        bearings: FloatArray,
        hist: FloatArray,
        stamps: npt.NDArray[np.int64],
        tau: FloatArray,
        stamp: int,
        bias: FloatArray,
        with_gyro: bool,
        usable_col: BoolArray,
    ) -> tuple[FloatArray, FloatArray]:
        """Rolling shutter: the time of each tracked position from its pixel row, and its
        bearing rotated from that time into the camera frame at ``stamp``.

        Args:
            bearings: (N, W, 3) unit bearings of ``hist`` (N, W, 2) px, each in its own
                frame's camera orientation; ``stamps`` (W,) their frame stamps, ns; ``tau``
                (W,) the same relative to ``stamp``, s.
            bias: (3,) gyro bias, IMU frame, rad/s; ``with_gyro``: derotate at all;
                ``usable_col`` (>= W,) the columns the gyro covers.

        Returns:
            (N, W, 3) bearings in the current camera frame (not rotated without gyro) and
            (N, W) their times relative to ``stamp``, s.
        """
        n, w = hist.shape[:2]
        row_tau = rs.row_times(hist[..., 1], tau, self.camera.height, self._readout_ns * 1e-9)
        cols = np.flatnonzero(usable_col[:w])
        if not with_gyro or cols.size < 2:
            return bearings, row_tau
        grid = rs.readout_rotations(self._gyro, stamps[cols], stamp, self._readout_ns, bias)
        frame = np.broadcast_to(np.arange(cols.size), (n, cols.size)).reshape(-1)
        fraction = hist[:, cols, 1].reshape(-1) / float(self.camera.height)
        out = np.full_like(bearings, np.nan)
        rotated = grid.to_stamp(frame, fraction, bearings[:, cols].reshape(-1, 3))
        out[:, cols] = rotated.reshape(n, cols.size, 3)
        return out, row_tau

    def _gyro_rotations(
        self, stamps: npt.NDArray[np.int64], stamp: int, bias: FloatArray, have_gyro: bool
    ) -> tuple[FloatArray, BoolArray, bool, np.uint8, list[str]] | StageSkip:
        """Rotations from each fit-window column to now, which columns are usable, whether
        the gyro is used, the flags for all points and notes; or why there are no points."""
        opts = self.options
        columns = np.flatnonzero(stamps >= 0)
        columns = columns[columns < opts.fit_frames]
        rotations = np.repeat(np.eye(3)[None], stamps.shape[0], axis=0)
        usable_col = stamps >= 0
        end = stamp + self._readout_ns  # the last row of this frame with a rolling shutter
        covered = [k for k in columns[1:] if self._gyro.covers(int(stamps[k]), end)]
        usable_col[[k for k in columns[1:] if k not in covered]] = False
        if covered:  # one integration back over the whole fit window
            rotations[covered] = self._gyro.relative_rotations(stamps[covered], stamp, bias)
        notes: list[str] = []
        with_gyro = True
        flags_all = np.uint8(0)
        if columns.size > 1 and not usable_col[columns[1]]:
            # not even the last interval is covered
            if opts.require_gyro:
                what = (
                    "no gyro samples" if not have_gyro else "IMU does not cover the frame interval"
                )
                return StageSkip(f"{what} (require_gyro): no points")
            with_gyro = False
            flags_all = np.uint8(PointFlag.NO_GYRO | (PointFlag.IMU_GAP if have_gyro else 0))
            rotations[:] = np.eye(3)
            usable_col = stamps >= 0
            notes.append(
                "processed without gyro derotation: "
                + ("IMU does not cover the interval" if have_gyro else "no gyro samples")
            )
        usable_col[opts.fit_frames :] = False
        uncovered = int(np.count_nonzero(~usable_col[columns]))
        if with_gyro and uncovered:
            notes.append(
                f"IMU does not reach back over {uncovered} of the last {columns.size} frames: "
                "shorter track fits"
            )
        return rotations, usable_col, with_gyro, flags_all, notes

    def _integrate(self, tracked: _Tracked, stamp: int) -> _Integrated | StageSkip:
        """Stage 2: derotate each track's history with the gyro and fit bearing and rate
        at the track's reference time."""
        t0 = self.clock()
        opts = self.options
        tracks = tracked.tracks
        n_fit = opts.fit_frames
        if opts.fit_window_s is not None:
            window, floor = opts.fit_window_s, 3
            flt = self._heading_filter
            if (
                opts.fit_turning_window_s is not None
                and flt.heading is not None
                and flt.weights[1] >= opts.fit_turning_weight
            ):
                window, floor = opts.fit_turning_window_s, 2
            n_fit = max(windows.fit_columns(tracks.stamps_ns, stamp, window, floor, n_fit), 1)
        min_frames = min(opts.min_track_frames, max(n_fit, 2))
        stamps = tracks.stamps_ns[:n_fit]
        gyro = self._gyro_rotations(stamps, stamp, tracked.bias, len(self._gyro) > 0)
        if isinstance(gyro, StageSkip):
            seconds = (("integrate", self.clock() - t0),)
            return StageSkip(gyro.reason, (("no_gyro", tracks.num_tracks),), seconds)
        rotations, usable_col, with_gyro, flags_all, notes = gyro
        hist = tracks.history[:, :n_fit]
        n_tracks = hist.shape[0]
        w = hist.shape[1]
        bearings_h = self._history_bearings(stamp, tracks.ids, hist, stamps)
        tau = np.where(stamps[:w] >= 0, (stamps[:w] - stamp) * 1e-9, 0.0)
        row_tau = None
        if self._readout_ns:  # rolling shutter: each position at its row's time
            bearings_h, row_tau = self._derotate_rows(
                bearings_h, hist, stamps, tau, stamp, tracked.bias, with_gyro, usable_col
            )
        else:  # column k rotated by rotations[k] (a batched matmul: ~10x faster than einsum)
            by_col = np.matmul(bearings_h.transpose(1, 0, 2), rotations[:w].transpose(0, 2, 1))
            bearings_h = np.ascontiguousarray(by_col.transpose(1, 0, 2))  # (N, W, 3)
        mask = motion.all_finite(bearings_h) & usable_col[None, :w]
        enough = mask.sum(axis=1) >= min_frames
        enough &= mask[:, 0]
        tau_rate = None
        if row_tau is None:
            fit = fit_tracks(bearings_h, tau, mask & enough[:, None], opts.fit_order)
            e_now = bearings_h[:, 0]
        else:
            *timed, tau_rate = rs.fit_timed(
                bearings_h, row_tau, mask & enough[:, None], opts.fit_order, tau
            )
            fit = TrackFit(*timed)  # type: ignore[arg-type]
            e_now = rs.bearings_at_stamp(bearings_h[:, 0], fit.rate, row_tau[:, 0])
        ok = enough & fit.valid
        young = int(np.count_nonzero(~enough))
        dropped = (("young_track", young),) if young else ()
        if not ok.any():
            why = f"no track spans {min_frames} frames yet (tracks: {n_tracks})"
            seconds = (("integrate", self.clock() - t0),)
            return StageSkip(why, dropped, seconds, tuple(notes))
        idx = np.flatnonzero(ok)
        columns = np.flatnonzero(stamps >= 0)
        columns = columns[columns < n_fit]
        window_s = float(-tau[columns[columns < w]].min()) if columns.size > 1 else 1.0
        bearing_sigma = opts.pixel_noise_px / max(self.camera.fx, self.camera.fy)
        return _Integrated(
            stamps=stamps,
            rotations=rotations,
            with_gyro=with_gyro,
            flags_all=flags_all,
            window_s=window_s,
            e_now=e_now[idx],
            e=fit.bearing[idx],
            f=fit.rate[idx],
            f_sigma=fit.gain[idx] * bearing_sigma,
            tau_ref=fit.tau_ref[idx],
            pixels=tracks.pixels[idx],
            ids=tracks.ids[idx],
            notes=tuple(notes),
            dropped=dropped,
            timings=(("integrate", self.clock() - t0),),
            tau_rate=tau_rate[idx] if tau_rate is not None else None,
        )

    def _estimate_heading(
        self, integ: _Integrated, prev: int | None, stamp: int
    ) -> _Headed | StageSkip:
        """Stage 3: heading and leftover rotation from all derotated flows (updates the
        gyro-bias filter), the heading brought to the current stamp."""
        t0 = self.clock()
        opts = self.options
        if integ.with_gyro:
            self._bias.predict(max(stamp - (prev or stamp), 0) * 1e-9)
            # the leftover rotation of this window: the bias error, the gyro noise over the
            # window and the frame-to-frame scatter the bias filter measured beyond both
            prior = self._bias.cov_camera + np.eye(3) * (
                opts.gyro_noise_density**2 / max(integ.window_s, 1e-3) + self._bias.model_variance
            )
            if not opts.estimate_bias:
                prior = prior * 1e-12
        else:
            prior = opts.no_gyro_rotation_sigma**2 * np.eye(3)
        memory = self._residual_memory(integ.ids)
        weights = 1.0 / (1.0 + (memory / opts.residual_memory_sigma) ** 2)
        if opts.edge_radius_px is not None:
            weights = weights * hd.depth_edge_weights(
                integ.pixels,
                integ.e,
                integ.f,
                integ.f_sigma,
                self._state.last_heading,
                opts.edge_radius_px,
                opts.edge_log_scale,
                min_sin=opts.heading.min_sin,
                spread_factor=opts.edge_spread_factor,
                neighbours=_EDGE_NEIGHBOURS,
                neighbourhood=self._pixel_neighbours(integ),
            )
        hopts = opts.heading
        flt = self._heading_filter
        if flt.heading is not None and flt.weights[1] >= opts.confirm_below_turning:
            hopts = self._heading_unconfirmed  # turning: keep the second start
        est = hd.estimate_motion(
            integ.e,
            integ.f,
            integ.f_sigma,
            prior,
            options=hopts,
            rng=self._rng,
            initial_heading=self._state.last_heading,
            fit_weights=weights,
        )
        self._remember_residuals(integ.ids, stamp, est.residuals, memory)
        if integ.with_gyro and opts.estimate_bias:
            self._bias.update(
                est.rotation_error,
                est.rotation_cov,
                prior,
                opts.bias_inflation,
                max_sigma=opts.bias_observable_sigma,
            )
        timings = (("heading", self.clock() - t0),)
        if not est.translating or est.heading is None:
            self._state.last_heading = None
            self._state.heading_history = []
            self._heading_filter.reset()
            self._state.speed_state = None
            key = "no_translation" if not est.translating else "no_heading"
            return StageSkip(est.reason, ((key, integ.e.shape[0]),), timings)
        heading_ref = est.heading
        self._state.last_heading = heading_ref
        args = (
            stamp,
            heading_ref,
            float(motion.median(integ.tau_ref)),
            est.heading_sigma_rad,
            integ.stamps,
            integ.rotations,
        )
        if opts.heading_filter is not None:
            heading, heading_sigma = hf.filter_step(self._heading_filter, *args)
        else:  # a straight line through the last headings
            heading, heading_sigma = self._heading_now(*args)
        # remove the leftover rotation found jointly with the heading
        f = integ.f + motion.cross(est.rotation_error, integ.e)
        return _Headed(est, heading_ref, heading, heading_sigma, f, timings)

    def _residual_memory(self, ids: npt.NDArray[np.uint32]) -> FloatArray:
        """(N,) running mean coplanarity residual of the tracks ``ids`` (N,), in flow-noise
        sigmas; 0 for tracks without one (new tracks, no memory)."""
        memory = self._state.residual_memory
        if memory is None:
            return np.zeros(ids.shape[0])
        _, old_ids, old_mean = memory
        rows, found = _match_ids(old_ids, ids)
        return np.where(found, old_mean[rows], 0.0)

    def _remember_residuals(
        self, ids: npt.NDArray[np.uint32], stamp: int, res: FloatArray, old: FloatArray
    ) -> None:
        """Move each track's running mean residual towards this frame's ``res`` (N,)
        (flow-noise sigmas; NaN = not used, counts as 0) with time constant
        ``residual_memory_s``; a track without one starts at its residual."""
        tau = self.options.residual_memory_s
        if tau is None:
            return
        memory = self._state.residual_memory
        dt = (stamp - memory[0]) * 1e-9 if memory is not None else 0.0
        gain = 1.0 - math.exp(-max(dt, 0.0) / tau)
        r = np.nan_to_num(res, nan=0.0)
        new = np.where(old != 0.0, old + gain * (r - old), r)
        self._state.residual_memory = (stamp, ids.copy(), new)

    def _filter_ranges(
        self,
        integ: _Integrated,
        headed: _Headed,
        stamp: int,
        ranges: FloatArray,
        rel_sigma: FloatArray,
        usable: BoolArray,
    ) -> tuple[FloatArray, FloatArray]:
        """Per-track filter of r/|t|: the previous frame's scaled point moved on by the
        elapsed time (minus heading x dt, rotated with the gyro into this frame) predicts
        this frame's, up to the speed change, which is common to all points and taken as
        the median ratio of measured to predicted r/|t|; fused by variance with the
        measurement in inverse range. Returns (N,) r/|t| (s) and its relative 1-sigma."""
        opts = self.options
        out_r = ranges.copy()
        out_rel = rel_sigma.copy()
        prev = self._state.range_state
        if prev is not None:
            p_stamp, p_ids, p_points, p_rel, p_heading = prev
            cols = np.flatnonzero(integ.stamps == p_stamp)
            if cols.size and cols[0] > 0:
                dt = (stamp - p_stamp) * 1e-9
                rot = integ.rotations[int(cols[0])]
                rows, found = _match_ids(p_ids, integ.ids)
                moved = (p_points[rows] - p_heading[None, :] * dt) * math.exp(
                    -self._speed_filter.rate * dt
                )
                pred = moved @ rot.T
                r_pred = np.einsum("ni,ni->n", pred, integ.e_now)
                # the speed change is common to every static point: take it from the
                # measurements themselves (the filtered speed rate lags an acceleration)
                both = found & usable & (r_pred > 0) & (ranges > 0)
                if np.count_nonzero(both) >= 20:
                    log_ratio = np.log(ranges[both] / r_pred[both])
                    r_pred = r_pred * float(np.exp(motion.median(log_ratio)))
                rel_pred = np.sqrt(p_rel[rows] ** 2 + opts.range_process_rel**2 * dt)
                # fused in inverse range (the noise of |ToR| is closer to Gaussian there)
                inv_p = 1.0 / np.where(r_pred > 0, r_pred, np.nan)
                inv_m = 1.0 / ranges
                var_p = (rel_pred * inv_p) ** 2
                var_m = (rel_sigma * inv_m) ** 2
                ok = found & usable & (r_pred > 0) & np.isfinite(var_p) & np.isfinite(var_m)
                ok &= np.abs(inv_m - inv_p) <= opts.range_gate * np.sqrt(var_p + var_m)
                w_p = np.where(ok, var_m / np.maximum(var_p + var_m, 1e-300), 0.0)
                inv = np.where(ok, w_p * inv_p + (1.0 - w_p) * inv_m, inv_m)
                var = np.where(ok, var_p * var_m / np.maximum(var_p + var_m, 1e-300), var_m)
                out_r = 1.0 / inv
                out_rel = np.where(ok, np.sqrt(var) / np.maximum(np.abs(inv), 1e-12), rel_sigma)
        keep = usable & np.isfinite(out_r) & np.isfinite(out_rel)
        points = integ.e_now[keep] * out_r[keep, None]
        self._state.range_state = (
            stamp, integ.ids[keep].copy(), points, out_rel[keep], headed.heading.copy()
        )  # fmt: skip
        return out_r, out_rel

    def _pixel_neighbours(self, integ: _Integrated) -> tuple[FloatArray, npt.NDArray[np.intp]]:
        """The nearest tracks of each of ``integ``'s N tracks in the image (itself first):
        (N, K) distances, pixels (inf where none), and indices (N where none), for both the
        depth-edge weights and the local looming rule: one k-d tree query per frame, with
        the larger of their neighbour counts and radii (each takes its own columns and
        radius of it), kept for the frame's ``integ``."""
        cached = self._neighbours_of
        if cached is not None and cached[0] is integ:
            return cached[1]
        opts = self.options
        n = integ.pixels.shape[0]
        k = max(min(max(opts.neighbours, _EDGE_NEIGHBOURS) + 1, n), 1)
        radius = max(opts.neighbour_radius_px, opts.edge_radius_px or 0.0)
        dist, nb = cKDTree(integ.pixels).query(integ.pixels, k=k, distance_upper_bound=radius)
        found = (
            np.asarray(dist, dtype=np.float64).reshape(n, k),
            np.asarray(nb, dtype=np.intp).reshape(n, k),
        )
        self._neighbours_of = (integ, found)
        return found

    def _local_looming(self, integ: _Integrated, f: FloatArray) -> motion.LocalFit | None:
        """The local deformation rule over each feature's pixel neighbours (None when there
        are too few features)."""
        opts = self.options
        n = integ.e.shape[0]
        k = min(opts.neighbours, n - 1)
        if k < opts.min_neighbours:
            return None
        dist, nb = self._pixel_neighbours(integ)
        dist, nb = dist[:, 1 : k + 1], nb[:, 1 : k + 1]
        nb_mask = (dist < opts.neighbour_radius_px) & (nb < n)
        nb_safe = np.where(nb_mask, nb, 0)
        # neighbours must refer to the same time (tracks of different lengths do not)
        nb_mask &= np.abs(integ.tau_ref[nb_safe] - integ.tau_ref[:, None]) < 1e-4
        noise = math.sqrt(2.0) * float(motion.median(integ.f_sigma))
        return motion.fit_local_looming(
            integ.e,
            f,
            integ.e[nb_safe],
            f[nb_safe],
            nb_mask,
            noise=noise,
            min_neighbours=opts.min_neighbours,
            iterations=opts.looming_iterations,
        )

    def _movers_and_fused(
        self, integ: _Integrated, headed: _Headed, omega: FloatArray, local: motion.LocalFit | None
    ) -> tuple[BoolArray, FloatArray, motion.FusedLooming]:
        """Independently moving points, the heading-coplanarity residuals, and L fused
        from the local rule and the heading route (movers excluded from the route)."""
        opts = self.options
        e, f_sigma, heading_ref = integ.e, integ.f_sigma, headed.heading_ref
        res = np.nan_to_num(headed.est.residuals, nan=0.0)
        moving = np.abs(res) > opts.moving_sigma
        # A static point's omega is a positive multiple of e x heading (it lies in front of
        # the camera): a clearly negative multiple is something moving against the flow.
        exh = motion.cross(e, heading_ref)
        sin = motion.row_norms(exh)
        along = np.einsum("ni,ni->n", omega, exh) / np.maximum(sin, 1e-12)
        along_sigma = (
            opts.moving_sigma if opts.moving_along_sigma is None else opts.moving_along_sigma
        )
        moving |= (sin > opts.heading_min_sin) & (along < -along_sigma * f_sigma)
        route = motion.looming_from_heading(
            e,
            omega,
            heading_ref,
            omega_sigma=f_sigma,
            heading_sigma=headed.est.heading_sigma_rad,
            min_sin=opts.heading_min_sin,
        )
        if local is not None:
            both = local.valid & route.valid
            l_gap = np.abs(np.where(both, local.looming - route.looming, 0.0))
            spread = np.sqrt(np.where(both, local.variance + route.variance, 1.0))
            route_sigma = (
                opts.moving_sigma if opts.moving_route_sigma is None else opts.moving_route_sigma
            )
            moving |= both & (l_gap > route_sigma * spread)
        route = motion.HeadingRoute(
            np.where(moving, np.nan, route.looming),
            np.where(moving, np.inf, route.variance),
            route.valid & ~moving,
        )
        fused = motion.fuse_looming(
            local,
            route,
            e.shape[0],
            max_disagreement=opts.moving_sigma,
            local_variance_scale=opts.local_variance_scale,
        )
        return moving, res, fused

    def _to_now(
        self,
        integ: _Integrated,
        headed: _Headed,
        at_ref: motion.OwlQuantities,
        moving: BoolArray,
        stamp: int,
    ) -> tuple[FloatArray, FloatArray, BoolArray]:
        """Each point from its fit's reference time to the current stamp: (N,) L now, 1/s,
        (N, 3) omega now, 1/s, and which points are still valid and in front."""
        e_now, tau_ref = integ.e_now, integ.tau_ref
        # Under a constant relative velocity the scaled point moves by -heading per second.
        # The fused heading turned from heading_ref to heading meanwhile (a curving path);
        # turn every point's heading with it (trapezoid rule for the displacement).
        turn = _small_rotation(headed.heading_ref, headed.heading)
        h_ref_i = np.where(at_ref.valid[:, None], at_ref.heading, 0.0)
        h_now_i = h_ref_i @ turn.T
        point_now = at_ref.points + 0.5 * (h_ref_i + h_now_i) * tau_ref[:, None]
        range_over_speed_now = motion.row_norms(point_now)
        ahead = np.einsum("ni,ni->n", point_now, e_now) > 0
        ok_now = at_ref.valid & ahead & (range_over_speed_now > 0)
        h_i = np.where(ok_now[:, None], h_now_i, 0.0)
        # point_now is in units of the speed at the fit reference time; a changing speed
        # (rate s = d ln|t|/dt, measured from frame to frame) rescales it to the current one
        # (without estimate_speed_change the filter never steps and its log change is 0)
        self._update_speed_filter(stamp, integ.ids, point_now, h_i, ok_now & ~moving, tau_ref)
        to_current = self._speed_filter.log_change(tau_ref)
        safe = np.where(ok_now, range_over_speed_now * np.exp(to_current), 1.0)
        looming_now = np.einsum("ni,ni->n", h_i, e_now) / safe
        omega_now = motion.cross(e_now, h_i) / safe[:, None]
        return looming_now, omega_now, ok_now

    def _update_time_offset(
        self, integ: _Integrated, headed: _Headed, tracked: _Tracked, stamp: int
    ) -> tuple[tuple[str, float], ...]:
        """``estimate_time_offset``: feed this frame's leftover rotation to the offset filter
        (:mod:`owl_core.time_offset`) and use its estimate once it is good enough. Returns
        the stage time."""
        t0 = self.clock()
        filt = self._offset_filter
        if filt is None or not integ.with_gyro or tracked.prev_ns is None:
            return ()
        self._offset_frames += 1
        if not self.options.estimate_time_offset and self._offset_frames % OBSERVE_STRIDE:
            return ()
        since = self._offset_prev_ns if self._offset_prev_ns is not None else tracked.prev_ns
        filt.predict(max(stamp - since, 0) * 1e-9)
        self._offset_prev_ns = stamp
        used = self._gyro.imu_time_offset_ns
        model = self._offset_model(
            integ.stamps,
            stamp,
            tracked.bias,
            filt.offset_s - used * 1e-9,
            with_phi=not self.options.estimate_time_offset,
        )
        wide = np.eye(3) * _OFFSET_LEFTOVER_PRIOR**2
        est = hd.estimate_motion(
            integ.e,
            integ.f,
            integ.f_sigma,
            wide,
            options=self.options.heading,
            rng=self._offset_rng,
            initial_heading=headed.est.heading,
        )
        info = np.linalg.inv(est.rotation_cov) - np.linalg.inv(wide)
        if model is not None and est.translating and np.all(np.linalg.eigvalsh(info) > 0):
            offset_leftover, jacobian, delta, by_phi = model
            bias_cam = self._r_ci.T @ tracked.bias
            filt.update(
                est.rotation_error,
                np.linalg.inv(info),
                offset_leftover,
                jacobian,
                used * 1e-9 + delta,
                bias_cam,
                by_phi,
            )
            if self.options.estimate_time_offset and filt.offset_sigma_s < (
                TIME_OFFSET_APPLY_SIGMA_S
            ):
                self._apply_time_offset(filt)
        return (("time_offset", self.clock() - t0),)

    def _set_imu_time_offset(self, offset_s: float) -> None:
        """Derotate with the IMU time offset ``offset_s`` (s) from now on."""
        rotation = self.options.camera_to_imu_rotation_xyzw
        self._gyro.set_calibration(rotation, round(offset_s * 1e9))

    def _apply_time_offset(self, filt: to.TimeOffsetFilter) -> None:
        """Derotate with the estimated offset from now on, and with the offset filter's bias,
        estimated jointly with it: the bias filter alone took the offset's leftover rotation
        for a bias (tens of mrad/s for a 30 ms offset while turning), which its gate would
        then keep it from unlearning. On ``brisk`` with the offset right the heading median
        goes 0.24 -> 0.27 deg with this; with a 30 ms offset, 0.39 deg (14 deg without)."""
        self._set_imu_time_offset(filt.offset_s)
        self._bias.bias = self._r_ci @ filt.bias_camera
        self._bias.cov = self._r_ci @ filt.cov[1:4, 1:4] @ self._r_ci.T

    def _offset_model(
        self,
        stamps: npt.NDArray[np.int64],
        stamp: int,
        bias: FloatArray,
        delta_s: float,
        with_phi: bool,
    ) -> tuple[FloatArray, FloatArray, float, FloatArray | None] | None:
        """The leftover rotation an offset ``delta_s`` (s) above the one in use would leave
        in this frame, and its derivative: the slope over the fit window of the rotation by
        which each column's derotation changes (:mod:`owl_core.time_offset`), from the gyro
        with the camera times shifted by delta (exact, not linearised) and by delta - 1 ms.

        Also the leftover a small error ``phi`` of the configured extrinsic rotation would
        leave (the true one ``R_ci Exp(phi)``: each gyro rotation in the camera frame is
        conjugated by ``Exp(phi)``), as its (3, 3) derivative by ``phi`` at 0 (None unless
        ``with_phi``).

        Returns ((3,) leftover rad/s, (3,) d leftover / d offset rad/s per s, the delta
        used s, (3, 3) d leftover / d phi rad/s per rad or None), linearised at a delta the gyro
        covers (0 when the IMU does not reach ``stamp + delta`` yet); None without 3
        columns covered.
        """
        cols = stamps[stamps >= 0]
        step = 1_000_000  # ns, the numerical derivative's step (backwards: IMU we have)
        if cols.size < 3 or not self._gyro.covers(int(cols.min()) - step, stamp):
            return None
        delta = round(delta_s * 1e9)
        if not self._gyro.covers(int(cols.min()) + min(delta, 0) - step, stamp + delta):
            delta = 0
        base = self._gyro.relative_rotations(cols, stamp, bias)
        tau = (cols - stamp) * 1e-9
        dt = tau - tau.mean()

        base_t = np.swapaxes(base, -1, -2)

        def rate(moved: FloatArray) -> FloatArray:
            out: FloatArray = (dt @ so3_log(moved @ base_t)) / float(dt @ dt)
            return out

        def leftover(shift: int) -> FloatArray:
            return rate(self._gyro.relative_rotations(cols + shift, stamp + shift, bias))

        at = leftover(delta) if delta else np.zeros(3)
        slope = (at - leftover(delta - step)) / (step * 1e-9)
        by_phi = None
        if with_phi:
            eps = 1e-3  # rad, the numerical derivative's step
            turns = [so3_exp(eps * axis) for axis in np.eye(3)]
            by_phi = np.stack([rate(t.T @ base @ t) / eps for t in turns], axis=1)
        return at, slope, delta * 1e-9, by_phi

    def _rates_at_bearing_time(self, integ: _Integrated, headed: _Headed) -> FloatArray:
        """The rates ``f`` (N, 3), 1/s, at the time of their bearings.

        With a rolling shutter a track's rate belongs to the centroid of its entries' row
        times (``tau_rate``), a few ms after its bearing's ``tau_ref``. A static point's
        derotated rate grows as ``df/dt = 2 L f`` (plus a part along the bearing; from
        ``f = -(I - e e^T) t / r`` and ``dr/dt = -L r``), so at ``tau_ref`` it is
        ``f (1 - 2 L (tau_rate - tau_ref))``, L from the heading route ``|f| cot(alpha)``
        (none within ``heading_min_sin`` of the focus of expansion, where f -> 0).
        Neighbours in other rows then compare rates of one time. Global shutter: ``f``.
        """
        f = headed.f
        if integ.tau_rate is None:
            return f
        h = headed.heading_ref
        cos = integ.e @ h
        sin = motion.row_norms(motion.cross(integ.e, h[None, :]))
        near = sin < self.options.heading_min_sin
        looming = np.where(near, 0.0, motion.row_norms(f) * cos / np.where(near, 1.0, sin))
        scale = 1.0 - 2.0 * looming * (integ.tau_rate - integ.tau_ref)
        out: FloatArray = f * scale[:, None]
        return out

    def _looming(self, integ: _Integrated, headed: _Headed, stamp: int) -> _Loomed:
        """Stage 4: L per feature (local rule fused with the heading route), movers, the
        OWL quantities at the current stamp, quality and flags."""
        t0 = self.clock()
        opts = self.options
        e, f = integ.e, self._rates_at_bearing_time(integ, headed)
        omega = motion.cross(f, e)
        local = self._local_looming(integ, f)
        moving, res, fused = self._movers_and_fused(integ, headed, omega, local)
        at_ref = motion.owl_quantities(e, fused.looming, omega, min_tor=opts.min_tor)
        looming_now, omega_now, ok_now = self._to_now(integ, headed, at_ref, moving, stamp)
        quantities = motion.owl_quantities(
            integ.e_now, looming_now, omega_now, min_tor=opts.min_tor
        )
        valid = quantities.valid & ok_now
        n = e.shape[0]
        q_local = np.where(local.valid, local.quality, 1.0) if local is not None else np.ones(n)
        # precision: relative 1-sigma of L against |ToR| (= relative sigma of r/|t|)
        tor_ref = np.sqrt(np.nan_to_num(at_ref.tor[:, 0]) ** 2 + np.sum(omega**2, axis=1))
        rel_sigma = np.sqrt(np.where(fused.valid, fused.variance, np.inf)) / np.maximum(
            tor_ref, 1e-12
        )
        if opts.range_filter:
            ranges, rel_sigma = self._filter_ranges(
                integ, headed, stamp, quantities.range_over_speed, rel_sigma,
                valid & fused.valid & ~moving,
            )  # fmt: skip
            # ToR scales with 1 / (r/|t|): L and omega keep the point's own heading
            scale = np.where(valid & np.isfinite(ranges), quantities.range_over_speed, 1.0)
            scale = scale / np.where(valid & np.isfinite(ranges), ranges, 1.0)
            looming_now, omega_now = looming_now * scale, omega_now * scale[:, None]
            quantities = motion.owl_quantities(
                integ.e_now, looming_now, omega_now, min_tor=opts.min_tor
            )
        q_precision = 1.0 / (1.0 + (rel_sigma / opts.quality_rel_sigma) ** 2)
        quality = q_local * q_precision / (1.0 + (res / opts.moving_sigma) ** 2)
        flags = fused.flags | integ.flags_all
        flags = flags | np.where(moving, np.uint8(PointFlag.MOVING), np.uint8(0))
        flags = flags | np.where(
            quality < opts.min_quality, np.uint8(PointFlag.LOW_QUALITY), np.uint8(0)
        )
        keep = fused.valid & valid
        no_l = int(np.count_nonzero(~fused.valid))
        no_tor = int(np.count_nonzero(fused.valid & ~valid))
        dropped: tuple[tuple[str, int], ...] = (("no_looming", no_l),) if no_l else ()
        dropped += (("no_translation_signal", no_tor),) if no_tor else ()
        notes: tuple[str, ...] = ()
        if not keep.any():
            notes = ("no feature has a looming estimate (too few neighbours, at the FOE)",)
        elif no_l:
            notes = (f"{no_l} features without L (too few neighbours or at the FOE)",)
        return _Loomed(
            looming=looming_now,
            omega=omega_now,
            rot=quantities.rot,
            range_over_speed=quantities.range_over_speed,
            points=quantities.points,
            quality=quality,
            flags=flags,
            keep=keep,
            notes=notes,
            dropped=dropped,
            timings=(("looming", self.clock() - t0),),
        )

    def _compose(
        self,
        stamp: int,
        integ: _Integrated,
        headed: _Headed,
        loomed: _Loomed,
        log: _FrameLog,
        t_start: float,
    ) -> FrameResult:
        """Stage 5: the frame's result, the points that have L and a translation signal."""
        keep = loomed.keep
        log.timings["total"] = self.clock() - t_start
        return FrameResult(
            stamp_ns=stamp,
            pixels=integ.pixels[keep],
            bearings=integ.e_now[keep],
            looming=loomed.looming[keep],
            omega=loomed.omega[keep],
            rot=loomed.rot[keep],
            range_over_speed=loomed.range_over_speed[keep],
            points=loomed.points[keep],
            quality=loomed.quality[keep],
            ids=integ.ids[keep].astype(np.uint32),
            flags=loomed.flags[keep].astype(np.uint8),
            heading=headed.heading.copy(),
            heading_sigma_rad=headed.heading_sigma,
            gyro_bias=self._bias.bias.copy(),
            timings=log.timings,
            reasons=tuple(log.reasons),
            dropped=log.dropped,
            speed_rate=self._speed_filter.rate,
        )
