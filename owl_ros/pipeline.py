"""The message -> engine -> message path shared by node ``owl`` and ``owl_process``.

No DDS here: the caller hands in ROS messages (rclpy classes) with the time they arrived
on its clock (the node: monotonic time; ``owl_process``: the bag's log time), the same
clock the pipeline is given to tell the time, and gets back what to publish. Everything
that touches the engine runs in one thread; only :meth:`Pipeline.add_image` may be called
from another (it only queues).

The parts, one job each:

- :class:`~owl_ros.scheduler.Scheduler`: the one bounded frame queue (newest wins) and the
  rule saying when its oldest frame is ready;
- :class:`~owl_ros.timejump.TimeJumps`: the one place that detects backwards time;
- :class:`~owl_core.gyro.GyroBuffer`: the one IMU store, and its sanitation (NaN/inf
  rates, duplicate and out-of-order stamps dropped and counted, never interpolated across a
  gap longer than ``imu_max_gap_s``), vectorised; it lives as long as the pipeline and is
  handed to every engine built (a reconfigure keeps the IMU history);
- :class:`~owl_ros.counters.Counters`: the counts the diagnostics publish;
- :func:`~owl_ros.status.build_status`: the diagnostics, from one snapshot.

What :class:`Pipeline` does per input:

- ``camera_info``: converted once per distinct calibration; an invalid one (zero focal
  length, unknown distortion model) is reported and frames are skipped until a valid one
  arrives; a changed calibration rebuilds the engine.
- ``imu``: to the gyro buffer. A stamp more than ``max_frame_gap_s`` older than the newest
  one is a backwards time jump (bag loop, sim clock restart): the frames queued from before
  it are processed first (their outputs are returned by :meth:`Pipeline.add_imus`), then
  the engine is reset and a diagnostic says so.
- ``image`` / ``image/compressed``: queued; processed once ready (see
  :mod:`owl_ros.scheduler`). A bad image (unknown encoding, step too small, wrong data
  length, size differing from camera_info) is skipped with a reason naming the field and
  value; a stamp going backwards resets the engine.
- speed (``nav_msgs/Odometry`` or ``geometry_msgs/TwistStamped``): the speed nearest the
  image stamp (within ``speed_max_age_s``, at least ``min_speed``) scales x y z to metres
  and the cloud's ``speed`` field says so (``msg_adapters.pointcloud``).

Every processed frame gives one ``owl/points`` cloud (empty when the frame produced no
points; the reason is in diagnostics) with the input image's header, and an
``owl/heading`` when the frame gave a heading.
"""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from msg_adapters.camera_info import camera_info_to_model
from msg_adapters.diagnostics import StatusRecord
from msg_adapters.heading import heading_to_msg, heading_to_twist_covariance
from msg_adapters.image import compressed_to_frame, image_to_frame
from msg_adapters.imu import gyro_bias_to_msg, imus_to_gyro
from msg_adapters.pointcloud import frame_result_to_cloud
from msg_adapters.stamps import header_to_ns, make_header
from owl_core.calib_check import CalibrationMonitor, MonitorVerdict
from owl_core.camera import CameraModel
from owl_core.engine import OwlEngine
from owl_core.errors import OwlError
from owl_core.geometry import quat_xyzw_to_matrix
from owl_core.gyro import GyroBuffer, GyroProblem
from owl_core.types import FrameResult, GyroSamples, ImageFrame
from owl_ros.counters import Counters, Skip
from owl_ros.params import NodeOptions
from owl_ros.roles import Role
from owl_ros.scheduler import Frame, Probe, Scheduler
from owl_ros.status import StatusInputs, build_status
from owl_ros.timejump import ImageStamp, Jump, TimeJumps

__all__ = ["Output", "Pipeline"]

#: IMU considered silent (no waiting for it) when nothing arrived for this long, ns.
IMU_SILENT_NS = 1_000_000_000
#: speed messages kept.
SPEED_KEEP = 400


@dataclass(frozen=True)
class Output:
    """What one processed frame publishes.

    Attributes:
        result: the engine's FrameResult.
        cloud: sensor_msgs/PointCloud2 for owl/points (header = the image's header).
        heading: geometry_msgs/Vector3Stamped for owl/heading, or None (no heading).
        image: (H, W) uint8 grey image the engine tracked on (for owl/debug_image).
        header: the input image's std_msgs/Header.
        speed: m/s used to scale x y z to metres, or None (cloud in seconds).
        arrival_ns: when the image arrived, on the caller's clock, ns.
        heading_cov: geometry_msgs/TwistWithCovarianceStamped for
            owl/heading_with_covariance, or None.
        gyro_bias: geometry_msgs/Vector3Stamped for owl/gyro_bias: the engine's bias
            estimate after this frame, rad/s, IMU frame (stamp = the image's), or None
            when it is not finite.
    """

    result: FrameResult
    cloud: Any
    heading: Any | None
    image: npt.NDArray[np.uint8]
    header: Any
    speed: float | None
    arrival_ns: int
    heading_cov: Any | None = None
    gyro_bias: Any = None


@dataclass
class _Window:
    """Samples since the last diagnostics report (the counts are ``totals.since(base)``)."""

    start_ns: int | None = None
    base: Counters = field(default_factory=Counters)
    process_s: list[float] = field(default_factory=list)
    latency_s: list[float] = field(default_factory=list)
    cycle_s: list[float] = field(default_factory=list)
    stamp_latency_s: list[float] = field(default_factory=list)
    points: list[int] = field(default_factory=list)


@dataclass
class _Notes:
    """The newest text of each kind of problem, for diagnostics ("" for none)."""

    empty_reason: str = ""
    bad_image: str = ""
    imu_problem: str = ""
    jump: str = ""
    worker_error: str = ""
    qos_events: list[str] = field(default_factory=list)
    image_bytes: int = 0  # size of the newest image message's data


def _speed_of(msg: Any) -> tuple[int, float]:
    """(stamp ns, |linear velocity| m/s) of a nav_msgs/Odometry or TwistStamped."""
    twist = msg.twist.twist if hasattr(msg, "pose") else msg.twist
    v = twist.linear
    return header_to_ns(msg.header), math.sqrt(v.x * v.x + v.y * v.y + v.z * v.z)


def _camera_key(msg: Any) -> tuple[Any, ...]:
    """Everything of a CameraInfo that the camera model depends on."""
    return (
        int(msg.width),
        int(msg.height),
        str(msg.distortion_model),
        tuple(float(v) for v in msg.k),
        tuple(float(v) for v in msg.d),
        tuple(float(v) for v in msg.p),
        int(msg.binning_x),
        int(msg.binning_y),
        int(msg.roi.x_offset),
        int(msg.roi.y_offset),
        int(msg.roi.width),
        int(msg.roi.height),
    )


def imu_problem_text(problem: GyroProblem) -> str:
    """The diagnostics line for a rejected or gap-opening IMU sample."""
    if problem.kind == "non_finite":
        return f"imu.angular_velocity not finite: {list(problem.rate)}"
    prior = problem.prior_ns if problem.prior_ns is not None else problem.stamp_ns
    if problem.kind == "gap":
        return (
            f"IMU gap of {(problem.stamp_ns - prior) * 1e-6:.1f} ms before "
            f"{problem.stamp_ns} ns (> imu_max_gap_s)"
        )
    return f"imu stamp {problem.stamp_ns} ns not after {prior} ns ({problem.kind})"


class Pipeline:
    """Messages in, FrameResults and output messages out (see the module docstring).

    Args:
        options: node options (engine options included).
        clock: the current time, ns, on the clock of the arrival times the caller gives
            (default: monotonic time).
        live: frames arrive in real time (the node): a newer frame the IMU covers
            replaces older queued ones (``owl_ros.scheduler``); False (``owl_process``)
            keeps every frame.
    """

    def __init__(
        self,
        options: NodeOptions | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
        live: bool = False,
    ) -> None:
        self.options = opts = options if options is not None else NodeOptions()
        #: the injected clock (read it; the scheduler shares it).
        self.clock = clock
        self._scheduler = Scheduler(opts.queue_size, opts.imu_wait_s, clock, skip_stale=live)
        self._jumps = TimeJumps(round(opts.engine.max_frame_gap_s * 1e9))
        eng = opts.engine
        self._gyro = GyroBuffer(
            eng.camera_to_imu_rotation_xyzw, round(eng.imu_time_offset_s * 1e9)
        )
        self._engine: OwlEngine | None = None
        self._camera: CameraModel | None = None
        self._camera_key: tuple[Any, ...] | None = None
        self._camera_error: str | None = None
        self._calibration: CalibrationMonitor | None = None
        self._uncovered_ns: int | None = None  # newest frame processed without its IMU
        self._engine_faults = 0  # unexpected engine exceptions in a row
        self._imu_arrival_ns: int | None = None
        self._imu_frame_id = ""  # of the newest IMU message: the frame of owl/gyro_bias
        self._speeds: collections.deque[tuple[int, float]] = collections.deque(maxlen=SPEED_KEEP)
        #: counts since start (see :class:`~owl_ros.counters.Counters`).
        self.totals = Counters()
        #: frames taken from the queue since start (processed or skipped).
        self.frames_taken = 0
        self._window = _Window()
        self._notes = _Notes()
        self._last_result: FrameResult | None = None

    # ------------------------------------------------------------------ state

    @property
    def engine(self) -> OwlEngine | None:
        """The engine (None until a valid camera_info arrived)."""
        return self._engine

    @property
    def camera(self) -> CameraModel | None:
        """The camera model from the last valid camera_info, or None."""
        return self._camera

    @property
    def gyro(self) -> GyroBuffer:
        """The IMU history (the one buffer every engine of this pipeline uses)."""
        return self._gyro

    @property
    def pending(self) -> int:
        """Frames queued, not yet processed."""
        return len(self._scheduler.queue)

    @property
    def last_skip_reason(self) -> str:
        """Why the newest skipped frame was not processed, or why the newest processed frame
        had no points ("" before either)."""
        return self._notes.empty_reason

    @property
    def calibration_verdict(self) -> MonitorVerdict | None:
        """The live calibration check's latest verdict (None before enough motion)."""
        return self._calibration.last if self._calibration is not None else None

    def deadline_ns(self) -> int | None:
        """When the oldest queued frame stops waiting for IMU (clock time, ns), or None."""
        return self._scheduler.deadline_ns()

    def _rebuild_engine(self) -> None:
        self._jumps.forget_image()
        self._engine_faults = 0  # a new engine: earlier faults say nothing of it
        if self._camera is None:
            self._engine = None
            return
        eng = self.options.engine
        if self.options.calibration_check:  # the check reads the online offset estimate
            eng = replace(eng, observe_time_offset=True)
        # new corners are detected on a helper thread while the engine estimates this
        # frame (the outputs are the same; about 4-10 ms less per VGA frame on 2 cores)
        eng = replace(eng, tracker=replace(eng.tracker, background_detection=True))
        self._engine = OwlEngine(self._camera, eng, gyro=self._gyro)
        self._calibration = self._calibration_monitor()

    def _calibration_monitor(self) -> CalibrationMonitor | None:
        """The live calibration check for the configured extrinsic (None when switched off
        by ``calibration_check`` or before a camera is known)."""
        if not self.options.calibration_check or self._camera is None:
            return None
        eng = self.options.engine
        q = np.asarray(eng.camera_to_imu_rotation_xyzw, dtype=np.float64)
        # its frame-to-frame rotations refer each image to its stamp, which with a rolling
        # shutter sees the middle row's time on average: half a readout after row 0
        offset = eng.imu_time_offset_s + 0.5 * eng.rolling_shutter_readout_s
        return CalibrationMonitor(self._camera, quat_xyzw_to_matrix(q / np.linalg.norm(q)), offset)

    def reconfigure(self, options: NodeOptions) -> None:
        """New options (already validated); a change of engine options rebuilds the engine
        (tracks reset, IMU history kept)."""
        old = self.options
        self.options = options
        self._jumps.tolerance_ns = round(options.engine.max_frame_gap_s * 1e9)
        if options.engine != old.engine or options.calibration_check != old.calibration_check:
            self._rebuild_engine()
            self.totals.reconfigured += 1
        self._scheduler.configure(options.queue_size, options.imu_wait_s)

    def _time_jump(self, jump: Jump) -> None:
        """Backwards time jump: reset everything that holds time."""
        self._notes.jump = jump.what
        self.totals.time_jumps += 1
        self._jumps.reset()
        self._speeds.clear()
        if self._engine is not None:
            self._engine.reset()  # the gyro buffer too
        self._gyro.reset()
        self._uncovered_ns = None
        if self._calibration is not None:
            self._calibration.reset()

    def _before_jump(self, jump: Jump) -> list[Output]:
        """The IMU jumped back: queued frames stamped after ``jump.before_ns`` are from
        before the jump, and all their IMU arrived before it. Process them now, while the
        engine still has that timeline."""

        def old(frame: Frame) -> bool:
            return (frame.stamp_ns if frame.stamp_ns is not None else 0) > jump.before_ns

        outs = []
        for frame in self._scheduler.queue.take_where(old):
            self.frames_taken += 1
            out = self._handle(frame, self._probe(frame))
            if out is not None:
                outs.append(out)
        return outs

    def count_backlog_dropped(self, count: int) -> None:
        """``count`` more input messages were dropped from the node's full backlog."""
        self.totals.backlog_dropped += int(count)

    def note_qos_event(self, text: str) -> None:
        """Record a QoS problem (e.g. an incompatible publisher/subscriber) for diagnostics."""
        self.totals.qos_events += 1
        self._notes.qos_events.append(text)
        del self._notes.qos_events[:-5]

    # ------------------------------------------------------------------ inputs

    def add(self, role: Role, msg: Any, arrival_ns: int) -> list[Output]:
        """One input message of ``role``; returns the outputs of frames it made ready out
        of turn (those queued before a backwards IMU time jump), else []."""
        if role is Role.IMU:
            return self.add_imus([msg], arrival_ns)
        if role is Role.IMAGE:
            self.add_image(msg, arrival_ns)
        elif role is Role.CAMERA_INFO:
            self.add_camera_info(msg)
        else:
            self.add_speed(msg)
        return []

    def add_camera_info(self, msg: Any) -> None:
        """A sensor_msgs/CameraInfo (converted once per distinct calibration)."""
        self.totals.camera_info += 1
        key = _camera_key(msg)
        if key == self._camera_key:
            return
        self._camera_key = key
        try:
            model = camera_info_to_model(msg, rectified=self.options.rectified)
        except (ValueError, OwlError) as err:
            self._camera_error = str(err)
            self.totals.bad_camera_info += 1
            self._camera = None
            self._engine = None
            return
        self._camera_error = None
        if model != self._camera:
            if self._camera is not None:
                self.totals.camera_changed += 1
            self._camera = model
            self._rebuild_engine()

    def add_imus(self, msgs: Sequence[Any], arrival_ns: int) -> list[Output]:
        """sensor_msgs/Imu messages (REP 145; only angular_velocity is used) in arrival
        order, handed to the gyro buffer in one batch.

        Returns:
            The outputs of the frames queued from before a backwards time jump among the
            samples (processed before the reset), else [].
        """
        if not msgs:
            return []
        self._imu_arrival_ns = arrival_ns
        self._imu_frame_id = str(msgs[-1].header.frame_id)
        try:
            samples = imus_to_gyro(msgs)
        except ValueError as err:
            if len(msgs) > 1:  # find the bad one(s); keep the others
                return [out for msg in msgs for out in self.add_imus([msg], arrival_ns)]
            self.totals.imu += 1
            self.totals.imu_invalid += 1
            self._notes.imu_problem = str(err)
            return []
        self.totals.imu += len(msgs)
        stamps, rates = samples.stamp_ns, samples.angular_velocity
        outs: list[Output] = []
        for run in self._jumps.imu_runs(stamps, np.all(np.isfinite(rates), axis=1)):
            if run.jump is not None:
                outs += self._before_jump(run.jump)
                self._time_jump(run.jump)
            part = slice(run.start, run.stop)
            self._take_gyro(GyroSamples(stamps[part], rates[part]))
        return outs

    def add_imu(self, msg: Any, arrival_ns: int) -> list[Output]:
        """One sensor_msgs/Imu (see :meth:`add_imus`)."""
        return self.add_imus([msg], arrival_ns)

    def _take_gyro(self, samples: GyroSamples) -> None:
        intake = self._gyro.intake(samples, max_gap_ns=self.options.imu_max_gap_s * 1e9)
        t = self.totals
        t.imu_non_finite += intake.non_finite
        t.imu_duplicate += intake.duplicate
        t.imu_out_of_order += intake.out_of_order
        t.imu_gaps += intake.gaps
        if intake.problem is not None:
            self._notes.imu_problem = imu_problem_text(intake.problem)
        late = self._uncovered_ns
        if late is not None and self._gyro.covers(late, late):
            t.frames_imu_late += 1  # its IMU came, after the frame had been processed
            self._uncovered_ns = None

    def add_speed(self, msg: Any) -> None:
        """A nav_msgs/Odometry or geometry_msgs/TwistStamped (speed = |linear velocity|)."""
        self.totals.speed += 1
        try:
            stamp, speed = _speed_of(msg)
        except ValueError:
            self.totals.speed_invalid += 1
            return
        if not math.isfinite(speed):
            self.totals.speed_invalid += 1
            return
        self._speeds.append((stamp, speed))

    def add_image(self, msg: Any, arrival_ns: int) -> None:
        """A sensor_msgs/Image or CompressedImage; queued (newest wins when full).
        Thread-safe: the only method that may be called from another thread."""
        self._scheduler.put(msg, arrival_ns)

    # ------------------------------------------------------------------ processing

    def _count_queue(self) -> None:
        received, dropped = self._scheduler.queue.counts()
        self.totals.images += received
        self.totals.dropped_queue_full += dropped
        self.totals.images_missing += self._scheduler.queue.missing()

    def _probe(self, frame: Frame) -> Probe:
        """What the readiness rule needs to know about ``frame``'s inputs."""
        engine = self._engine
        if engine is None:
            return Probe(engine=False, camera_failed=self._camera_error is not None)
        if frame.stamp_ns is None:
            return Probe(engine=True)
        newest = self._jumps.newest_imu_ns
        arrived = self._imu_arrival_ns
        return Probe(
            engine=True,
            covered=engine.covers(frame.stamp_ns),
            # a rolling shutter's last row is seen a readout after the stamp
            passed=newest is not None
            and newest - self._gyro.imu_time_offset_ns > frame.stamp_ns + engine.readout_ns,
            imu_live=arrived is not None and self.clock() - arrived < IMU_SILENT_NS,
        )

    def poll(self, flush: bool = False, limit: int | None = None) -> list[Output]:
        """Process the queued frames that are ready (see :mod:`owl_ros.scheduler`).

        Args:
            flush: process every queued frame now (end of a bag, shutdown).
            limit: take at most this many frames from the queue (processed or skipped);
                None: all that are ready.

        Returns:
            One Output per processed frame, in order.
        """
        self._count_queue()
        if self._window.start_ns is None:
            self._window.start_ns = self.clock()
        outs = []
        taken = 0
        while limit is None or taken < limit:
            got = self._scheduler.take(self._probe, flush)
            if got is None:
                break
            taken += 1
            self.frames_taken += 1
            out = self._handle(*got)
            if out is not None:
                outs.append(out)
        return outs

    def _handle(self, frame: Frame, probe: Probe) -> Output | None:
        """A frame taken from the queue: skipped with its reason, or processed."""
        if not probe.engine:
            error = self._camera_error
            why = f"no valid camera_info: {error}" if error is not None else None
            self._skip(Skip.NO_CAMERA_INFO, why or "no camera_info received yet")
            return None
        if frame.stamp_ns is None:
            self._skip(Skip.BAD_IMAGE, f"image header: {frame.stamp_error}")
            return None
        return self._process(frame, frame.stamp_ns, probe.covered)

    def record_worker_error(self, text: str) -> None:
        """An exception the node's worker survived outside the engine (``text``: where,
        its type and message): counted, and said in ``owl: processing``."""
        self.totals.worker_errors += 1
        self._notes.worker_error = text

    def _skip(self, skip: Skip, reason: str) -> None:
        self.totals.count_skip(skip)
        self._notes.empty_reason = reason
        if skip is Skip.BAD_IMAGE:
            self._notes.bad_image = reason

    def _speed_for(self, stamp: int) -> float | None:
        if self.options.speed_source == "none" or not self._speeds:
            return None
        best = min(self._speeds, key=lambda s: abs(s[0] - stamp))
        if abs(best[0] - stamp) > self.options.speed_max_age_s * 1e9:
            self.totals.speed_stale += 1
            return None
        if best[1] < self.options.min_speed or best[1] <= 0:
            self.totals.speed_too_low += 1
            return None
        return best[1]

    def _to_frame(self, msg: Any, camera: CameraModel) -> ImageFrame | None:
        """The engine's input from an image message, or None (skipped: bad image)."""
        bits = self.options.significant_bits
        self._notes.image_bytes = len(getattr(msg, "data", b""))
        try:
            if hasattr(msg, "format"):
                frame = compressed_to_frame(msg, bits)
            else:
                frame = image_to_frame(msg, bits)
        except (ValueError, OwlError) as err:
            self._skip(Skip.BAD_IMAGE, str(err))
            return None
        h, w = frame.image.shape
        if (w, h) != (camera.width, camera.height):
            self._skip(
                Skip.BAD_IMAGE,
                f"image size {w}x{h} (image.width x image.height) differs from camera_info "
                f"{camera.width}x{camera.height}",
            )
            return None
        return frame

    def _run_engine(self, engine: OwlEngine, image: ImageFrame) -> FrameResult | None:
        try:
            result = engine.process(image)
        except OwlError as err:
            self._skip(Skip.ENGINE_ERROR, f"engine: {err}")
            return None
        except Exception as err:  # never let one frame stop the node; say what happened
            # A fault in one frame's processing: its tracks and heading are suspect, the
            # IMU history and the bias estimate (seconds to converge) are not, so they are
            # kept. A second fault in a row resets everything: whatever keeps failing may
            # live in the state kept.
            self._engine_faults += 1
            again = self._engine_faults > 1
            what = "engine reset with its IMU history" if again else "tracks reset"
            self._skip(Skip.ENGINE_ERROR, f"engine: {type(err).__name__}: {err} ({what})")
            self._jumps.forget_image()
            engine.reset(keep_gyro=not again)
            if again:
                self._engine_faults = 0
            return None
        self._engine_faults = 0
        return result

    def _process(self, frame: Frame, stamp: int, covered: bool) -> Output | None:
        engine = self._engine
        camera = self._camera
        if engine is None or camera is None:
            return None
        image = self._to_frame(frame.msg, camera)
        if image is None:
            return None
        order = self._jumps.check_image(stamp)
        if order is ImageStamp.DUPLICATE:
            self._skip(Skip.DUPLICATE_STAMP, f"image stamp {stamp} ns repeated")
            return None
        if order is ImageStamp.OUT_OF_ORDER:
            last = self._jumps.last_image_ns or stamp
            self._skip(
                Skip.OUT_OF_ORDER,
                f"image stamp {stamp} ns is {(last - stamp) * 1e-6:.1f} ms before the last "
                "processed frame's (out of order; a jump back beyond max_frame_gap_s resets)",
            )
            return None
        if order is ImageStamp.BACKWARDS:
            self._time_jump(self._jumps.image_jump(stamp))
            covered = engine.covers(stamp)
        result = self._run_engine(engine, image)
        if result is None:
            return None
        self._jumps.image_processed(stamp)
        self._last_result = result
        if self._calibration is not None:  # images vs gyro (owl_core.calib_check)
            online = engine.online_calibration
            if online is not None:  # the monitor refers each image to its middle row
                online = replace(online, offset_s=online.offset_s + 0.5e-9 * engine.readout_ns)
            self._calibration.update(
                engine.last_tracks,
                GyroSamples(self._gyro.stamps_ns, self._gyro.rates_imu),
                engine.gyro_bias,
                online,
            )
        if not covered:
            self.totals.frames_imu_not_covered += 1
            self._uncovered_ns = stamp  # counted late if the IMU reaches it afterwards
        return self._output(frame, stamp, image.image, result)

    def _output(
        self, frame: Frame, stamp: int, grey: npt.NDArray[np.uint8], result: FrameResult
    ) -> Output:
        """The messages of one processed frame (and its counts)."""
        t = self.totals
        t.processed += 1
        self._window.process_s.append(result.timings.get("total", math.nan))
        self._window.points.append(result.num_points)
        speed = self._speed_for(stamp)
        header = frame.msg.header
        cloud = frame_result_to_cloud(result, header, speed=speed)
        heading = cov = bias = None
        if result.heading is not None:
            heading = heading_to_msg(result.heading, header)
            t.headings += 1
            if np.isfinite(result.heading_sigma_rad):
                cov = heading_to_twist_covariance(result.heading, result.heading_sigma_rad, header)
        if result.num_points:
            t.frames_with_points += 1
            t.frames_metric += int(speed is not None)
        else:
            self._notes.empty_reason = "; ".join(result.reasons) or "no points"
        if np.isfinite(result.gyro_bias).all():
            bias = gyro_bias_to_msg(result.gyro_bias, make_header(stamp, self._imu_frame_id))
        return Output(result, cloud, heading, grey, header, speed, frame.arrival_ns, cov, bias)

    def record_latency(self, latency_s: float, stamp_latency_s: float | None = None) -> None:
        """Record one frame's arrival -> publication latency (and image stamp ->
        publication on the ROS clock), seconds, for diagnostics."""
        self._window.latency_s.append(float(latency_s))
        if stamp_latency_s is not None:
            self._window.stamp_latency_s.append(float(stamp_latency_s))

    def record_cycle(self, cycle_s: float) -> None:
        """Record the worker's time for one frame, seconds: taken from the queue to its
        outputs published (conversion, engine, messages, publishing)."""
        self._window.cycle_s.append(float(cycle_s))

    # ------------------------------------------------------------------ diagnostics

    def diagnostics(
        self, wrong_type: Sequence[str] = (), reset_window: bool = True
    ) -> list[StatusRecord]:
        """Status records for /diagnostics over the window since the last call (which the
        clock's time now closes).

        Three statuses: ``owl: input`` (rates, drops, bad input, QoS, publishers of the
        wrong type), ``owl: processing`` (frames, points, timing, latency, reason for empty
        output, time jumps) and ``owl: gyro`` (bias estimate, IMU coverage).

        Args:
            wrong_type: one text per publisher on an input topic whose message type is not
                the subscribed one (the node finds them in the ROS graph).
            reset_window: start a new rate window.
        """
        now_ns = self.clock()
        self._count_queue()
        win, notes = self._window, self._notes
        engine = self._engine
        result = self._last_result
        snapshot = StatusInputs(
            span_s=(now_ns - win.start_ns) * 1e-9 if win.start_ns is not None else math.nan,
            counts=self.totals.since(win.base),
            totals=self.totals.copy(),
            points=win.points,
            process_s=win.process_s,
            cycle_s=win.cycle_s,
            latency_s=win.latency_s,
            stamp_latency_s=win.stamp_latency_s,
            camera_known=self._camera is not None,
            camera_error=self._camera_error,
            wrong_type=tuple(wrong_type),
            last_bad_image=notes.bad_image,
            last_imu_problem=notes.imu_problem,
            last_empty_reason=notes.empty_reason,
            last_jump=notes.jump,
            last_worker_error=notes.worker_error,
            qos_events=tuple(notes.qos_events),
            image_bytes=notes.image_bytes,
            heading_sigma_rad=result.heading_sigma_rad if result is not None else math.nan,
            gyro_bias=engine.gyro_bias if engine is not None else np.zeros(3),
            gyro_bias_sigma=engine.gyro_bias_sigma if engine is not None else np.full(3, math.nan),
            queue_size=self.options.queue_size,
            require_gyro=self.options.engine.require_gyro,
            calibration=self.calibration_verdict,
            imu_time_offset_s=engine.imu_time_offset_s if engine is not None else math.nan,
            imu_time_offset_sigma_s=(
                engine.imu_time_offset_sigma_s if engine is not None else math.nan
            ),
            dense_max_rate_hz=self.options.dense_max_rate_hz if self.options.dense else None,
        )
        records = build_status(snapshot)
        if reset_window:
            self._window = _Window(start_ns=now_ns, base=self.totals.copy())
        return records

    def start_window(self) -> None:
        """Start the first diagnostics window now (the clock's time)."""
        self._window.start_ns = self.clock()
