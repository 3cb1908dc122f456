"""Live camera-IMU calibration check: does the rotation the images show match the gyro?

Two judges, every ``check_every`` frames.

**The online estimate** (the default judge once it has data). The engine runs its online
offset filter observe-only (:mod:`owl_core.time_offset`, ``observe_time_offset``): each
frame's leftover rotation, fitted jointly with the heading, gives the time offset (from the
angular acceleration) and the error of the configured rotation (from the rotation rate).
Translation is part of that fit, so it does not leak into the estimate. When it has taken
``filter_min_updates`` frames, and took some since the last check with its gate dropping
at most one in three of them, the verdict is its own (and the window's per-frame fits,
about 5 ms a frame, are not computed meanwhile):

- the **offset** disagrees by more than ``filter_offset_threshold_s`` (default 5 ms) and 3
  of its sigma, once that sigma is below ``filter_max_sigma_s`` (2 ms: it needs changes of
  the rotation rate; a steady turn leaves it undetermined, and it is not judged);
- the **rotation** disagrees by more than ``filter_angle_threshold_deg`` (3 deg) and beyond
  its 99.9 % chi-square bound, over the directions it determines (1-sigma below
  ``filter_max_angle_sigma_deg``: about the axis of a one-axis motion it stays at its prior).

Measured on rendered scenarios (320x240, 30 Hz): with the calibration right, what it
judges stays within 1 ms and 2 deg on ``handheld``, ``brisk``, ``street``, ``mover``,
``car`` and ``turn`` (whose steady turn leaves the offset undetermined), and none WARNs;
10 ms offsets are read as 9.5-10.8 ms by the 2 s check on ``handheld``, ``brisk``,
``street``, ``mover`` and ``car``; a rotation 6 deg off is read as 5.9 deg.

**The window** judges otherwise: before the estimate has data (a frame's IMU arrived too
late for it), while it gets none (turning on the spot: no translation, no heading fit),
and when its gate drops most frames, as it does for gross errors (an identity
instead of the 120 deg forward mount, a 40-60 ms lag) and on recordings whose leftover
rotations scatter far beyond their stated noise (the real handheld walk). It fits the
frame-to-frame camera rotation on the tracks (:func:`owl_core.calibration.
rotation_from_bearings`) and compares the last ``window_s`` seconds with the gyro:

- the **time offset** from the rate magnitudes (rotation-invariant,
  :func:`owl_core.calibration.search_offset`, then the joint refine when possible);
- the **rotation**: when the window excites two axes, the full estimate
  (:func:`owl_core.calibration.calibrate`, no bootstrap) and its angle to the configured
  rotation; with one axis only, the angle between the configured rotation applied to the
  visual rotation increments and the gyro increments.

It disagrees when the offset differs from the configured one by more than
``offset_threshold_s`` (default 20 ms) or the rotation by more than
``angle_threshold_deg`` (default 5 deg), and by more than 3 sigma of the window's
estimate. Translation leaks into its rotation fits: with the calibration right it reads up
to 2.3 deg and 13 ms on ``handheld``, and on ``car`` and ``turn`` (3-8 m/s) up to 44 deg
and 100 ms, which is why the online estimate judges whenever it can.

Units: seconds, radians (angles reported in degrees where the name says so); stamps are
integer nanoseconds. One rotation fit per frame (vectorised over features).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from owl_core import calibration as cal
from owl_core.camera import CameraModel
from owl_core.errors import CalibrationError, InvalidInputError
from owl_core.geometry import matrix_to_quat_xyzw, so3_exp, so3_log
from owl_core.time_offset import GATE, OnlineCalibration
from owl_core.tracker import Tracks
from owl_core.types import GyroSamples

FloatArray = npt.NDArray[np.float64]

__all__ = ["CalibrationMonitor", "MonitorOptions", "MonitorVerdict"]

#: the end of a verdict's message when images and gyro disagree.
_DISAGREE = "; images and gyro disagree: run owl_calibrate"


@dataclass(frozen=True)
class MonitorOptions:
    """Settings of :class:`CalibrationMonitor`.

    Attributes:
        window_s: compare the last this many seconds, s (> 0).
        check_every: frames between two comparisons, count (>= 1).
        min_rate: intervals turning slower than this do not count as motion, rad/s.
        min_moving_intervals: fewer moving intervals in the window -> no verdict, count.
        angle_threshold_deg: rotation disagreement that warns, degrees (and more than 3
            sigma of the window's estimate).
        offset_threshold_s: time-offset disagreement that warns, s (and more than 3 sigma).
        filter_offset_threshold_s: the same, when the offset comes from the engine's
            online filter, s (and more than 3 of its sigma).
        filter_max_sigma_s: the online filter's offset is judged once its 1-sigma is below
            this, s.
        filter_max_angle_sigma_deg: the online filter's rotation error is judged along
            the directions whose 1-sigma is below this, degrees.
        filter_angle_threshold_deg: rotation disagreement that warns when it comes from
            the online filter, degrees (and beyond its 99.9 % chi-square bound).
        filter_min_updates: the online filter judges once it has taken this many frames
            (while its gate keeps more than it drops), count.
        max_offset_s: the offset search covers +-this, s.
        max_features: features used per rotation fit (a subsample), count.
        pixel_noise_px: tracking noise, pixels (the rotation fits' noise floor).
    """

    window_s: float = 2.0
    check_every: int = 30
    min_rate: float = 0.1
    min_moving_intervals: int = 25
    angle_threshold_deg: float = 5.0
    offset_threshold_s: float = 0.020
    filter_offset_threshold_s: float = 0.005
    filter_max_sigma_s: float = 0.002
    filter_max_angle_sigma_deg: float = 1.0
    filter_angle_threshold_deg: float = 3.0
    filter_min_updates: int = 6
    max_offset_s: float = 0.1
    max_features: int = 120
    pixel_noise_px: float = 0.3

    def __post_init__(self) -> None:
        for name in (
            "window_s",
            "min_rate",
            "angle_threshold_deg",
            "offset_threshold_s",
            "filter_offset_threshold_s",
            "filter_max_sigma_s",
            "filter_max_angle_sigma_deg",
            "filter_angle_threshold_deg",
            "max_offset_s",
            "pixel_noise_px",
        ):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise InvalidInputError(f"{name} must be positive and finite, got {value!r}")
        for name, low in (
            ("check_every", 1),
            ("min_moving_intervals", 3),
            ("max_features", 10),
            ("filter_min_updates", 1),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InvalidInputError(f"{name} must be an integer >= {low}, got {value!r}")


@dataclass(frozen=True)
class MonitorVerdict:
    """One comparison of images and gyro.

    Attributes:
        stamp_ns: camera stamp of the newest frame compared, ns.
        disagrees: True when the rotation or the offset is beyond its threshold.
        angle_deg: rotation disagreement, degrees (full estimate vs configured when
            ``rotation_xyzw`` is set, else the misalignment of the one excited axis).
        rotation_xyzw: (4,) estimated camera_to_imu rotation (x, y, z, w), or None when the
            window excited one axis only.
        offset_s: estimated imu_time_offset, s.
        source: "online" (the engine's online offset and rotation-error filter) or
            "window" (the fits over the last ``window_s``).
        offset_sigma_s: 1-sigma of ``offset_s``, s (NaN when the window gave none).
        configured_offset_s: the configured one, s.
        moving_intervals: frame intervals in the window that turned, count (``online``:
            the frames the filter took).
        message: one line saying what was found.
    """

    stamp_ns: int
    disagrees: bool
    angle_deg: float
    rotation_xyzw: FloatArray | None
    offset_s: float
    configured_offset_s: float
    moving_intervals: int
    message: str
    source: str = "window"
    offset_sigma_s: float = math.nan


class CalibrationMonitor:
    """Compares the camera rotation seen in the images with the gyro, continuously.

    Args:
        camera: the camera model of the tracked images.
        camera_to_imu: (3, 3) configured rotation taking camera vectors into the IMU frame.
        imu_time_offset_s: configured IMU stamp minus camera stamp, s.
        options: settings.
    """

    def __init__(
        self,
        camera: CameraModel,
        camera_to_imu: npt.ArrayLike,
        imu_time_offset_s: float,
        options: MonitorOptions | None = None,
    ) -> None:
        r = np.asarray(camera_to_imu, dtype=np.float64)
        if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6):
            raise CalibrationError(f"camera_to_imu must be a (3, 3) rotation, got {r.tolist()}")
        self.camera = camera
        self.options = opts = options if options is not None else MonitorOptions()
        self._r = r
        self._offset = float(imu_time_offset_s)
        self._fit_options = cal.CalibrationOptions(
            max_offset_s=opts.max_offset_s,
            pixel_noise_px=opts.pixel_noise_px,
            min_intervals=opts.min_moving_intervals,
            min_second_axis_rate=opts.min_rate,
            bootstrap=0,
            exact_gyro=False,
        )
        self._rng = np.random.default_rng(0)
        self._intervals: collections.deque[tuple[int, int, FloatArray, float, int]] = (
            collections.deque()
        )
        self._frames = 0
        self._newest_ns = 0
        self._online_judges = False
        self._seen = (0, 0)  # the online filter's (updates, rejected) at the last check
        self.last: MonitorVerdict | None = None

    def reset(self) -> None:
        """Forget the window (e.g. after a time jump)."""
        self._intervals.clear()
        self._frames = 0
        self._online_judges = False
        self._seen = (0, 0)
        self.last = None

    def _add_tracks(self, tracks: Tracks) -> None:
        stamps = tracks.stamps_ns
        if stamps.shape[0] < 2 or stamps[1] < 0:
            return
        h = tracks.history
        ok = np.flatnonzero(np.all(np.isfinite(h[:, :2]), axis=(1, 2)))
        if ok.shape[0] < self._fit_options.min_inliers:
            return
        if ok.shape[0] > self.options.max_features:
            ok = ok[:: math.ceil(ok.shape[0] / self.options.max_features)]
        e1 = self.camera.pixel_to_bearing(h[ok, 0])
        e0 = self.camera.pixel_to_bearing(h[ok, 1])
        good = np.all(np.isfinite(e0), axis=1) & np.all(np.isfinite(e1), axis=1)
        rot = cal.interval_rotations(
            [(int(stamps[1]), int(stamps[0]), e0[good], e1[good])],
            max(self.camera.fx, self.camera.fy),
            self._fit_options,
        )
        if len(rot):
            self._intervals.append(
                (int(rot.t0_ns[0]), int(rot.t1_ns[0]), rot.theta[0], float(rot.sigma[0]), 0)
            )
        newest = int(stamps[0])
        while self._intervals and self._intervals[0][0] < newest - self.options.window_s * 1e9:
            self._intervals.popleft()

    def update(
        self,
        tracks: Tracks | None,
        gyro: GyroSamples,
        bias_imu: npt.ArrayLike = (0, 0, 0),
        online: OnlineCalibration | None = None,
    ) -> MonitorVerdict | None:
        """Add one frame's tracks; every ``check_every`` frames compare with the gyro.

        Args:
            tracks: the tracker output of the newest frame (None: nothing to add).
            gyro: the gyro samples held (IMU frame, IMU clock, rad/s), covering the window.
            bias_imu: (3,) current gyro-bias estimate, IMU frame, rad/s (used when only one
                axis is excited).
            online: the engine's online offset and rotation-error estimate
                (:class:`~owl_core.time_offset.OnlineCalibration`, its offset in this
                monitor's convention), or None.

        Returns:
            The new verdict when a comparison ran (also kept in :attr:`last`), else None.
        """
        if tracks is not None:
            if not self._online_judges:  # the window's fits cost ~5 ms a frame
                self._add_tracks(tracks)
            if tracks.stamps_ns.shape[0]:
                self._newest_ns = int(tracks.stamps_ns[0])
        self._frames += 1
        if self._frames % self.options.check_every:
            return None
        # The online estimate judges once it has taken filter_min_updates frames, while its
        # gate drops at most one frame in three of those offered since the last check; a
        # grossly wrong rotation or offset leaves leftovers far beyond the noise, which the
        # gate drops (frames without IMU or without translation offer none): then the
        # window judges, collecting its fits again.
        seen = (online.updates, online.rejected) if online is not None else (0, 0)
        kept, dropped = seen[0] - self._seen[0], seen[1] - self._seen[1]
        self._seen = seen
        if online is not None and kept > 0 and 2 * dropped <= kept:
            if online.updates < self.options.filter_min_updates:
                return None
            if not self._online_judges:
                self._online_judges = True
                self._intervals.clear()
            self.last = self._online_verdict(online)
            return self.last
        self._online_judges = False
        return self._window_verdict(gyro, bias_imu)

    def _online_verdict(self, online: OnlineCalibration) -> MonitorVerdict:
        """The verdict from the engine's online estimate: the rotation error over the
        directions it determines (1-sigma below ``filter_max_angle_sigma_deg``; about the
        axis of a one-axis motion it stays at its prior), the offset once its 1-sigma is
        below ``filter_max_sigma_s``."""
        opts = self.options
        phi = np.asarray(online.misalignment, dtype=np.float64)
        var, axes = np.linalg.eigh(np.asarray(online.misalignment_cov, dtype=np.float64))
        known = var < math.radians(opts.filter_max_angle_sigma_deg) ** 2
        part = axes[:, known].T @ phi  # the error along the determined directions, rad
        angle = math.degrees(float(np.linalg.norm(part)))
        chi2 = float(np.sum(part**2 / var[known]))
        rotation_off = angle > opts.filter_angle_threshold_deg and chi2 > GATE
        q = matrix_to_quat_xyzw(self._r @ so3_exp(axes[:, known] @ part))
        what = (
            f"online estimate: camera_to_imu_rotation_xyzw [{q[0]:.4f}, {q[1]:.4f}, "
            f"{q[2]:.4f}, {q[3]:.4f}] ({angle:.1f} deg from the configured one"
        )
        if not np.all(known):
            free = axes[:, ~known][:, np.argmax(var[~known])]
            what += (
                f"; not determined about camera axis [{free[0]:.2f}, {free[1]:.2f}, "
                f"{free[2]:.2f}]: the motion turned about one axis"
            )
        what += ")"
        offset_off = False
        if online.offset_sigma_s < opts.filter_max_sigma_s:
            gap = online.offset_s - self._offset
            offset_off = abs(gap) > max(
                opts.filter_offset_threshold_s, 3.0 * online.offset_sigma_s
            )
            when = (
                f"imu_time_offset {online.offset_s:.4f} s (1-sigma {online.offset_sigma_s:.4f} "
                f"s; configured {self._offset:.4f} s)"
            )
        else:
            when = (
                f"imu_time_offset not determined yet (1-sigma {online.offset_sigma_s:.4f} s; "
                f"it needs changes of the rotation rate)"
            )
        disagrees = rotation_off or offset_off
        message = f"{what}, {when}" + (_DISAGREE if disagrees else "")
        return MonitorVerdict(
            self._newest_ns,
            disagrees,
            angle,
            q,
            float(online.offset_s),
            self._offset,
            online.updates,
            message,
            "online",
            online.offset_sigma_s,
        )

    def _window_verdict(self, gyro: GyroSamples, bias_imu: npt.ArrayLike) -> MonitorVerdict | None:
        """The verdict from the last ``window_s`` of frame-to-frame rotations alone."""
        if not self._intervals or len(gyro.stamp_ns) < 2:
            return None
        t0 = np.array([i[0] for i in self._intervals], dtype=np.int64)
        t1 = np.array([i[1] for i in self._intervals], dtype=np.int64)
        theta = np.array([i[2] for i in self._intervals], dtype=np.float64).reshape(-1, 3)
        sigma = np.array([i[3] for i in self._intervals], dtype=np.float64)
        dt = (t1 - t0).astype(np.float64) * 1e-9
        moving = np.linalg.norm(theta, axis=1) / dt >= self.options.min_rate
        n_moving = int(np.count_nonzero(moving))
        if n_moving < self.options.min_moving_intervals:
            return None
        k = theta.shape[0]
        rot = cal.IntervalRotations(
            t0, t1, theta, sigma, np.zeros(k, dtype=np.int64), np.zeros(k, dtype=bool)
        )
        try:
            offset, _, _ = cal.search_offset(rot, gyro, self.options.max_offset_s)
        except CalibrationError:
            return None
        estimate: FloatArray | None = None
        angle_sigma = offset_sigma = 0.0
        try:
            found = cal.calibrate(rot, gyro, self._fit_options)
            estimate = found.camera_to_imu
            offset = found.time_offset_s
            angle = math.degrees(float(np.linalg.norm(so3_log(estimate @ self._r.T))))
            angle_sigma = math.degrees(float(np.linalg.norm(found.rotation_sigma_rad)))
            offset_sigma = found.time_offset_sigma_s
        except CalibrationError:  # one axis only (or too few covered): its misalignment
            bias = np.asarray(bias_imu, dtype=np.float64)
            sub = rot.subset(moving)
            inc = cal.gyro_increments(gyro, sub.t0_ns, sub.t1_ns, offset)
            inc = inc - np.outer((sub.t1_ns - sub.t0_ns) * 1e-9, bias)
            pred = sub.theta @ self._r.T
            cos = np.einsum("ki,ki->k", pred, inc) / np.maximum(
                np.linalg.norm(pred, axis=1) * np.linalg.norm(inc, axis=1), 1e-15
            )
            angle = math.degrees(float(np.median(np.arccos(np.clip(cos, -1.0, 1.0)))))
        gap = offset - self._offset
        disagrees = angle > max(self.options.angle_threshold_deg, 3.0 * angle_sigma) or abs(
            gap
        ) > max(self.options.offset_threshold_s, 3.0 * offset_sigma)
        if estimate is not None:
            q = matrix_to_quat_xyzw(estimate)
            what = (
                f"estimated camera_to_imu_rotation_xyzw [{q[0]:.4f}, {q[1]:.4f}, {q[2]:.4f}, "
                f"{q[3]:.4f}] ({angle:.1f} deg from the configured one)"
            )
        else:
            q = None
            what = f"rotation axis {angle:.1f} deg off the configured rotation (one axis seen)"
        message = f"{what}, imu_time_offset {offset:.4f} s (configured {self._offset:.4f} s)" + (
            _DISAGREE if disagrees else ""
        )
        self.last = MonitorVerdict(
            int(t1[-1]),
            disagrees,
            angle,
            q,
            float(offset),
            self._offset,
            n_moving,
            message,
            "window",
            offset_sigma if estimate is not None else math.nan,
        )
        return self.last
