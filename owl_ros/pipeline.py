"""The message -> engine -> message path shared by node ``owl`` and ``owl_process``.

No DDS here: the caller hands in ROS messages (rclpy classes) with the time they arrived
on its own clock (the node: monotonic wall time; ``owl_process``: the bag's log time), and
gets back what to publish. Everything that touches the engine runs in one thread (the
node's worker); :class:`Inbox` is the thread-safe hand-over from the subscription
callbacks, which never block.

What :class:`Pipeline` does per input:

- ``camera_info``: converted once per distinct calibration; an invalid one (zero focal
  length, unknown distortion model) is reported and frames are skipped until a valid one
  arrives; a changed calibration rebuilds the engine.
- ``imu``: samples with NaN/inf rates, duplicate or out-of-order stamps are dropped and
  counted; a gap longer than ``imu_max_gap_s`` is never interpolated across (frames whose
  interval spans it count as not covered); a stamp more than ``max_frame_gap_s`` older
  than the newest one is a backwards time jump (bag loop, sim clock restart): frames
  queued from before it are processed first, then the engine is reset and a diagnostic
  says so. A ring buffer of the last seconds of good samples re-feeds a rebuilt engine.
- ``image`` / ``image/compressed``: queued (at most ``queue_size``; when full the oldest
  is dropped and counted: the newest frame wins). A queued frame is processed once the IMU
  covers the interval since the previous frame, or after ``imu_wait_s`` (then the engine
  flags or skips it, per ``require_gyro``), or at once when the IMU already passed its
  stamp with a gap, has gone silent, or the next frame filled the queue. A bad image
  (unknown encoding, step too small, wrong data length, size differing from camera_info)
  is skipped with a reason naming the field and value; a stamp going backwards resets the engine.
- speed (``nav_msgs/Odometry`` or ``geometry_msgs/TwistStamped``): the speed nearest the
  image stamp (within ``speed_max_age_s``, at least ``min_speed``) scales x y z to metres
  and the cloud's ``speed`` field says so (``msg_adapters.pointcloud``).

Every processed frame gives one ``owl/points`` cloud (empty when the frame produced no
points; the reason is in diagnostics) with the input image's header, and an
``owl/heading`` when the frame gave a heading.
"""

from __future__ import annotations

import collections
import heapq
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
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
from owl_core.types import FrameResult, GyroSamples, PointFlag
from owl_ros.debug_legend import draw_legend
from owl_ros.params import NodeOptions
from owl_ros.status import StatusInputs, build_status

__all__ = ["Inbox", "Output", "Pipeline", "draw_debug"]

#: IMU considered silent (no waiting for it) when nothing arrived for this long, ns.
IMU_SILENT_NS = 1_000_000_000
#: seconds of good IMU samples kept to re-feed a rebuilt engine.
IMU_RING_S = 2.0
#: speed messages kept.
SPEED_KEEP = 400
#: name prefix of the diagnostic statuses.


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
    heading_cov: Any | None = None  # TwistWithCovarianceStamped (owl/heading_with_covariance)
    gyro_bias: Any = None  # Vector3Stamped (owl/gyro_bias)


@dataclass
class _Pending:
    msg: Any
    arrival_ns: int


@dataclass
class _Window:
    """Counts and samples since the last diagnostics report."""

    start_ns: int | None = None
    counts: collections.Counter[str] = field(default_factory=collections.Counter)
    process_s: list[float] = field(default_factory=list)
    latency_s: list[float] = field(default_factory=list)
    cycle_s: list[float] = field(default_factory=list)
    stamp_latency_s: list[float] = field(default_factory=list)
    points: list[int] = field(default_factory=list)


class Inbox:
    """Thread-safe hand-over from subscription callbacks to the worker (never blocks long).

    Images are kept in a bounded deque (``image_capacity``; the oldest is dropped when
    full and counted in ``dropped_images``); IMU, camera_info and speed messages in deques
    bounded generously (``other_capacity``) so memory stays bounded even if the worker
    stalls. ``drain`` hands everything over in the order it was put, across kinds: a
    backwards time jump is then seen after the images taken before it, not before them.
    ``wait`` lets the worker sleep until something arrives.
    """

    def __init__(self, image_capacity: int, other_capacity: int = 20000) -> None:
        self._lock = threading.Lock()
        self._event = threading.Event()
        self._seq = 0  # put order across both deques
        self._images: collections.deque[tuple[int, str, Any, int]] = collections.deque(
            maxlen=image_capacity
        )
        self._other: collections.deque[tuple[int, str, Any, int]] = collections.deque(
            maxlen=other_capacity
        )
        self.dropped_images = 0
        self.dropped_other = 0

    def put_image(self, msg: Any, arrival_ns: int) -> None:
        """Store an image (newest wins when full)."""
        with self._lock:
            if len(self._images) == self._images.maxlen:
                self.dropped_images += 1
            self._seq += 1
            self._images.append((self._seq, "image", msg, arrival_ns))
        self._event.set()

    def put(self, kind: str, msg: Any, arrival_ns: int) -> None:
        """Store a non-image message: kind is "imu", "camera_info", "speed", "options" or
        "qos"."""
        with self._lock:
            if len(self._other) == self._other.maxlen:
                self.dropped_other += 1
            self._seq += 1
            self._other.append((self._seq, kind, msg, arrival_ns))
        self._event.set()

    def wait(self, timeout_s: float) -> None:
        """Sleep until something is put or ``timeout_s`` passes."""
        self._event.wait(timeout_s)
        self._event.clear()

    def wake(self) -> None:
        """Wake a waiting worker (e.g. to stop it)."""
        self._event.set()

    def drain(self) -> tuple[list[tuple[str, Any, int]], int]:
        """((kind, message, arrival ns) in put order, images being kind "image"; images
        dropped since the last drain)."""
        with self._lock:
            other = list(self._other)
            images = list(self._images)
            self._other.clear()
            self._images.clear()
            dropped, self.dropped_images = self.dropped_images, 0
        merged = heapq.merge(other, images)  # both are in put order; seq is unique
        return [(kind, msg, arrival) for _, kind, msg, arrival in merged], dropped


def _speed_of(msg: Any) -> tuple[int, float]:
    """(stamp ns, |linear velocity| m/s) of a nav_msgs/Odometry or TwistStamped."""
    twist = msg.twist.twist if hasattr(msg, "pose") else msg.twist
    v = twist.linear
    return header_to_ns(msg.header), math.sqrt(v.x * v.x + v.y * v.y + v.z * v.z)


class Pipeline:
    """Messages in, FrameResults and output messages out (see the module docstring).

    Args:
        options: node options (engine options included).
    """

    def __init__(self, options: NodeOptions | None = None) -> None:
        self.options = options if options is not None else NodeOptions()
        self._engine: OwlEngine | None = None
        self._camera: CameraModel | None = None
        self._camera_key: tuple[Any, ...] | None = None
        self._camera_error: str | None = None
        self._pending: collections.deque[_Pending] = collections.deque()
        self._ready: list[Output] = []  # processed outside poll (before a time jump)
        self._ring: collections.deque[tuple[int, tuple[float, float, float]]] = collections.deque()
        self._newest_imu_ns: int | None = None
        self._imu_arrival_ns: int | None = None
        self._imu_frame_id = ""  # of the newest IMU message: the frame of owl/gyro_bias
        self._last_stamp: int | None = None
        self._speeds: collections.deque[tuple[int, float]] = collections.deque(maxlen=SPEED_KEEP)
        #: totals since start, by key (see diagnostics()).
        self.totals: collections.Counter[str] = collections.Counter()
        self._window = _Window()
        self._last_empty_reason = ""
        self._last_bad_image = ""
        self._last_imu_problem = ""
        self._last_jump = ""
        self._qos_events: list[str] = []
        self._last_result: FrameResult | None = None
        self._calibration: CalibrationMonitor | None = None

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
    def pending(self) -> int:
        """Frames waiting for processing."""
        return len(self._pending)

    def _count(self, key: str, n: int = 1) -> None:
        self.totals[key] += n
        self._window.counts[key] += n

    def _rebuild_engine(self) -> None:
        if self._camera is None:
            self._engine = None
            return
        self._engine = OwlEngine(self._camera, self.options.engine)
        self._calibration = self._calibration_monitor()
        if self._ring:
            stamps = np.fromiter((s for s, _ in self._ring), dtype=np.int64, count=len(self._ring))
            rates = np.array([w for _, w in self._ring], dtype=np.float64).reshape(-1, 3)
            self._engine.add_gyro(GyroSamples(stamp_ns=stamps, angular_velocity=rates))
        self._last_stamp = None

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
        if options.engine != old.engine:
            self._rebuild_engine()
            self._count("reconfigured")
        elif options.calibration_check != old.calibration_check:
            self._calibration = self._calibration_monitor()
        while len(self._pending) > options.queue_size:
            self._pending.popleft()
            self._count("dropped_queue_full")

    def _time_jump(self, what: str) -> None:
        """Backwards time jump: reset everything that holds time."""
        self._last_jump = what
        self._count("time_jumps")
        self._ring.clear()
        self._newest_imu_ns = None
        self._last_stamp = None
        self._speeds.clear()
        if self._engine is not None:
            self._engine.reset()
        if self._calibration is not None:
            self._calibration.reset()

    def _process_before_jump(self, after_ns: int, now_ns: int) -> None:
        """The IMU jumped back: queued frames stamped after ``after_ns`` are from before the
        jump, and all their IMU arrived before it. Process them now, while the engine still
        has that timeline; their outputs wait in ``_ready`` for the next :meth:`poll`."""
        old: collections.deque[_Pending] = collections.deque()
        rest: collections.deque[_Pending] = collections.deque()
        for p in self._pending:
            (old if self._stamp_or_zero(p.msg) > after_ns else rest).append(p)
        if not old:
            return
        self._pending = old
        self._ready = self.poll(now_ns, flush=True)  # (with what was ready already)
        self._pending = rest

    def note_qos_event(self, text: str) -> None:
        """Record a QoS problem (e.g. an incompatible publisher/subscriber) for diagnostics."""
        self._count("qos_events")
        self._qos_events.append(text)
        del self._qos_events[:-5]

    # ------------------------------------------------------------------ inputs

    def add_camera_info(self, msg: Any) -> None:
        """A sensor_msgs/CameraInfo (converted once per distinct calibration)."""
        self._count("camera_info")
        key = (
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
        if key == self._camera_key:
            return
        self._camera_key = key
        try:
            model = camera_info_to_model(msg, rectified=self.options.rectified)
        except (ValueError, OwlError) as err:
            self._camera_error = str(err)
            self._count("bad_camera_info")
            self._camera = None
            self._engine = None
            return
        self._camera_error = None
        if model != self._camera:
            if self._camera is not None:
                self._count("camera_changed")
            self._camera = model
            self._rebuild_engine()

    def add_imu(self, msg: Any, arrival_ns: int) -> None:
        """A sensor_msgs/Imu (REP 145; only angular_velocity is used)."""
        self.add_imus([msg], arrival_ns)

    def add_imus(self, msgs: Sequence[Any], arrival_ns: int) -> None:
        """sensor_msgs/Imu messages in arrival order, handed to the engine in one batch."""
        if not msgs:
            return
        self._imu_arrival_ns = arrival_ns
        self._imu_frame_id = str(msgs[-1].header.frame_id)
        try:
            samples = imus_to_gyro(msgs)
        except ValueError as err:
            if len(msgs) > 1:  # find the bad one(s); keep the others
                for msg in msgs:
                    self.add_imus([msg], arrival_ns)
                return
            self._count("imu")
            self._count("imu_invalid")
            self._last_imu_problem = str(err)
            return
        self._count("imu", len(msgs))
        stamps = samples.stamp_ns
        rates = samples.angular_velocity
        finite = np.all(np.isfinite(rates), axis=1)
        keep: list[int] = []
        for i in range(stamps.shape[0]):
            stamp = int(stamps[i])
            if not finite[i]:
                self._count("imu_non_finite")
                self._last_imu_problem = f"imu.angular_velocity not finite: {rates[i].tolist()}"
                continue
            newest = self._newest_imu_ns
            if newest is not None and stamp <= newest:
                jump_ns = round(self.options.engine.max_frame_gap_s * 1e9)
                if stamp >= newest - jump_ns:
                    key = "imu_duplicate" if stamp == newest else "imu_out_of_order"
                    self._count(key)
                    self._last_imu_problem = (
                        f"imu stamp {stamp} ns not after {newest} ns ({key[4:]})"
                    )
                    continue
                self._feed(stamps, rates, keep)
                self._process_before_jump(stamp + jump_ns, arrival_ns)
                self._time_jump(
                    f"IMU stamp went back {(newest - stamp) * 1e-9:.3f} s ({stamp} ns after "
                    f"{newest} ns): engine reset"
                )
            elif newest is not None and stamp - newest > self.options.imu_max_gap_s * 1e9:
                # never interpolate across a gap: frames spanning it are not covered
                self._feed(stamps, rates, keep)
                self._count("imu_gaps")
                self._last_imu_problem = (
                    f"IMU gap of {(stamp - newest) * 1e-6:.1f} ms before {stamp} ns "
                    "(> imu_max_gap_s)"
                )
                self._ring.clear()
                if self._engine is not None:
                    self._engine.gyro.reset()
            self._newest_imu_ns = stamp
            keep.append(i)
        self._feed(stamps, rates, keep)

    def _feed(
        self, stamps: npt.NDArray[np.int64], rates: npt.NDArray[np.float64], keep: list[int]
    ) -> None:
        """Accepted samples ``keep`` (indices, cleared here) -> ring buffer and engine."""
        if not keep:
            return
        idx = np.asarray(keep, dtype=np.int64)
        keep.clear()
        good_t, good_w = stamps[idx], rates[idx]
        self._ring.extend(zip(good_t.tolist(), map(tuple, good_w.tolist()), strict=True))
        horizon = int(good_t[-1]) - round(IMU_RING_S * 1e9)
        while self._ring and self._ring[0][0] < horizon:
            self._ring.popleft()
        if self._engine is not None:
            self._engine.add_gyro(GyroSamples(stamp_ns=good_t, angular_velocity=good_w))

    def add_speed(self, msg: Any) -> None:
        """A nav_msgs/Odometry or geometry_msgs/TwistStamped (speed = |linear velocity|)."""
        self._count("speed")
        try:
            stamp, speed = _speed_of(msg)
        except ValueError:
            self._count("speed_invalid")
            return
        if not math.isfinite(speed):
            self._count("speed_invalid")
            return
        self._speeds.append((stamp, speed))

    def add_image(self, msg: Any, arrival_ns: int) -> None:
        """A sensor_msgs/Image or CompressedImage; queued (newest wins when full)."""
        self._count("images")
        if len(self._pending) >= self.options.queue_size:
            self._pending.popleft()
            self._count("dropped_queue_full")
        self._pending.append(_Pending(msg, arrival_ns))

    def add_events(self, events: Sequence[tuple[str, Any, int]]) -> None:
        """Messages in arrival order, as ``(kind, message, arrival ns)`` with kind "image",
        "imu", "camera_info", "speed", "options" (NodeOptions) or "qos" (text); runs of IMU
        messages go to the engine in one batch."""
        imus: list[Any] = []
        for i, (kind, msg, arrival_ns) in enumerate(events):
            if kind == "imu":
                imus.append(msg)
                if i + 1 < len(events) and events[i + 1][0] == "imu":
                    continue
                self.add_imus(imus, arrival_ns)
                imus = []
            elif kind == "image":
                self.add_image(msg, arrival_ns)
            elif kind == "camera_info":
                self.add_camera_info(msg)
            elif kind == "speed":
                self.add_speed(msg)
            elif kind == "options":
                self.reconfigure(msg)
            elif kind == "qos":
                self.note_qos_event(msg)
            else:
                raise ValueError(f"unknown inbox message kind {kind!r}")

    def count_dropped(self, n: int) -> None:
        """Images dropped before they reached the pipeline (the node's inbox was full)."""
        if n:
            self.totals["images"] += n
            self._window.counts["images"] += n
            self._count("dropped_queue_full", n)

    # ------------------------------------------------------------------ processing

    def _imu_live(self, now_ns: int) -> bool:
        return self._imu_arrival_ns is not None and now_ns - self._imu_arrival_ns < IMU_SILENT_NS

    @property
    def pending_count(self) -> int:
        """Frames queued, not yet processed."""
        return len(self._pending)

    def poll(self, now_ns: int, flush: bool = False, limit: int | None = None) -> list[Output]:
        """Process the queued frames that are ready (see the module docstring).

        Args:
            now_ns: the caller's current time, on the clock of ``arrival_ns``, ns.
            flush: process every queued frame now (end of a bag, shutdown).
            limit: take at most this many frames from the queue (processed or skipped);
                None: all that are ready.

        Returns:
            One Output per processed frame, in order (first any processed before a time
            jump since the last call).
        """
        outs, self._ready = self._ready, []
        if self._window.start_ns is None:
            self._window.start_ns = now_ns
        wait_ns = round(self.options.imu_wait_s * 1e9)
        taken = 0
        while self._pending and (limit is None or taken < limit):
            item = self._pending[0]
            engine = self._engine
            if engine is None:
                if not flush and self._camera_error is None and now_ns - item.arrival_ns < wait_ns:
                    break  # camera_info may be just behind its image
                self._pending.popleft()
                taken += 1
                if self._camera_error is not None:
                    self._skip("no_camera_info", f"no valid camera_info: {self._camera_error}")
                else:
                    self._skip("no_camera_info", "no camera_info received yet")
                continue
            stamp = self._stamp_of(item.msg)
            if stamp is None:
                self._pending.popleft()
                taken += 1
                continue
            covered = engine.covers(stamp)
            if not covered and not flush:
                offset = engine.gyro.imu_time_offset_ns
                last_row = stamp + engine.readout_ns  # a rolling shutter's last row
                passed = (
                    self._newest_imu_ns is not None and self._newest_imu_ns - offset > last_row
                )
                waiting = now_ns - item.arrival_ns < wait_ns
                # a full queue ends the wait (the next frame is there already)
                full = len(self._pending) >= self.options.queue_size > 1
                if waiting and not passed and not full and self._imu_live(now_ns):
                    break
            self._pending.popleft()
            taken += 1
            out = self._process(item, stamp, covered)
            if out is not None:
                outs.append(out)
        return outs

    def next_deadline_ns(self) -> int | None:
        """When the oldest queued frame stops waiting for IMU (caller's clock), or None."""
        if not self._pending:
            return None
        return self._pending[0].arrival_ns + round(self.options.imu_wait_s * 1e9)

    def _skip(self, key: str, reason: str) -> None:
        self._count("skipped_" + key)
        self._last_empty_reason = reason
        if key == "bad_image":
            self._last_bad_image = reason

    @staticmethod
    def _stamp_or_zero(msg: Any) -> int:
        try:
            return header_to_ns(msg.header)
        except ValueError:
            return 0

    def _stamp_of(self, msg: Any) -> int | None:
        try:
            return header_to_ns(msg.header)
        except ValueError as err:
            self._skip("bad_image", f"image header: {err}")
            return None

    def _speed_for(self, stamp: int) -> float | None:
        if self.options.speed_source == "none" or not self._speeds:
            return None
        best = min(self._speeds, key=lambda s: abs(s[0] - stamp))
        if abs(best[0] - stamp) > self.options.speed_max_age_s * 1e9:
            self._count("speed_stale")
            return None
        if best[1] < self.options.min_speed or best[1] <= 0:
            self._count("speed_too_low")
            return None
        return best[1]

    def _process(self, item: _Pending, stamp: int, covered: bool) -> Output | None:
        engine = self._engine
        camera = self._camera
        if engine is None or camera is None:
            return None
        msg = item.msg
        bits = self.options.significant_bits
        try:
            if hasattr(msg, "format"):
                frame = compressed_to_frame(msg, bits)
            else:
                frame = image_to_frame(msg, bits)
        except (ValueError, OwlError) as err:
            self._skip("bad_image", str(err))
            return None
        h, w = frame.image.shape
        if (w, h) != (camera.width, camera.height):
            self._skip(
                "bad_image",
                f"image size {w}x{h} (image.width x image.height) differs from camera_info "
                f"{camera.width}x{camera.height}",
            )
            return None
        if self._last_stamp is not None and stamp <= self._last_stamp:
            if stamp == self._last_stamp:
                self._skip("duplicate_stamp", f"image stamp {stamp} ns repeated")
                return None
            self._time_jump(
                f"image stamp went back {(self._last_stamp - stamp) * 1e-9:.3f} s ({stamp} ns "
                f"after {self._last_stamp} ns): engine reset"
            )
            covered = engine.covers(stamp)
        try:
            result = engine.process(frame)
        except OwlError as err:
            self._skip("engine_error", f"engine: {err}")
            return None
        except Exception as err:  # never let one frame stop the node; say what happened
            self._skip("engine_error", f"engine: {type(err).__name__}: {err}")
            self._last_stamp = None
            engine.reset()
            return None
        self._last_stamp = stamp
        self._last_result = result
        if self._calibration is not None:  # images vs gyro (owl_core.calib_check)
            gyro = engine.gyro
            self._calibration.update(
                engine.last_tracks,
                GyroSamples(gyro.stamps_ns, gyro.rates_imu),
                engine.gyro_bias,
            )
        if not covered:
            self._count("frames_imu_not_covered")
        self._count("processed")
        self._window.process_s.append(result.timings.get("total", math.nan))
        self._window.points.append(result.num_points)
        speed = self._speed_for(stamp)
        header = msg.header
        cloud = frame_result_to_cloud(result, header, speed=speed)
        heading = None
        if result.heading is not None:
            heading = heading_to_msg(result.heading, header)
            self._count("headings")
        if result.num_points:
            self._count("frames_with_points")
            if speed is not None:
                self._count("frames_metric")
        else:
            self._last_empty_reason = "; ".join(result.reasons) or "no points"
        cov = None
        if heading is not None and np.isfinite(result.heading_sigma_rad):
            cov = heading_to_twist_covariance(result.heading, result.heading_sigma_rad, header)
        bias = None
        if np.isfinite(result.gyro_bias).all():
            bias = gyro_bias_to_msg(result.gyro_bias, make_header(stamp, self._imu_frame_id))
        return Output(
            result, cloud, heading, frame.image, header, speed, item.arrival_ns, cov, bias
        )

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
        self, now_ns: int, wrong_type: Sequence[str] = (), reset_window: bool = True
    ) -> list[StatusRecord]:
        """Status records for /diagnostics over the window since the last call.

        Three statuses: ``owl: input`` (rates, drops, bad input, QoS, publishers of the
        wrong type), ``owl: processing`` (frames, points, timing, latency, reason for empty
        output, time jumps) and ``owl: gyro`` (bias estimate, IMU coverage).

        Args:
            now_ns: monotonic time of the call, ns (closes the rate window).
            wrong_type: one text per publisher on an input topic whose message type is not
                the subscribed one (the node finds them in the ROS graph).
            reset_window: start a new rate window.
        """
        win = self._window
        engine = self._engine
        result = self._last_result
        snapshot = StatusInputs(
            span_s=(now_ns - win.start_ns) * 1e-9 if win.start_ns is not None else math.nan,
            counts=win.counts,
            totals=self.totals,
            points=win.points,
            process_s=win.process_s,
            cycle_s=win.cycle_s,
            latency_s=win.latency_s,
            stamp_latency_s=win.stamp_latency_s,
            camera_known=self._camera is not None,
            camera_error=self._camera_error,
            wrong_type=tuple(wrong_type),
            last_bad_image=self._last_bad_image,
            last_imu_problem=self._last_imu_problem,
            last_empty_reason=self._last_empty_reason,
            last_jump=self._last_jump,
            qos_events=tuple(self._qos_events),
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
        )
        records = build_status(snapshot)
        if reset_window:
            self._window = _Window(start_ns=now_ns)
        return records

    @property
    def calibration_verdict(self) -> MonitorVerdict | None:
        """The live calibration check's latest verdict (None before enough motion)."""
        return self._calibration.last if self._calibration is not None else None

    def start_window(self, now_ns: int) -> None:
        """Start the first diagnostics window at ``now_ns`` (caller's clock)."""
        self._window.start_ns = now_ns


def draw_debug(
    grey: npt.NDArray[np.uint8], result: FrameResult, camera: CameraModel | None
) -> npt.NDArray[np.uint8]:
    """The owl/debug_image picture: (H, W, 3) uint8 BGR.

    Each point is a 5x5 dot coloured by r/|t| (red near, blue far, on a log scale between
    0.5 and 20 s); suspected moving points are magenta with a white centre; the heading
    (focus of expansion) is a green cross in a circle when it lies in front of the camera;
    a colour legend sits in the bottom-left corner (owl_ros.debug_legend). Drawing is
    vectorised (no loop over points).
    """
    img = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    h, w = grey.shape
    n = result.num_points
    if n:
        range_over_speed = np.clip(
            np.asarray(result.range_over_speed, dtype=np.float64), 0.5, 20.0
        )
        level = np.log(range_over_speed / 0.5) / math.log(40.0)  # 0 near .. 1 far
        lut = cv2.applyColorMap(
            np.round(255 * (1.0 - level)).astype(np.uint8).reshape(-1, 1), cv2.COLORMAP_JET
        ).reshape(-1, 3)
        moving = (result.flags & np.uint8(PointFlag.MOVING)) != 0
        lut[moving] = (255, 0, 255)
        uv = np.rint(result.pixels).astype(np.int64)
        offs = np.arange(-2, 3)
        du, dv = np.meshgrid(offs, offs)
        us = np.clip(uv[:, 0, None] + du.reshape(1, -1), 0, w - 1)
        vs = np.clip(uv[:, 1, None] + dv.reshape(1, -1), 0, h - 1)
        img[vs, us] = lut[:, None, :]
        centre_u = np.clip(uv[moving, 0], 0, w - 1)
        centre_v = np.clip(uv[moving, 1], 0, h - 1)
        img[centre_v, centre_u] = (255, 255, 255)
    if result.heading is not None and camera is not None and result.heading[2] > 0:
        foe = camera.bearing_to_pixel(np.asarray(result.heading, dtype=np.float64)[None])[0]
        if np.all(np.isfinite(foe)):
            c = (round(float(foe[0])), round(float(foe[1])))
            size = max(6, min(h, w) // 20)
            cv2.circle(img, c, size, (0, 255, 0), 2)
            cv2.drawMarker(img, c, (0, 255, 0), cv2.MARKER_CROSS, 2 * size, 2)
    return draw_legend(img)  # the colour key, bottom left
