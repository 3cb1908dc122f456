"""Node ``owl`` (executable ``owl_node``): images + IMU in, OWL point cloud and heading out.

A thin node: everything is created in ``__init__``; the subscription callbacks never
block: an image goes straight into the pipeline's one bounded frame queue (newest wins,
:mod:`owl_ros.scheduler`), every other message into the node's :class:`Inbox`; one worker
thread owns the :class:`~owl_ros.pipeline.Pipeline` (engine, IMU buffer), hands it the
inbox's messages in order, processes frames and publishes (the engine's tracker detects
new corners on a helper thread of its own while the worker estimates the frame). Topics,
parameters and diagnostics are described in ``docs`` / contract.md and
``config/owl.yaml``; every parameter is declared from the one table in
:mod:`owl_ros.params`.

Subscriptions (rclpy's sensor-data QoS: best effort, volatile, keep last 5, the IMU 200;
they match reliable and best-effort drivers and replayed bags): ``image`` (or
``image/compressed`` with ``image_transport: compressed``), ``camera_info``, ``imu`` and,
with ``speed_source`` odometry/twist, ``speed_topic``. Publications (reliable, volatile,
keep last 10): ``owl/points``, ``owl/heading``, ``owl/heading_with_covariance``,
``owl/gyro_bias``, ``owl/heading_marker``, ``/diagnostics`` and ``owl/debug_image`` (built
only while someone subscribes). QoS-incompatible peers of each are reported in
``/diagnostics``; the history, depth and reliability of each may be set at start with the
standard read-only ``qos_overrides.<topic>.<subscription|publisher>.<policy>`` parameters
(an override the node has no such entity for is warned about, not ignored silently).

Time: header stamps only for the maths; the node's clock (``use_sim_time`` honoured) only
stamps diagnostics and measures stamp -> publication latency; waits are on a monotonic
clock.
"""

from __future__ import annotations

import collections
import contextlib
import signal
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from enum import StrEnum
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped, TwistWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import InvalidQosOverridesError, QoSOverridingOptions
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, Imu, PointCloud2
from visualization_msgs.msg import Marker

from msg_adapters.debug_image import draw_debug
from msg_adapters.diagnostics import records_to_msg
from msg_adapters.image import array_to_image
from msg_adapters.stamps import header_to_ns
from owl_core.os_thread import name_os_thread
from owl_ros import node_report
from owl_ros.dense_outputs import DensePublishers
from owl_ros.extrinsic_tf import TfExtrinsic, tf_available
from owl_ros.heap import keep_freed_memory
from owl_ros.params import (
    PARAMS,
    NodeOptions,
    ParameterError,
    build_options,
    descriptor,
    validate,
)
from owl_ros.pipeline import Output, Pipeline
from owl_ros.roles import Role
from owl_ros.threads import one_blas_thread
from owl_ros.topics import GYRO_BIAS, RESULT_TOPICS

PROG = "owl_node"
NODE_NAME = "owl"
#: depth of the best-effort subscriptions (IMU deeper: 400 Hz bursts while busy).
IMAGE_DEPTH = 5
IMU_DEPTH = 200
#: depth of the reliable publications.
PUB_DEPTH = 10
#: length of the owl/heading_marker arrow, m (RViz).
MARKER_LENGTH = 5.0
#: signals that stop the node cleanly (exit code 0).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: executor spin_once timeout: how soon a stop signal is noticed, s.
SPIN_TIMEOUT_S = 0.1
#: longest worker sleep between checks, s.
WORKER_TICK_S = 0.05
#: at shutdown, how long to wait for subscribers to acknowledge the last outputs, s.
FLUSH_TIMEOUT_S = 1.0


class Control(StrEnum):
    """Inbox entries that are not input messages."""

    OPTIONS = "options"  # new NodeOptions (parameters changed, or the rotation from TF)
    QOS = "qos"  # the text of an incompatible-QoS event


Kind = Role | Control


class Inbox:
    """Thread-safe, ordered hand-over of the non-image inputs from the callbacks to the
    worker (images go to the pipeline's frame queue).

    IMU, camera_info and speed messages wait in one deque bounded generously
    (``capacity``; the oldest is dropped when full, counted in ``dropped``) so memory stays
    bounded even if the worker stalls. Control entries (option changes, QoS events) are
    rare and never dropped: a parameter change that was acknowledged is always applied.
    ``drain`` hands everything over in the order it was put; ``wait`` lets the worker
    sleep until something arrives.
    """

    def __init__(self, capacity: int = 20000) -> None:
        self._lock = threading.Lock()
        self._event = threading.Event()
        self._items: collections.deque[tuple[int, Kind, Any, int]] = collections.deque(
            maxlen=capacity
        )
        self._controls: list[tuple[int, Kind, Any, int]] = []
        self._seq = 0
        self.dropped = 0

    def put(self, kind: Kind, msg: Any, arrival_ns: int) -> None:
        """Store one entry (the oldest message gives way when full; controls never do)."""
        with self._lock:
            self._seq += 1
            entry = (self._seq, kind, msg, arrival_ns)
            if isinstance(kind, Control):
                self._controls.append(entry)
            else:
                if len(self._items) == self._items.maxlen:
                    self.dropped += 1
                self._items.append(entry)
        self._event.set()

    def wait(self, timeout_s: float) -> None:
        """Sleep until something is put (or :meth:`wake`) or ``timeout_s`` passes."""
        self._event.wait(timeout_s)
        self._event.clear()

    def wake(self) -> None:
        """Wake a waiting worker (an image was queued, or to stop it)."""
        self._event.set()

    def drain(self) -> list[tuple[Kind, Any, int]]:
        """Every entry ``(kind, message, arrival ns)``, in the order put."""
        with self._lock:
            items = list(self._items)
            self._items.clear()
            if self._controls:
                items = sorted(items + self._controls, key=lambda e: e[0])
                self._controls = []
        return [(kind, msg, arrival) for _, kind, msg, arrival in items]


def feed(
    pipeline: Pipeline,
    entries: Sequence[tuple[Kind, Any, int]],
    on_error: Callable[[Kind, Exception], None] | None = None,
    on_options: Callable[[NodeOptions], None] | None = None,
) -> list[Output]:
    """Hand inbox entries to the pipeline in order (runs of IMU messages in one batch);
    returns the outputs of frames processed out of turn (before an IMU time jump).

    An entry that raises is reported to ``on_error`` (re-raised without one) and the
    entries after it are still handed over: a bad message costs only itself, never the
    IMU samples, calibration or option changes drained with it. ``on_options`` also
    receives every option change (the dense stage's settings follow them).
    """
    outs: list[Output] = []
    imus: list[Any] = []
    for i, (kind, msg, arrival_ns) in enumerate(entries):
        try:
            if kind is Role.IMU:
                imus.append(msg)
                if i + 1 < len(entries) and entries[i + 1][0] is Role.IMU:
                    continue
                batch, imus = imus, []
                outs += pipeline.add_imus(batch, arrival_ns)
            elif kind is Control.OPTIONS:
                pipeline.reconfigure(msg)
                if on_options is not None:
                    on_options(msg)
            elif kind is Control.QOS:
                pipeline.note_qos_event(msg)
            else:
                outs += pipeline.add(kind, msg, arrival_ns)
        except Exception as err:
            if on_error is None:
                raise
            on_error(kind, err)
    return outs


def _sensor_qos(depth: int) -> QoSProfile:
    """rclpy's ``qos_profile_sensor_data`` with ``depth`` (a new profile each call: a QoS
    override changes the profile it is applied to)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT
    )


def _reliable_qos() -> QoSProfile:
    """Reliable, volatile, keep last ``PUB_DEPTH`` (a new profile each call)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=PUB_DEPTH, reliability=ReliabilityPolicy.RELIABLE
    )


def _check_qos_override(qos: QoSProfile) -> SetParametersResult:
    """Refuse an overridden profile that rmw would fail on with an obscure error."""
    if qos.history == HistoryPolicy.KEEP_LAST and qos.depth < 1:
        return SetParametersResult(
            successful=False, reason=f"depth must be >= 1 with keep_last, got {qos.depth}"
        )
    return SetParametersResult(successful=True)


#: the QoS policies of each subscription and publication of node.py that a user may set at
#: start with read-only ``qos_overrides.<topic>.<subscription|publisher>.<policy>``
#: parameters (``<topic>`` resolved: ``/camera/image_raw`` after ``-r image:=...``).
QOS_OVERRIDES = QoSOverridingOptions.with_default_policies(callback=_check_qos_override)


def heading_marker(heading: Any, header: Any) -> Any:
    """visualization_msgs/Marker: an arrow from the camera along the heading (for RViz,
    which has no Vector3Stamped display)."""
    from geometry_msgs.msg import Point

    marker = Marker(header=header, ns="owl_heading", id=0, type=Marker.ARROW)
    marker.action = Marker.ADD
    tip = Point(
        x=float(heading[0]) * MARKER_LENGTH,
        y=float(heading[1]) * MARKER_LENGTH,
        z=float(heading[2]) * MARKER_LENGTH,
    )
    marker.points = [Point(), tip]
    marker.pose.orientation.w = 1.0
    marker.scale.x, marker.scale.y, marker.scale.z = 0.08, 0.2, 0.3
    marker.color.g, marker.color.a = 1.0, 1.0
    return marker


def _param_value(value: Any) -> Any:
    """A parameter value as plain Python (double arrays come as array.array)."""
    if hasattr(value, "tolist") or isinstance(value, list | tuple):
        return list(value)
    return value


class OwlNode(Node):
    """The OWL node (see the module docstring).

    Raises:
        ParameterError: invalid parameter values at start (one line per value).
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        node_report.coerce_overrides(self._parameter_overrides)  # 1 for 1.0, [0,0,0,1]
        values, lines = self._declare()
        lines += validate(values, unknown_ok=True) if not lines else []
        unknown, unknown_warnings = node_report.unknown_parameters(self._parameter_overrides)
        lines += unknown
        if lines:
            raise ParameterError(lines)
        for line in unknown_warnings:
            self.get_logger().warning(line)
        self.options = build_options(values)
        self._values = values
        self._lock = threading.Lock()
        self._inbox = Inbox()
        self._backlog_dropped = 0  # the inbox's drops already counted
        self._pipeline = Pipeline(self.options, clock=time.monotonic_ns, live=True)
        self._calibration_logged = False
        self._stop = threading.Event()

        self._inputs: list[tuple[Any, str]] = []  # (subscription, expected type name)
        if self.options.image_transport == "compressed":
            self._subscribe(CompressedImage, "image/compressed", self._on_image, IMAGE_DEPTH)
        else:
            self._subscribe(Image, "image", self._on_image, IMAGE_DEPTH)
        self._subscribe(CameraInfo, "camera_info", self._on_camera_info, IMAGE_DEPTH)
        self._subscribe(Imu, "imu", self._on_imu, IMU_DEPTH)
        if self.options.speed_source != "none":
            kind = Odometry if self.options.speed_source == "odometry" else TwistStamped
            topic = self.options.speed_topic
            self._subscribe(kind, topic, self._on_speed, IMAGE_DEPTH, param="speed_topic")

        self._points_pub = self._advertise(PointCloud2, "owl/points")
        self._heading_pub = self._advertise(Vector3Stamped, "owl/heading")
        self._bias_pub = self._advertise(Vector3Stamped, GYRO_BIAS.name)
        self._diag_pub = self._advertise(DiagnosticArray, "/diagnostics")
        self._debug_pub = None
        if self.options.publish_debug_image:
            self._debug_pub = self._advertise(Image, "owl/debug_image")
        self._marker_pub = self._advertise(Marker, "owl/heading_marker")
        self._dense: DensePublishers | None = None
        if self.options.dense:
            self._dense = DensePublishers(self, self.options, _reliable_qos())
        self._heading_cov_pub = self._advertise(
            TwistWithCovarianceStamped, "owl/heading_with_covariance"
        )
        self._warn_unused_qos_overrides()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._announce()
        self._worker = threading.Thread(target=self._run, name="owl-worker", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------ setup helpers

    def _declare(self) -> tuple[dict[str, Any], list[str]]:
        values: dict[str, Any] = {}
        lines: list[str] = []
        for p in PARAMS:
            default = list(p.default) if p.kind == "double_array" else p.default
            try:
                param = self.declare_parameter(p.name, default, descriptor(p))
            except ParameterException as err:
                lines.append(f"parameter {p.name}: {' '.join(str(err).split())}")
                continue
            except (TypeError, ValueError) as err:
                # rclpy: an override of the wrong type (e.g. an int for a double array)
                lines.append(
                    f"parameter {p.name}: wrong type ({' '.join(str(err).split())}); "
                    f"expected {p.kind}"
                )
                continue
            values[p.name] = _param_value(param.value)
        return values, lines

    def _announce(self) -> None:
        """Log the start-up line; choose the extrinsic source; prepare the silence watch."""
        roles = (Role.IMAGE, Role.CAMERA_INFO, Role.IMU, Role.SPEED)
        self._topics: dict[Role, str] = {
            role: sub.topic_name for role, (sub, _) in zip(roles, self._inputs, strict=False)
        }
        self._frames: dict[Role, str] = {}  # role -> header.frame_id of its first message
        self._tf: TfExtrinsic | None = None
        log = self.get_logger()
        rotation = self.options.engine.camera_to_imu_rotation_xyzw
        if "camera_to_imu_rotation_xyzw" in self._parameter_overrides:
            source = "parameter"
            if tuple(abs(v) for v in rotation) == (0.0, 0.0, 0.0, 1.0) and tf_available():
                source += f" ({node_report.IDENTITY_BLOCKS_TF})"
        elif tf_available():
            self._tf = TfExtrinsic(self)
            source = "default (identity) until TF has the IMU -> camera transform"
        else:
            source = "default (identity)"
            log.warning(node_report.extrinsic_warning(tf_available=False))
        pubs = [self._points_pub, self._heading_pub, self._heading_cov_pub, self._bias_pub]
        pubs += [self._diag_pub, self._marker_pub]
        pubs += [self._debug_pub] if self._debug_pub else []
        pubs += self._dense.publishers if self._dense is not None else []
        names = [p.topic_name for p in pubs]
        log.info(
            node_report.startup_line(
                self._topics, names, rotation, source, self.options.speed_source
            )
        )
        self._watch = node_report.SilenceWatch(self._topics)
        self._tf_deadline = time.monotonic() + node_report.WARN_PERIOD_S

    def _check_tf(self) -> None:
        """Once the image's and the IMU's frame_id are known, take the rotation from TF."""
        cam, imu = self._frames.get(Role.IMAGE), self._frames.get(Role.IMU)
        tf = self._tf  # the parameter callback may drop it meanwhile
        if tf is None or not cam or not imu:
            return
        found = tf.lookup(cam, imu)
        if found is None:
            if time.monotonic() > self._tf_deadline:
                self._tf_deadline = time.monotonic() + 1e9  # once
                self.get_logger().warning(
                    f"no TF transform {imu} -> {cam} yet: "
                    + node_report.extrinsic_warning(tf_available=True)
                )
            return
        with self._lock:
            if self._tf is None:  # the parameter was set meanwhile: it wins
                return
            self._drop_tf()
            # into the parameter values too, so that a later parameter change keeps it
            values = {**self._values, "camera_to_imu_rotation_xyzw": list(found)}
            options = build_options(values)
            self._values = values
            self.options = options
            # queued under the lock: option sets reach the worker in the order they were
            # built, so neither this rotation nor a parameter change overtakes the other
            self._inbox.put(Control.OPTIONS, options, time.monotonic_ns())
        self.get_logger().info(
            f"camera_to_imu_rotation_xyzw {list(found)} from TF ({imu} -> {cam})"
        )

    def _drop_tf(self) -> None:
        """No more TF lookups (the rotation is known); unsubscribe from TF. Under the lock."""
        tf, self._tf = self._tf, None
        if tf is not None:
            try:
                tf.close()
            except Exception as err:  # only costs the TF messages' deserialisation
                self.get_logger().warning(f"TF listener not closed: {err}")

    def _subscribe(
        self, kind: Any, topic: str, callback: Any, depth: int, param: str = ""
    ) -> None:
        """Subscribe with the sensor-data QoS (best effort: matches reliable and best-effort
        publishers), QoS events reported, ``qos_overrides`` honoured. ``param``: the
        parameter that gave ``topic``, named if it cannot be resolved."""
        try:
            name = self.resolve_topic_name(topic)
        except RuntimeError as err:  # rclpy's RCLError, e.g. "a//b"
            why = " ".join(str(err).split())
            raise ParameterError([f"parameter {param or topic}: {why}, got {topic!r}"]) from None
        events = SubscriptionEventCallbacks(
            incompatible_qos=lambda info: self._qos_event("subscription", name, info)
        )
        with self._qos_override_errors(name, "subscription"):
            sub = self.create_subscription(
                kind, topic, callback, _sensor_qos(depth), event_callbacks=events,
                qos_overriding_options=QOS_OVERRIDES,
            )  # fmt: skip
        package = kind.__module__.split(".")[0]
        self._inputs.append((sub, f"{package}/msg/{kind.__name__}"))

    def _advertise(self, kind: Any, topic: str) -> Any:
        """A reliable publisher (keep last ``PUB_DEPTH``), QoS events reported in
        /diagnostics, ``qos_overrides`` honoured."""
        name = self.resolve_topic_name(topic)
        with self._qos_override_errors(name, "publisher"):
            return self.create_publisher(
                kind, topic, _reliable_qos(), event_callbacks=self._pub_events(name),
                qos_overriding_options=QOS_OVERRIDES,
            )  # fmt: skip

    @contextlib.contextmanager
    def _qos_override_errors(self, topic: str, side: str) -> Iterator[None]:
        """A bad ``qos_overrides.<topic>.<side>.*`` value as a ParameterError (one line)."""
        prefix = f"qos_overrides.{topic}.{side}."
        try:
            yield
        except (ParameterException, InvalidQosOverridesError, RuntimeError) as err:
            if not any(n.startswith(prefix) for n in self._parameter_overrides):
                raise
            raise ParameterError([f"parameters {prefix}*: {' '.join(str(err).split())}"]) from None

    def _warn_unused_qos_overrides(self) -> None:
        """A ``qos_overrides`` parameter that no subscription or publication declared (a
        topic the node does not have, a policy other than history, depth, reliability, or a
        dense topic) changes nothing: say so rather than ignore it silently."""
        for name in sorted(self._parameter_overrides):
            if name.startswith("qos_overrides.") and not self.has_parameter(name):
                self.get_logger().warning(
                    f"parameter {name}: no such QoS override (the node's topics accept "
                    "history, depth and reliability), ignored"
                )

    def _foreign_publishers(self) -> list[str]:
        """Publishers on an input topic whose type is not the one subscribed.

        DDS never matches them, and Fast DDS raises no incompatible-type event, so without
        this graph query the only symptom would be "no images".
        """
        found = []
        for sub, expected in self._inputs:
            for info in self.get_publishers_info_by_topic(sub.topic_name):
                if info.topic_type != expected:
                    who = f"{info.node_namespace.rstrip('/')}/{info.node_name}"
                    if info.node_name == "_NODE_NAME_UNKNOWN_":  # not discovered yet
                        who = "(node not known yet)"
                    found.append(
                        f"{sub.topic_name}: publisher {who} offers type {info.topic_type}, "
                        f"subscribed as {expected}"
                    )
        return found

    def _pub_events(self, topic: str) -> PublisherEventCallbacks:
        return PublisherEventCallbacks(
            incompatible_qos=lambda info: self._qos_event("publication", topic, info)
        )

    def _qos_event(self, side: str, topic: str, info: Any) -> None:
        policy = getattr(info.last_policy_kind, "name", str(info.last_policy_kind))
        text = (
            f"{side} {topic}: incompatible QoS with a peer (policy {policy}, "
            f"{info.total_count} total)"
        )
        self.get_logger().warning(text)
        self._inbox.put(Control.QOS, text, time.monotonic_ns())

    # ------------------------------------------------------------------ callbacks

    def _on_image(self, msg: Any) -> None:
        if msg.header.frame_id:  # the first non-empty one (TF needs a name)
            self._frames.setdefault(Role.IMAGE, msg.header.frame_id)
        self._pipeline.add_image(msg, time.monotonic_ns())  # thread-safe: only queues
        self._inbox.wake()

    def _on_camera_info(self, msg: Any) -> None:
        self._inbox.put(Role.CAMERA_INFO, msg, time.monotonic_ns())

    def _on_imu(self, msg: Any) -> None:
        if msg.header.frame_id:
            self._frames.setdefault(Role.IMU, msg.header.frame_id)
        self._inbox.put(Role.IMU, msg, time.monotonic_ns())

    def _on_speed(self, msg: Any) -> None:
        self._inbox.put(Role.SPEED, msg, time.monotonic_ns())

    def _on_set_parameters(self, params: Sequence[Any]) -> SetParametersResult:
        changes = {p.name: _param_value(p.value) for p in params}
        known = {k: v for k, v in changes.items() if any(q.name == k for q in PARAMS)}
        if not known:
            return SetParametersResult(successful=True)
        with self._lock:
            merged = {**self._values, **known}
            lines = validate(merged, unknown_ok=True)
            if lines:
                return SetParametersResult(successful=False, reason="; ".join(lines))
            try:
                options = build_options(merged)
            except ParameterError as err:
                return SetParametersResult(successful=False, reason="; ".join(err.lines))
            self._values = merged
            self.options = options
            if "camera_to_imu_rotation_xyzw" in known:
                self._drop_tf()  # the parameter overrides TF
            self._inbox.put(Control.OPTIONS, options, time.monotonic_ns())
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ worker

    def _run(self) -> None:
        name_os_thread()  # "owl-worker" in top -H
        diag_period_ns = round(self.options.diagnostics_period_s * 1e9)
        next_diag = time.monotonic_ns() + diag_period_ns
        self._pipeline.start_window()
        busy = False  # a frame was taken last step: more may be ready, do not sleep
        while not self._stop.is_set():
            now = time.monotonic_ns()
            deadline = self._pipeline.deadline_ns()
            timeout = WORKER_TICK_S
            if deadline is not None:
                timeout = min(timeout, max((deadline - now) * 1e-9, 0.001))
            if not busy:
                self._inbox.wait(min(timeout, max((next_diag - now) * 1e-9, 0.001)))
            if self._stop.is_set():
                break
            busy = False  # stays so if the step raises
            try:
                busy = self._step()
            except Exception as err:  # keep running whatever one message did
                if not self.context.ok():
                    break
                self._worker_error("worker", err)
            now = time.monotonic_ns()
            if now < next_diag:
                continue
            diag_period_ns = round(self.options.diagnostics_period_s * 1e9)
            next_diag = now + diag_period_ns
            try:  # on its own: /diagnostics goes on even while every step fails
                self._publish_diagnostics(now)
            except Exception as err:
                if not self.context.ok():
                    break
                self._worker_error("diagnostics", err)

    def _worker_error(self, where: str, err: Exception) -> None:
        """Log an exception the worker survived (at most once a second: a message that
        fails every frame must not flood the log) and say it in ``owl: processing``."""
        text = f"{where}: {type(err).__name__}: {err}"
        self._pipeline.record_worker_error(text)
        self.get_logger().error(text, throttle_duration_sec=1.0)

    def _on_options(self, options: NodeOptions) -> None:
        """An option change reached the worker: the dense stage follows it too."""
        if self._dense is not None:
            self._dense.stage.options = options

    def _step(self) -> bool:
        """Hand over what arrived, then process at most one frame and publish its outputs
        at once (a newer frame arriving meanwhile is seen before the next one is taken).
        Returns whether a frame was taken from the queue."""
        pipeline = self._pipeline
        entries = self._inbox.drain()
        dropped = self._inbox.dropped  # read after the drain: counts what it lost
        if dropped > self._backlog_dropped:
            pipeline.count_backlog_dropped(dropped - self._backlog_dropped)
            self._backlog_dropped = dropped
        outs = feed(
            pipeline,
            entries,
            on_error=lambda kind, err: self._worker_error(f"input {kind}", err),
            on_options=self._on_options,
        )
        for out in outs:
            self._publish(out)  # frames from before an IMU time jump
        before = pipeline.frames_taken
        start = time.monotonic_ns()
        outs = pipeline.poll(limit=1)
        for out in outs:
            self._publish(out)
        taken = pipeline.frames_taken > before
        if taken and outs:
            pipeline.record_cycle((time.monotonic_ns() - start) * 1e-9)
        return taken

    def _publish(self, out: Output) -> None:
        self._points_pub.publish(out.cloud)
        if out.heading is not None:
            self._heading_pub.publish(out.heading)
        if out.heading_cov is not None:
            self._heading_cov_pub.publish(out.heading_cov)
        if out.gyro_bias is not None:
            self._bias_pub.publish(out.gyro_bias)
        done = time.monotonic_ns()
        clock_ns = self.get_clock().now().nanoseconds  # 0 under use_sim_time before /clock
        stamp_latency = (clock_ns - header_to_ns(out.header)) * 1e-9 if clock_ns > 0 else None
        self._pipeline.record_latency((done - out.arrival_ns) * 1e-9, stamp_latency)
        if out.result.heading is not None and self._marker_pub.get_subscription_count() > 0:
            self._marker_pub.publish(heading_marker(out.result.heading, out.header))
        pub = self._debug_pub
        if pub is not None and pub.get_subscription_count() > 0:
            picture = draw_debug(out.image, out.result, self._pipeline.camera)
            pub.publish(array_to_image(picture, "bgr8", header=out.header))
        if self._dense is not None:
            self._dense.publish(out, self._pipeline.engine, self._pipeline.camera)

    def _publish_diagnostics(self, now_mono_ns: int) -> None:
        records = self._pipeline.diagnostics(self._foreign_publishers())
        verdict = self._pipeline.calibration_verdict
        if verdict is not None and verdict.disagrees and not self._calibration_logged:
            self._calibration_logged = True  # once: /diagnostics keeps saying it
            self.get_logger().warning(f"camera-IMU calibration: {verdict.message}")
        records += [self._dense.stage.status()] if self._dense is not None else []
        records = node_report.name_inputs(records, self._topics, self.get_fully_qualified_name())
        totals = self._pipeline.totals
        received = {role: totals.received(role) for role in self._topics}
        for line in self._watch.check(
            now_mono_ns * 1e-9, received, node_report.empty_reason(records)
        ):
            self.get_logger().warning(line)
        self._check_tf()
        stamp = self.get_clock().now().nanoseconds
        self._diag_pub.publish(records_to_msg(records, max(stamp, 0)))

    def close(self) -> None:
        """Stop the worker thread, then give the reliable subscribers up to
        ``FLUSH_TIMEOUT_S`` to acknowledge the last outputs, so that the last cloud of a
        replay, still in flight, is not lost with the writers. Call before destroy_node."""
        self._stop.set()
        self._inbox.wake()
        if self._worker.is_alive():
            self._worker.join(timeout=5.0)
        if self._dense is not None:
            self._dense.close()  # its thread publishes the last handed-over frame first
        deadline = time.monotonic() + FLUSH_TIMEOUT_S
        pubs = [self._points_pub, self._heading_pub, self._heading_cov_pub, self._bias_pub]
        pubs += [self._marker_pub, self._debug_pub]
        dense = self._dense.publishers if self._dense is not None else []
        for pub in (*pubs, *dense, self._diag_pub):
            left = deadline - time.monotonic()
            if pub is not None and left > 0 and pub.get_subscription_count() > 0:
                if not pub.wait_for_all_acked(Duration(nanoseconds=round(left * 1e9))):
                    self.get_logger().warning(
                        f"{pub.topic_name}: not every subscriber acknowledged the last "
                        f"message within {FLUSH_TIMEOUT_S} s of shutdown"
                    )


def _help() -> str:
    lines = [
        f"usage: {PROG} [--ros-args -p NAME:=VALUE ... --params-file FILE -r FROM:=TO ...]",
        "",
        *textwrap.wrap(
            "OWL node 'owl': subscribes image (or image/compressed), camera_info, imu (and "
            "the speed_topic with speed_source); publishes "
            + ", ".join(t.name for t in RESULT_TOPICS)
            + ", owl/debug_image (publish_debug_image) and the dense images and cloud "
            "(dense). Parameters:",
            88,
        ),
    ]
    for p in PARAMS:
        ro = ", read-only" if p.read_only else ""
        rng = p.constraint_text()
        lines.append(f"  {p.name} ({p.kind}, default {p.default!r}{ro}) {rng}")
        lines.append(f"      {p.description}")
    return "\n".join(lines)


def _executor() -> Any:
    """rclpy's EventsExecutor when available (callbacks dispatched from C++: a fraction of
    the per-message cost of the Python SingleThreadedExecutor at 400 Hz IMU), else the
    SingleThreadedExecutor."""
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:
        return SingleThreadedExecutor()
    return EventsExecutor()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``owl_node``; returns the exit status (0 after SIGINT/SIGTERM)."""
    args = list(sys.argv[1:] if argv is None else argv)
    own = args[: args.index("--ros-args")] if "--ros-args" in args else args
    if "-h" in own or "--help" in own:
        try:
            print(_help())
        except BrokenPipeError:  # e.g. owl_node --help | head
            pass
        return 0
    heap_line = keep_freed_memory()
    blas_line = one_blas_thread()
    stop = threading.Event()
    bad_file = node_report.check_params_file_args(args)
    if bad_file is not None:
        print(f"{PROG}: error: {bad_file}", file=sys.stderr)
        return 2
    try:
        rclpy.init(args=[PROG, *args], signal_handler_options=SignalHandlerOptions.NO)
    except Exception as err:  # rclpy's RCLError: a bad --ros-args item
        print(f"{PROG}: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    # SIGINT/SIGTERM end the spin loop below; the node then shuts down in order
    old = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in STOP_SIGNALS}
    try:
        node = OwlNode()
    except ParameterError as err:
        for line in err.lines:
            print(f"{PROG}: error: {line}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    node.get_logger().debug(heap_line)
    node.get_logger().debug(blas_line)
    executor = _executor()
    executor.add_node(node)
    try:
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=SPIN_TIMEOUT_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.close()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return 0


if __name__ == "__main__":
    sys.exit(main())
