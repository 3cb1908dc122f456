"""Dense OWL outputs of node ``owl`` and ``owl_process`` (parameter ``dense: true``).

The glue between :class:`~owl_ros.pipeline.Pipeline` outputs and
:class:`owl_core.dense.DenseOwl`: after each processed frame, :meth:`DenseStage.begin`
takes the grey image, the gyro rotation since the dense stage's previous image (bias
removed, from the engine's gyro buffer) and the engine's heading; the dense stage measures
them in a child process (``dense_process``, :mod:`owl_ros.dense_worker`, which returns the
published arrays) or in this process (:meth:`DenseStage.finish`, then
:func:`build_messages`), and :func:`arrays_to_messages` turns the arrays into messages
(only the ones asked for):

| topic | type | content |
|---|---|---|
| ``owl/looming`` | sensor_msgs/Image 32FC1 | L, 1/s, NaN where not confident |
| ``owl/range_over_speed`` | sensor_msgs/Image 32FC1 | r/|t|, s, NaN where not confident |
| ``owl/depth/image`` | sensor_msgs/Image 32FC1 | z/|t| (s), z (m) with a known speed |
| ``owl/depth/camera_info`` | sensor_msgs/CameraInfo | the working grid's calibration |
| ``owl/dense_points`` | sensor_msgs/PointCloud2 | confident pixels at a stride |
| ``owl/time_to_contact`` | geometry_msgs/PointStamped | bearing x shortest TTC (s) |

Images are on the working grid (``dense_width`` x ``dense_height``) of the input image,
with the input image's header. ``owl/time_to_contact``: ``point`` is the unit bearing of
the pixel with the shortest time to contact inside the path cone multiplied by that time
in seconds, so ``|point|`` is the time to contact and ``point/|point|`` where it is (the
same direction in the camera optical frame); NaN x y z when nothing inside the cone
approaches with a precise window-averaged L. A PointStamped was chosen because it is the
smallest stamped message that carries both what a planner acts on and where it lies
(sensor_msgs/Range has no direction: its cone is the frame's x axis), and RViz draws it
as is.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters.camera_info import camera_model_to_info
from msg_adapters.diagnostics import Level, StatusRecord
from msg_adapters.image import array_to_image
from msg_adapters.pointcloud import array_to_cloud
from owl_core.camera import CameraModel
from owl_core.dense import DenseOptions, DenseOwl, DenseResult, Readout
from owl_core.engine import OwlEngine
from owl_core.errors import OwlError
from owl_core.os_thread import name_os_thread
from owl_core.rolling_shutter import readout_rotations
from owl_ros.dense_worker import (
    DenseInputs,
    DenseProcess,
    DenseProcessError,
    DenseRequest,
    DenseSummary,
    message_arrays,
    summarize,
)
from owl_ros.params import NodeOptions

__all__ = [
    "TOPICS",
    "DenseJob",
    "DensePublishers",
    "DenseStage",
    "DenseWriter",
    "build_messages",
    "dense_options",
    "working_camera",
]

#: topic (relative name) -> ROS message type name, in publication order.
TOPICS: dict[str, str] = {
    "owl/looming": "sensor_msgs/msg/Image",
    "owl/range_over_speed": "sensor_msgs/msg/Image",
    "owl/depth/image": "sensor_msgs/msg/Image",
    "owl/depth/camera_info": "sensor_msgs/msg/CameraInfo",
    "owl/dense_points": "sensor_msgs/msg/PointCloud2",
    "owl/time_to_contact": "geometry_msgs/msg/PointStamped",
}


#: what ``owl: dense`` adds when the dense process failed
_AGAIN = "; it starts again with the next frame"


def dense_options(options: NodeOptions) -> DenseOptions:
    """The dense stage's settings from the node options."""
    return DenseOptions(
        width=options.dense_width,
        height=options.dense_height,
        preset=options.dense_preset,
        baseline_frames=options.dense_baseline_frames,
        min_confidence=options.dense_min_confidence,
        ttc_cone_deg=options.ttc_cone_deg,
    )


def working_camera(camera: CameraModel, width: int, height: int) -> CameraModel:
    """The camera model of the working grid: K scaled about pixel centres, same lens."""
    sx, sy = width / camera.width, height / camera.height
    k = np.array(camera.K, dtype=np.float64)
    k[0, 0] *= sx
    k[0, 1] *= sx
    k[0, 2] = (k[0, 2] + 0.5) * sx - 0.5
    k[1, 1] *= sy
    k[1, 2] = (k[1, 2] + 0.5) * sy - 0.5
    return CameraModel(width, height, k, np.array(camera.D), camera.distortion_model)


@dataclass
class _Last:
    result: DenseSummary | None = None
    error: str = ""  # why the newest frame gave no result ("" once one did)
    errors: int = 0
    frames: int = 0
    warned: int = 0
    gyro_missing: int = 0
    dropped: int = 0
    # shortest time to contact since the last status: (seconds, pixel (u, v) or None)
    window_min: tuple[float, Any] | None = None


@dataclass(frozen=True)
class DenseJob:
    """One frame's dense work.

    Attributes:
        dense: the dense stage that took the images (it owns the flow instance).
        inputs: what the frame is measured from, read from the engine at hand-over time.
    """

    dense: DenseOwl
    inputs: DenseInputs

    def measure(self) -> DenseResult:
        """Measure the frame in this thread.

        Raises:
            OwlError: malformed rotation or heading (:meth:`DenseOwl.measure`).
        """
        return self.inputs.measure(self.dense)


class DenseStage:
    """Runs :class:`~owl_core.dense.DenseOwl` after the sparse engine, frame by frame.

    :meth:`begin` (in the thread that owns the engine: it reads the gyro buffer) takes the
    image and returns a :class:`DenseJob`; :meth:`finish` measures it, in any thread, and
    keeps the bookkeeping of ``owl: dense`` (under a lock: the status is read elsewhere).

    Args:
        options: node options (the ``dense_*`` and ``ttc_*`` parameters).
    """

    def __init__(self, options: NodeOptions) -> None:
        self.options = options
        self._dense: DenseOwl | None = None
        self._work: CameraModel | None = None
        self._last = _Last()
        self._lock = threading.Lock()
        self._next_due_ns: int | None = None

    @property
    def last(self) -> DenseSummary | None:
        """What ``owl: dense`` reports of the latest dense result (None before one)."""
        return self._last.result

    @property
    def camera_info_model(self) -> CameraModel | None:
        """The working grid's camera model (None before the first frame)."""
        return self._work

    def reset(self) -> None:
        """Forget the kept images and the last result (call when nobody listens for a
        while: ``owl: dense`` then says there is no result rather than show an old one)."""
        if self._dense is not None:
            self._dense.reset()
        self._next_due_ns = None
        with self._lock:
            self._last.result = None
            self._last.error = ""
            self._last.window_min = None

    def due(self, stamp_ns: int) -> bool:
        """Whether the frame stamped ``stamp_ns`` is to be measured under
        ``dense_max_rate_hz`` (always at 0). Decided by the stamps, so ``owl_process`` and
        the node measure the same frames: the due time advances by one period per measured
        frame (a 30 Hz camera under 20 Hz gives gaps of 2 and 1 frames, 20 frames/s), a
        frame up to a tenth of a period early counts as on time (stamp jitter), a gap
        longer than a period starts again from the frame after it, and so does a stamp
        before the last measured one (time went back: a looped bag, a restarted
        simulation)."""
        rate = self.options.dense_max_rate_hz
        if not rate > 0:
            return True
        period = round(1e9 / rate)
        nxt = self._next_due_ns
        if nxt is not None and nxt - period <= stamp_ns < nxt - period // 10:
            return False
        base = nxt if nxt is not None and 0 <= stamp_ns - nxt < period else stamp_ns
        self._next_due_ns = base + period
        return True

    def record_error(self, text: str) -> None:
        """Say in ``owl: dense`` why a frame gave no dense output."""
        with self._lock:
            self._fail(text)

    def _fail(self, text: str) -> None:
        """A frame gave no dense output (under the lock): the status says why until a
        frame gives one again, and counts it."""
        self._last.error = text
        self._last.errors += 1

    def count_dropped(self) -> None:
        """A job was dropped for a newer one (the dense stage fell behind)."""
        with self._lock:
            self._last.dropped += 1

    def begin(
        self, engine: OwlEngine | None, camera: CameraModel | None, image: Any, result: Any
    ) -> DenseJob | None:
        """Keep one frame's image (``(H, W)`` uint8 grey; ``result`` the engine's
        FrameResult); the job to measure, or None (first frame, no engine yet, bad image,
        or not :meth:`due` under ``dense_max_rate_hz``: the image is kept all the same)."""
        if engine is None or camera is None:
            return None
        opts = dense_options(self.options)
        if self._dense is None or self._dense.camera != camera or self._dense.options != opts:
            self._dense = DenseOwl(camera, opts)
            self._work = working_camera(camera, opts.width, opts.height)
        dense = self._dense
        try:
            pair = dense.take(image, int(result.stamp_ns))
        except OwlError as err:
            with self._lock:
                self._fail(f"dense: {err}")
            dense.reset()
            return None
        if pair is None or not self.due(pair.stamp_ns):
            return None
        rotation = None
        readout = None
        readout_ns = engine.readout_ns
        if engine.gyro.covers(pair.prev_stamp_ns, pair.stamp_ns):
            bias = engine.gyro_bias
            rotation = engine.gyro.relative_rotation(pair.prev_stamp_ns, pair.stamp_ns, bias)
            end = pair.stamp_ns + readout_ns  # each row from its own time, when covered
            if readout_ns > 0 and engine.gyro.covers(pair.prev_stamp_ns, end):
                stamps = [pair.prev_stamp_ns, pair.stamp_ns]
                rows = readout_rotations(engine.gyro, stamps, pair.stamp_ns, readout_ns, bias)
                readout = Readout(readout_ns * 1e-9, rows.rotations[0], rows.rotations[1])
        else:
            with self._lock:
                self._last.gyro_missing += 1
        inputs = DenseInputs(
            pair, rotation, result.heading, result.heading_sigma_rad, result.speed_rate, readout
        )
        return DenseJob(dense, inputs)

    def finish(self, job: DenseJob) -> DenseResult | None:
        """Measure a job in this thread and keep its summary for ``owl: dense``; None after
        bad input (said in the status)."""
        try:
            out = job.measure()
        except OwlError as err:
            self.record_error(f"dense: {err}")
            return None
        self.record(summarize(out))
        return out

    def request(self, job: DenseJob, speed: float | None, topics: frozenset[str]) -> DenseRequest:
        """The job as it crosses to the dense process, with what its messages need."""
        stride = self.options.dense_cloud_stride
        return DenseRequest(job.dense.camera, job.dense.options, job.inputs, speed, stride, topics)

    def answer(self, get: Callable[[], tuple[str, Any, Any]]) -> dict[str, Any] | None:
        """The arrays of the dense process's answer (``get``: its ``measure`` or
        ``receive``), its summary kept for ``owl: dense``; None after an error (said in the
        status)."""
        try:
            kind, summary, arrays = get()
        except DenseProcessError as err:
            self.record_error(f"{err}{_AGAIN}")
            return None
        if kind != "ok":
            self.record_error(summary)
            return None
        self.record(summary)
        result: dict[str, Any] = arrays
        return result

    def record(self, summary: DenseSummary) -> None:
        """Keep one frame's dense result for ``owl: dense`` (any thread)."""
        with self._lock:
            self._last.frames += 1
            self._last.result = summary
            self._last.error = ""
            seconds = summary.ttc_s
            if math.isfinite(seconds):
                best = self._last.window_min
                if best is None or seconds < best[0]:
                    self._last.window_min = (seconds, summary.ttc_pixel)
                if self._warning(seconds, summary.ttc_pixel) is not None:
                    self._last.warned += 1

    def _warning(self, seconds: float, pixel: Any) -> str | None:
        """The WARN line when a time to contact is below ``ttc_warn_s``."""
        limit = self.options.ttc_warn_s
        if not limit > 0 or not math.isfinite(seconds) or seconds >= limit:
            return None
        where = "" if pixel is None else f" at pixel ({pixel[0]:.0f}, {pixel[1]:.0f})"
        return f"time to contact {seconds:.2f} s < ttc_warn_s {limit:g} s{where}"

    def status(self) -> StatusRecord:
        """The ``owl: dense`` diagnostic status since the last call: WARN when the shortest
        time to contact in the path cone went below ``ttc_warn_s`` meanwhile, or when the
        newest frame gave no dense result (why, and no figures of an older result)."""
        with self._lock:
            last = self._last
            res = last.result
            error = last.error
            window_min, last.window_min = last.window_min, None
            values: dict[str, object] = {
                "dense_frames_total": last.frames,
                "dense_errors_total": last.errors,
                "ttc_warnings_total": last.warned,
                "frames_without_gyro_total": last.gyro_missing,
                "dropped_for_newer_total": last.dropped,
            }
        if error:
            return StatusRecord.build("owl: dense", Level.WARN, error, values)
        if res is None:
            msg = "no dense result yet (needs two frames while subscribed)"
            return StatusRecord.build("owl: dense", Level.OK, msg, values)
        shortest = window_min[0] if window_min is not None else math.nan
        values.update(
            {
                "confident_fraction": res.confident_fraction,
                "dense_ms": 1e3 * res.total_s,
                "ttc_s": res.ttc_s,
                "ttc_min_period_s": shortest,
                "ttc_cone_pixels": res.ttc_cone_pixels,
            }
        )
        if window_min is not None:
            warning = self._warning(*window_min)
            if warning is not None:
                return StatusRecord.build("owl: dense", Level.WARN, warning, values)
        text = "; ".join(res.reasons) or (
            "no approaching confident pixel in the path cone"
            if not math.isfinite(shortest)
            else f"shortest time to contact {shortest:.2f} s"
        )
        return StatusRecord.build("owl: dense", Level.OK, text, values)


def arrays_to_messages(
    arrays: dict[str, Any], work_camera: CameraModel, header: Any, wanted: Callable[[str], bool]
) -> dict[str, Any]:
    """Messages of :func:`~owl_ros.dense_worker.message_arrays`' arrays (and
    ``owl/depth/camera_info`` where wanted), with ``header``."""
    from geometry_msgs.msg import PointStamped

    out: dict[str, Any] = {}
    for topic in ("owl/looming", "owl/range_over_speed", "owl/depth/image"):
        if topic in arrays:
            out[topic] = array_to_image(arrays[topic], "32FC1", header=header)
    if wanted("owl/depth/camera_info"):
        out["owl/depth/camera_info"] = camera_model_to_info(work_camera, header)
    if "owl/dense_points" in arrays:
        out["owl/dense_points"] = array_to_cloud(arrays["owl/dense_points"], header)
    if "owl/time_to_contact" in arrays:
        msg = PointStamped(header=header)
        p = arrays["owl/time_to_contact"]
        msg.point.x, msg.point.y, msg.point.z = float(p[0]), float(p[1]), float(p[2])
        out["owl/time_to_contact"] = msg
    return {t: out[t] for t in TOPICS if t in out}  # publication order


def build_messages(
    result: DenseResult,
    work_camera: CameraModel,
    header: Any,
    speed: float | None,
    stride: int,
    wanted: Callable[[str], bool],
) -> dict[str, Any]:
    """Messages of one dense result for the topics where ``wanted(topic)`` is true.

    ``speed`` (m/s) makes the depth image and the cloud metric; None keeps seconds.
    """
    arrays = message_arrays(result, speed, stride, wanted)
    return arrays_to_messages(arrays, work_camera, header, wanted)


class DensePublishers:
    """The node's dense publishers; builds each message only while it has a subscriber.

    The dense stage runs beside the sparse engine, so that on a machine with two cores it
    measures one frame while the node's worker runs the sparse engine on the next:
    :meth:`publish` takes the image and what the dense stage needs from the engine (in the
    caller's thread, which owns the engine) and hands the job to the ``owl-dense`` thread;
    newest wins when it is still busy (the dropped job is counted in ``owl: dense``). The
    thread sends the job to the dense process and publishes what it returns
    (``dense_process``, the default: the process has its own interpreter, so the two
    stages do not take turns at the GIL), or measures it itself.

    Args:
        node: the rclpy node (publishers are created on it, reliable QoS ``qos``).
        options: node options.
        qos: QoS profile of the publications.
    """

    def __init__(self, node: Any, options: NodeOptions, qos: Any) -> None:
        from geometry_msgs.msg import PointStamped
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2

        kinds = {
            "sensor_msgs/msg/Image": Image,
            "sensor_msgs/msg/CameraInfo": CameraInfo,
            "sensor_msgs/msg/PointCloud2": PointCloud2,
            "geometry_msgs/msg/PointStamped": PointStamped,
        }
        self.stage = DenseStage(options)
        self._pubs = {t: node.create_publisher(kinds[k], t, qos) for t, k in TOPICS.items()}
        self._idle = True
        self._cond = threading.Condition()
        self._pending: tuple[Any, ...] | None = None
        self._busy = False
        self._closing = False
        self._process = DenseProcess() if options.dense_process else None
        self._thread = threading.Thread(target=self._loop, name="owl-dense", daemon=True)
        self._thread.start()

    @property
    def process(self) -> DenseProcess | None:
        """The dense child process's handle (``dense_process``), or None (a thread)."""
        return self._process

    def publish(self, out: Any, engine: OwlEngine | None, camera: CameraModel | None) -> None:
        """Hand one pipeline Output to the dense thread, which publishes what is
        subscribed."""
        listening = {t for t, p in self._pubs.items() if p.get_subscription_count() > 0}
        if not listening:
            if not self._idle:
                self.stage.reset()  # the kept images would be stale when someone returns
            self._idle = True
            return
        self._idle = False
        job = self.stage.begin(engine, camera, out.image, out.result)
        work = self.stage.camera_info_model
        if job is None or work is None:
            return
        with self._cond:
            if self._pending is not None:
                self.stage.count_dropped()
            self._pending = (job, work, out.header, out.speed, frozenset(listening))
            self._cond.notify_all()

    def _loop(self) -> None:
        name_os_thread()  # "owl-dense" in top -H
        while True:
            with self._cond:
                while self._pending is None and not self._closing:
                    self._cond.wait()
                if self._pending is None:
                    return
                item, self._pending = self._pending, None
                self._busy = True
            try:
                self._measure(*item)
            except Exception as err:  # a thread boundary: say it in the status, go on
                self.stage.record_error(f"dense thread: {type(err).__name__}: {err}")
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def _measure(
        self, job: DenseJob, work: CameraModel, header: Any, speed: Any, listening: Any
    ) -> None:
        wanted = listening.__contains__
        if self._process is None:
            result = self.stage.finish(job)
            if result is None:
                return
            stride = self.stage.options.dense_cloud_stride
            msgs = build_messages(result, work, header, speed, stride, wanted)
        else:
            process, req = self._process, self.stage.request(job, speed, listening)
            arrays = self.stage.answer(lambda: process.measure(req))
            if arrays is None:
                return
            msgs = arrays_to_messages(arrays, work, header, wanted)
        for topic, msg in msgs.items():
            self._pubs[topic].publish(msg)

    def wait_idle(self, timeout_s: float) -> bool:
        """Wait until the handed-over job is published; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: self._pending is None and not self._busy, timeout_s)

    def close(self, timeout_s: float = 5.0) -> None:
        """Finish the handed-over job and stop the dense thread (and process)."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self._thread.join(timeout=timeout_s)
        if self._process is not None:
            self._process.close(timeout_s)

    @property
    def publishers(self) -> list[Any]:
        """The publishers (for the shutdown flush)."""
        return list(self._pubs.values())


class DenseWriter:
    """``owl_process``'s dense topics: every message of every frame, into a bag writer.

    With ``dense_process`` (the default) the child process measures a frame while the
    caller's engine runs the next one: :meth:`write` hands over this frame's job after
    writing the previous frame's messages, and :meth:`flush` (before the diagnostics, and
    at the end) writes the one in flight. The messages are those of the thread: the same
    arrays, at the same stamps; only their place among the other topics' messages in the
    file differs (a reader takes them in log-time order).

    Args:
        options: node options.
        writer: a ``bags.io.BagWriter`` (topics are added here, ``/`` + the relative name).
        encode: ``(msg, msgtype) -> CDR bytes`` (owl_process's canonical encoder).
    """

    def __init__(self, options: NodeOptions, writer: Any, encode: Callable[[Any, str], bytes]):
        self.stage = DenseStage(options)
        self._writer = writer
        self._encode = encode
        self._process = DenseProcess() if options.dense_process else None
        self._in_flight: tuple[CameraModel, Any, int] | None = None
        for topic, kind in TOPICS.items():
            writer.add_topic("/" + topic, kind, "reliable")

    def write(self, out: Any, engine: OwlEngine | None, camera: CameraModel | None) -> None:
        """Run the dense stage on one pipeline Output and write all its messages (with a
        dense process: those of the previous frame, and hand this one over)."""
        from msg_adapters.stamps import header_to_ns

        job = self.stage.begin(engine, camera, out.image, out.result)
        work = self.stage.camera_info_model
        if job is None or work is None:
            return
        stamp = max(header_to_ns(out.header), 0)
        if self._process is None:
            result = self.stage.finish(job)
            if result is not None:
                stride = self.stage.options.dense_cloud_stride
                msgs = build_messages(result, work, out.header, out.speed, stride, lambda _: True)
                self._write(msgs, stamp)
            return
        self.flush()
        try:
            self._process.send(self.stage.request(job, out.speed, frozenset(TOPICS)))
        except DenseProcessError as err:
            self.stage.record_error(f"{err}{_AGAIN}")
            return
        self._in_flight = (work, out.header, stamp)

    def flush(self) -> None:
        """Write the messages of the frame the dense process is measuring (none without)."""
        if self._process is None or self._in_flight is None:
            return
        (work, header, stamp), self._in_flight = self._in_flight, None
        arrays = self.stage.answer(self._process.receive)
        if arrays is not None:
            self._write(arrays_to_messages(arrays, work, header, lambda _: True), stamp)

    def close(self) -> None:
        """Write what is in flight and stop the dense process."""
        try:
            self.flush()
        finally:
            if self._process is not None:
                self._process.close()

    def _write(self, msgs: dict[str, Any], stamp: int) -> None:
        for topic, msg in msgs.items():
            self._writer.write_raw("/" + topic, stamp, self._encode(msg, TOPICS[topic]))
