"""owl_process IN_BAG -o OUT_BAG: node ``owl``'s pipeline over a bag, without DDS.

Reads the image (raw or compressed: taken from the topic's type), camera_info and IMU
topics (and optionally a speed topic) in log-time order, feeds them to the same
:class:`~owl_ros.pipeline.Pipeline` the node uses, with the bag's log time as the clock
(so the result is deterministic: the same bag and options give the same bytes), and
writes an MCAP rosbag2 with

- ``/owl/points`` (sensor_msgs/PointCloud2), ``/owl/heading`` and ``/owl/gyro_bias``
  (Vector3Stamped), logged at the image stamp, headers = the image's header (the bias's
  frame is the IMU's); the table is :mod:`owl_ros.topics`;
- ``/diagnostics`` (DiagnosticArray) every ``diagnostics_period_s`` of bag time and at the
  end (these hold measured processing times, so only they differ between runs);
- with ``--copy-inputs``, every input topic of the bag as recorded (one file for Foxglove).

The camera-IMU rotation comes from ``--camera-to-imu-rotation-xyzw`` when given, else from
the bag's ``/tf_static`` (the transform from the IMU frame to the camera frame, either
direction), else identity; ``-p camera_to_imu_rotation_xyzw:=[...]`` and a parameter file
setting a non-identity rotation count as given. Any node parameter can be set with
``-p NAME:=VALUE`` or a ROS parameter file (``--params-file config/owl.yaml``).

Python use (evaluation, demo)::

    from owl_ros.process import process_bag, ProcessOptions
    summary = process_bag("in_bag", "out_bag", ProcessOptions())
    summary.heading_stamps_ns, summary.headings, summary.heading_sigma_rad
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import numpy.typing as npt

from bags.cli import OneLineErrorParser
from bags.errors import BagError, CorruptBagError
from bags.io import BagReader, BagWriter, RawMessage, serialize
from msg_adapters.diagnostics import records_to_msg
from msg_adapters.msgtypes import message_class
from msg_adapters.stamps import header_to_ns
from owl_core.geometry import matrix_to_quat_xyzw, quat_xyzw_to_matrix, so3_log
from owl_ros.counters import Skip
from owl_ros.dense_outputs import DenseWriter
from owl_ros.heap import keep_freed_memory
from owl_ros.node import heading_marker
from owl_ros.node_report import EXTRINSIC_HOWTO, unknown_parameters
from owl_ros.params import (
    NodeOptions,
    ParameterError,
    build_options,
    defaults,
    parse_assignment,
    to_values,
)
from owl_ros.pipeline import Output, Pipeline
from owl_ros.roles import Role
from owl_ros.threads import one_blas_thread
from owl_ros.topics import (
    DIAGNOSTICS,
    GYRO_BIAS,
    HEADING,
    HEADING_COV,
    HEADING_MARKER,
    POINTS,
    RESULT_TOPICS,
)

PROG = "owl_process"

TF_STATIC = "/tf_static"
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
SPEED_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/TwistStamped")


#: what to do with a bag that has no IMU topic.
NO_IMU_HINT = "for a bag without IMU: --imu-topic '' -p require_gyro:=false"


class ProcessError(Exception):
    """Bad input for owl_process (one-line message naming the topic, path or value)."""


@dataclass(frozen=True)
class ProcessOptions:
    """What to read and how.

    Attributes:
        node: node options (engine included); the same parameters as node ``owl``.
        image_topic: sensor_msgs/Image or CompressedImage topic.
        camera_info_topic: sensor_msgs/CameraInfo topic.
        imu_topic: sensor_msgs/Imu topic ("" = no IMU).
        speed_topic: nav_msgs/Odometry or TwistStamped topic for metric clouds ("" = none).
        rotation_from_tf: take camera_to_imu_rotation_xyzw from /tf_static when present
            (False when the rotation was given explicitly).
        copy_inputs: copy every input topic into the output bag.
        overwrite: replace an existing output bag.
    """

    node: NodeOptions = field(default_factory=NodeOptions)
    image_topic: str = "/camera/image_raw"
    camera_info_topic: str = "/camera/camera_info"
    imu_topic: str = "/imu/data"
    speed_topic: str = ""
    rotation_from_tf: bool = True
    copy_inputs: bool = False
    overwrite: bool = False


@dataclass(frozen=True)
class Summary:
    """What ``process_bag`` did.

    Attributes:
        out_path: the output bag.
        images: image messages read.
        frames_processed: frames the engine processed.
        frames_with_points: of those, frames with at least one point.
        points: total points written.
        heading_stamps_ns: (K,) int64 stamps of the frames with a heading.
        headings: (K, 3) float64 unit headings (camera optical frame).
        heading_sigma_rad: (K,) float64 1-sigma heading uncertainty, rad.
        extrinsic_source: "option", "tf_static" or "default" (identity).
        camera_to_imu_rotation_xyzw: the rotation used.
        tf_static_rotation_xyzw: the bag's /tf_static rotation (also when another was
            given), or None.
        calibration_warning: the live calibration check's verdict at the end of the bag
            when it finds images and gyro disagreeing (one line), else None.
        counts: pipeline totals (drops, skips, IMU problems...), and ``undecodable TOPIC``:
            messages of TOPIC that could not be read.
        reasons: reasons for frames without points, with counts.
        last_skip_reason: why the newest frame taken but not processed was skipped, or why
            the newest processed frame had no points ("" for neither).
        damage: one line when the input bag was truncated/corrupt (the readable part was
            processed), else None.
        elapsed_s: wall time, s.
    """

    out_path: Path
    images: int
    frames_processed: int
    frames_with_points: int
    points: int
    heading_stamps_ns: npt.NDArray[np.int64]
    headings: npt.NDArray[np.float64]
    heading_sigma_rad: npt.NDArray[np.float64]
    extrinsic_source: str
    camera_to_imu_rotation_xyzw: tuple[float, float, float, float]
    tf_static_rotation_xyzw: tuple[float, float, float, float] | None
    calibration_warning: str | None
    counts: dict[str, int]
    reasons: dict[str, int]
    damage: str | None
    elapsed_s: float
    last_skip_reason: str = ""


def tf_rotation(
    transforms: list[Any], imu_frame: str | None, camera_frame: str
) -> tuple[float, float, float, float] | None:
    """camera_to_imu rotation from /tf_static transforms (rosbags TransformStamped): the
    transform IMU (parent) -> camera (child), or its inverse; None when absent."""

    def strip(name: str) -> str:
        return name.lstrip("/")

    cam = strip(camera_frame)
    imu = strip(imu_frame) if imu_frame else None
    for tf in transforms:
        parent, child = strip(tf.header.frame_id), strip(tf.child_frame_id)
        q = tf.transform.rotation
        xyzw = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
        if child == cam and (imu is None or parent == imu):
            return tuple(float(v) for v in xyzw / np.linalg.norm(xyzw))  # type: ignore[return-value]
        if parent == cam and imu is not None and child == imu:
            inv = quat_xyzw_to_matrix(xyzw / np.linalg.norm(xyzw)).T
            return tuple(float(v) for v in matrix_to_quat_xyzw(inv))  # type: ignore[return-value]
    return None


#: the message types each input role accepts.
ROLE_TYPES: dict[Role, tuple[str, ...]] = {
    Role.IMAGE: IMAGE_TYPES,
    Role.CAMERA_INFO: ("sensor_msgs/msg/CameraInfo",),
    Role.IMU: ("sensor_msgs/msg/Imu",),
    Role.SPEED: SPEED_TYPES,
}


def _check_topics(bag: BagReader, opts: ProcessOptions) -> dict[str, Role]:
    """topic -> role of the topics to read; ProcessError when one is missing or of the
    wrong type."""
    topics = bag.topics
    have = ", ".join(sorted(topics)) or "no topics"
    wanted = {Role.IMAGE: opts.image_topic, Role.CAMERA_INFO: opts.camera_info_topic}
    if opts.imu_topic:
        wanted[Role.IMU] = opts.imu_topic
    if opts.speed_topic:
        wanted[Role.SPEED] = opts.speed_topic
    expected = ROLE_TYPES
    for role, topic in wanted.items():
        if topic not in topics:
            hint = f" ({NO_IMU_HINT})" if role is Role.IMU else ""
            raise ProcessError(
                f"{role} topic {topic} is not in bag {bag.path} (has: {have}){hint}"
            )
        msgtype = topics[topic].msgtype
        if msgtype not in expected[role]:
            raise ProcessError(
                f"{role} topic {topic} has type {msgtype}, expected {' or '.join(expected[role])}"
            )
    return {topic: role for role, topic in wanted.items()}


#: no time estimate before this fraction of the messages and this many seconds: the first
#: frames pay for lazy imports and the engine's start, which the rate would extrapolate.
ETA_MIN_FRACTION = 0.1
ETA_MIN_S = 1.0


def eta_text(elapsed_s: float, fraction: float) -> str:
    """``", ~N s left"`` from the rate so far, or "" while that rate means little."""
    if fraction >= 1 or fraction < ETA_MIN_FRACTION or elapsed_s < ETA_MIN_S:
        return ""
    return f", ~{elapsed_s / fraction - elapsed_s:.0f} s left"


class _Progress:
    def __init__(self, stream: TextIO | None, total: int) -> None:
        self.stream = stream
        self.total = max(total, 1)
        self.tty = bool(stream is not None and stream.isatty())
        self.last = 0.0
        self.t0 = time.monotonic()

    def __call__(self, done: int, frames: int, force: bool = False) -> None:
        if self.stream is None:
            return
        now = time.monotonic()
        if not force and now - self.last < (0.2 if self.tty else 5.0):
            return
        self.last = now
        elapsed = now - self.t0
        frac = done / self.total
        bar = "#" * int(30 * frac)
        text = f"{PROG}: [{bar:<30}] {100 * frac:5.1f}%  {frames} frames  {elapsed:.1f} s"
        text += eta_text(elapsed, frac)
        self.stream.write(("\r" + text + "\x1b[K") if self.tty else text + "\n")
        if force and self.tty:
            self.stream.write("\n")
        self.stream.flush()


class _Run:
    """One owl_process run: feeds the bag's messages to the pipeline in log-time order and
    writes its outputs (the state process_bag's loop carries)."""

    def __init__(
        self,
        bag: BagReader,
        writer: BagWriter,
        opts: ProcessOptions,
        node_opts: NodeOptions,
        roles: dict[str, Role],
        copy: list[str],
    ) -> None:
        from rclpy.serialization import deserialize_message

        self.bag = bag
        self.writer = writer
        self.node_opts = node_opts
        self.roles = roles
        self.copy = set(copy)
        self.now_ns = bag.start_ns  # the pipeline's clock: the log time of the newest message
        self.pipeline = Pipeline(node_opts, clock=lambda: self.now_ns)
        self.classes = {t: message_class(bag.topics[t].msgtype) for t in roles}
        self.deserialize = deserialize_message
        self.transforms: list[Any] = []
        self.imu_frame: str | None = None
        self.extrinsic_source = "option" if not opts.rotation_from_tf else "default"
        self.rotation = opts.node.engine.camera_to_imu_rotation_xyzw
        self.decided = not opts.rotation_from_tf
        self.camera_frame: str | None = None  # of the first camera_info
        self.stamps: list[int] = []
        self.headings: list[npt.NDArray[np.float64]] = []
        self.sigmas: list[float] = []
        self.reasons: Counter[str] = Counter()
        self.undecodable: Counter[str] = Counter()
        self.points = 0
        self.frames = 0
        self.period_ns = round(node_opts.diagnostics_period_s * 1e9)
        self.next_diag: int | None = None
        self.dense = DenseWriter(node_opts, writer, serialize) if node_opts.dense else None

    def emit(self, outputs: list[Output]) -> None:
        """Write the pipeline's outputs (points, heading, its marker and covariance, gyro
        bias) at the image stamp."""
        for o in outputs:
            stamp = header_to_ns(o.header)
            self.frames += 1
            self.points += o.result.num_points
            if self.dense is not None:
                self.dense.write(o, self.pipeline.engine, self.pipeline.camera)
            self.writer.write(POINTS.bag, max(stamp, 0), o.cloud)
            if o.heading is not None and o.result.heading is not None:
                self.writer.write(HEADING.bag, max(stamp, 0), o.heading)
                marker = heading_marker(o.result.heading, o.header)
                self.writer.write(HEADING_MARKER.bag, max(stamp, 0), marker)
                self.stamps.append(stamp)
                self.headings.append(np.asarray(o.result.heading, dtype=np.float64))
                self.sigmas.append(float(o.result.heading_sigma_rad))
            if o.heading_cov is not None:
                self.writer.write(HEADING_COV.bag, max(stamp, 0), o.heading_cov)
            if o.gyro_bias is not None:
                self.writer.write(GYRO_BIAS.bag, max(stamp, 0), o.gyro_bias)
            if not o.result.num_points:
                for reason in o.result.reasons or ("no points",):
                    self.reasons[reason.split(" (")[0].split(":")[0]] += 1

    def diagnostics(self) -> None:
        """Write the pipeline's /diagnostics at the bag time now."""
        now_ns = self.now_ns
        if self.dense is not None:
            self.dense.flush()  # the status counts every frame handed over so far
        extra = [self.dense.stage.status()] if self.dense is not None else []
        msg = records_to_msg(self.pipeline.diagnostics() + extra, now_ns)
        self.writer.write(DIAGNOSTICS.bag, max(now_ns, 0), msg)

    def tf_static_rotation(self) -> tuple[float, float, float, float] | None:
        """The bag's /tf_static camera-to-IMU rotation from every transform read and the
        frames of the IMU and camera_info messages (None without one)."""
        if self.camera_frame is None:
            return None
        return tf_rotation(self.transforms, self.imu_frame, self.camera_frame)

    def _camera_info(self, msg: Any) -> None:
        if self.camera_frame is None:
            self.camera_frame = msg.header.frame_id
        if not self.decided:  # the first camera_info decides the extrinsic from /tf_static
            found = tf_rotation(self.transforms, self.imu_frame, msg.header.frame_id)
            if found is not None:
                self.rotation, self.extrinsic_source = found, "tf_static"
                self.pipeline.reconfigure(
                    self.node_opts.with_values({"camera_to_imu_rotation_xyzw": found})
                )
            self.decided = True
        self.pipeline.add_camera_info(msg)

    def _dispatch(self, raw: RawMessage, role: Role) -> None:
        try:
            msg = self.deserialize(raw.data, self.classes[raw.topic])
        except Exception:  # a damaged message: skip it, count it
            self.undecodable[raw.topic] += 1
            return
        if role is Role.IMU and self.imu_frame is None:
            self.imu_frame = msg.header.frame_id
        if role is Role.CAMERA_INFO:
            self._camera_info(msg)
        else:  # outputs of frames processed before an IMU time jump
            self.emit(self.pipeline.add(role, msg, raw.log_time_ns))

    def handle(self, raw: RawMessage) -> None:
        """One bag message: to the pipeline (or the tf buffer), copied when asked; then
        the pipeline's ready outputs and, every diagnostics period, its diagnostics."""
        now = self.now_ns = raw.log_time_ns
        role = self.roles.get(raw.topic)
        if raw.topic == TF_STATIC:  # all of them: the summary compares a given rotation
            try:
                self.transforms.extend(self.bag.deserialize(raw).transforms)
            except Exception:  # a damaged message: skip it, count it
                self.undecodable[raw.topic] += 1
        elif role is not None:
            self._dispatch(raw, role)
        if raw.topic in self.copy:
            self.writer.write_raw(raw.topic, now, raw.data)
        self.emit(self.pipeline.poll())
        if self.next_diag is None:
            self.next_diag = now + self.period_ns
        elif now >= self.next_diag:
            self.diagnostics()
            self.next_diag = now + self.period_ns


def _add_topics(
    writer: BagWriter, node_opts: NodeOptions, infos: dict[str, Any], copy: list[str]
) -> None:
    """The result topics, the copied input topics and the options, in the output bag."""
    for result_topic in RESULT_TOPICS:
        writer.add_topic(result_topic.bag, result_topic.msgtype, result_topic.qos)
    for topic in copy:
        if topic not in {t.bag for t in RESULT_TOPICS}:
            writer.add_topic(topic, infos[topic].msgtype, infos[topic].qos_kind)
    writer.set_custom_data(
        "owl_process", repr(sorted((k, v) for k, v in to_values(node_opts).items()))
    )


def process_bag(
    in_path: str | Path,
    out_path: str | Path,
    options: ProcessOptions | None = None,
    progress: Callable[[int, int, bool], None] | TextIO | None = None,
) -> Summary:
    """Run the OWL pipeline over a bag and write the results (see the module docstring).

    Args:
        in_path: input rosbag2 directory or .mcap file.
        out_path: output rosbag2 directory (MCAP).
        options: what to read and the node options.
        progress: a text stream for a progress bar (e.g. sys.stderr), or a callable
            ``(messages_done, frames_processed, final)``, or None.

    Returns:
        A :class:`Summary`. A truncated/corrupt input is processed up to the damage, the
        output written, and ``Summary.damage`` says what was wrong.

    Raises:
        BagError: input missing or not a bag, output exists (no overwrite).
        ProcessError: a topic missing from the bag or of the wrong type.
    """
    t_start = time.monotonic()
    opts = options if options is not None else ProcessOptions()
    out = Path(out_path)
    # refuse an existing output, or one that is/holds/lies inside the input, before reading
    BagWriter(out, overwrite=opts.overwrite, inputs=[in_path])
    with BagReader(in_path, recover=True) as bag:
        roles = _check_topics(bag, opts)
        infos = bag.topics
        read_topics = list(roles)
        if TF_STATIC in infos:  # also with a given rotation: the summary compares the two
            read_topics.append(TF_STATIC)
        copy = sorted(infos) if opts.copy_inputs else []
        total = sum(infos[t].count for t in set(read_topics) | set(copy))
        report = progress if callable(progress) else _Progress(progress, total)
        speed_source = "none"
        if opts.speed_topic:
            is_odom = infos[opts.speed_topic].msgtype == "nav_msgs/msg/Odometry"
            speed_source = "odometry" if is_odom else "twist"
        node_opts = replace(opts.node, speed_source=speed_source)
        damage: str | None = None
        done = 0
        with BagWriter(out, overwrite=opts.overwrite, inputs=[in_path]) as writer:
            _add_topics(writer, node_opts, infos, copy)
            run = _Run(bag, writer, opts, node_opts, roles, copy)
            last_ns = bag.start_ns
            try:
                try:
                    for raw in bag.messages(sorted(set(read_topics) | set(copy))):
                        run.handle(raw)
                        last_ns = raw.log_time_ns
                        done += 1
                        report(done, run.frames, False)
                except CorruptBagError as err:
                    damage = str(err)
                if damage is None and bag.damage is not None:
                    damage = f"truncated or corrupt bag {bag.path}: {bag.damage}"
                run.now_ns = last_ns
                run.emit(run.pipeline.poll(flush=True))
                run.diagnostics()
            finally:
                if run.dense is not None:
                    run.dense.close()  # the dense process ends with the run, even on error
            report(done, run.frames, True)
            totals = run.pipeline.totals.as_dict()
            totals.update({f"undecodable {t}": n for t, n in run.undecodable.items()})
    return Summary(
        out_path=out,
        images=totals.get("images", 0),
        frames_processed=run.frames,
        frames_with_points=totals.get("frames_with_points", 0),
        points=run.points,
        heading_stamps_ns=np.asarray(run.stamps, dtype=np.int64),
        headings=np.asarray(run.headings, dtype=np.float64).reshape(-1, 3),
        heading_sigma_rad=np.asarray(run.sigmas, dtype=np.float64),
        extrinsic_source=run.extrinsic_source,
        camera_to_imu_rotation_xyzw=tuple(float(v) for v in run.rotation),  # type: ignore[arg-type]
        tf_static_rotation_xyzw=run.tf_static_rotation(),
        calibration_warning=(
            verdict.message
            if (verdict := run.pipeline.calibration_verdict) is not None and verdict.disagrees
            else None
        ),
        counts=totals,
        reasons=dict(run.reasons),
        damage=damage,
        elapsed_s=time.monotonic() - t_start,
        last_skip_reason=run.pipeline.last_skip_reason,
    )


# ------------------------------------------------------------------------------ CLI


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    p = OneLineErrorParser(
        prog=PROG,
        description="Run the OWL pipeline of node 'owl' over a bag (no DDS, deterministic) "
        "and write owl/points, owl/heading and /diagnostics to an MCAP rosbag2.",
    )
    p.add_argument("in_bag", help="input rosbag2 directory or .mcap file")
    p.add_argument("-o", "--output", required=True, help="output rosbag2 directory")
    p.add_argument(
        "--image-topic",
        default=ProcessOptions.image_topic,
        help="Image or CompressedImage topic (default %(default)s)",
    )
    p.add_argument(
        "--camera-info-topic",
        default=ProcessOptions.camera_info_topic,
        help="CameraInfo topic (default %(default)s)",
    )
    p.add_argument(
        "--imu-topic",
        default=ProcessOptions.imu_topic,
        help="Imu topic (default %(default)s; '' = none)",
    )
    p.add_argument(
        "--speed-topic",
        default="",
        help="nav_msgs/Odometry or TwistStamped "
        "topic: x y z in metres (default: none, x y z in seconds)",
    )
    p.add_argument(
        "--camera-to-imu-rotation-xyzw",
        metavar="X,Y,Z,W",
        default=None,
        help="camera-to-IMU rotation quaternion, or [x, y, z, w] as owl_import and "
        "owl_calibrate print it (default: from /tf_static, else identity)",
    )
    p.add_argument(
        "--imu-time-offset",
        type=float,
        default=None,
        metavar="S",
        help="IMU stamp - camera stamp, seconds (default 0)",
    )
    p.add_argument(
        "--rolling-shutter-readout-s",
        type=float,
        default=None,
        metavar="S",
        help="rolling-shutter readout time (row 0 to the row after the last), seconds "
        "(default 0: global shutter); the same as -p rolling_shutter_readout_s:=S",
    )
    p.add_argument(
        "-p",
        "--param",
        action="append",
        default=[],
        metavar="NAME:=VALUE",
        help="any node parameter (see config/owl.yaml), repeatable",
    )
    p.add_argument("--params-file", default=None, help="ROS 2 parameter YAML (node 'owl')")
    p.add_argument(
        "--copy-inputs", action="store_true", help="copy every input topic into the output bag"
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def _params_file(path: str) -> dict[str, Any]:
    import yaml

    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as err:
        msg = f"cannot read --params-file {path}: {' '.join(str(err).split())}"
        raise ProcessError(msg) from None
    if not isinstance(data, dict):
        raise ProcessError(f"--params-file {path}: expected a mapping of node names")
    values: dict[str, Any] = {}
    for key in ("/**", "/**/owl", "owl", "/owl"):
        section = data.get(key)
        if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
            values.update(section["ros__parameters"])
    if not values:
        raise ProcessError(
            f"--params-file {path}: no '/**: ros__parameters:' or 'owl: ros__parameters:' section"
        )
    values.pop("use_sim_time", None)
    return values


def options_from_args(args: argparse.Namespace) -> ProcessOptions:
    """ProcessOptions from parsed arguments; ProcessError/ParameterError on bad values."""
    values: dict[str, Any] = {}
    rotation_given = False
    if args.params_file:
        values.update(_params_file(args.params_file))
        # a parameter file that keeps the default (identity) rotation does not override
        # /tf_static; one that sets another rotation does
        given = values.get("camera_to_imu_rotation_xyzw")
        rotation_given = given is not None and given != list(
            defaults()["camera_to_imu_rotation_xyzw"]
        )
    for item in args.param:
        name, values[name] = parse_assignment(item)
        rotation_given |= name == "camera_to_imu_rotation_xyzw"
    if args.camera_to_imu_rotation_xyzw is not None:
        try:
            # "x,y,z,w", or as a -p value "[x, y, z, w]"
            text = args.camera_to_imu_rotation_xyzw.strip().removeprefix("[").removesuffix("]")
            q = [float(v) for v in text.split(",")]
        except ValueError:
            raise ProcessError(
                "--camera-to-imu-rotation-xyzw must be 4 comma-separated numbers, got "
                f"{args.camera_to_imu_rotation_xyzw!r}"
            ) from None
        values["camera_to_imu_rotation_xyzw"] = q
        rotation_given = True
    if args.imu_time_offset is not None:
        values["imu_time_offset"] = args.imu_time_offset
    if args.rolling_shutter_readout_s is not None:
        values["rolling_shutter_readout_s"] = args.rolling_shutter_readout_s
    typos, _ = unknown_parameters(values)  # a typo in a parameter file: refused
    if typos:
        raise ParameterError(typos)
    node = build_options(values)
    return ProcessOptions(
        node=node,
        image_topic=args.image_topic,
        camera_info_topic=args.camera_info_topic,
        imu_topic=args.imu_topic,
        speed_topic=args.speed_topic,
        rotation_from_tf=not rotation_given,
        copy_inputs=args.copy_inputs,
        overwrite=args.overwrite,
    )


#: frames taken from the queue but not processed: counter key -> what the notes call it
_SKIPS = {
    Skip.NO_CAMERA_INFO.value: "no camera_info yet",
    Skip.BAD_IMAGE.value: "bad image",
    Skip.DUPLICATE_STAMP.value: "repeated stamp",
    Skip.OUT_OF_ORDER.value: "stamp out of order",
    Skip.ENGINE_ERROR.value: "engine error",
}


def summary_notes(summary: Summary, opts: ProcessOptions) -> list[str]:
    """Lines after a run: why frames had no points (counts per reason, one line), what to
    do about a missing IMU, images missing between the recorded stamps, and the identity
    extrinsic when none was given or found."""
    notes = []
    if summary.reasons:
        ranked = sorted(summary.reasons.items(), key=lambda kv: (-kv[1], kv[0]))
        without = summary.frames_processed - summary.frames_with_points
        text = ", ".join(f"{reason} {n}" for reason, n in ranked)
        notes.append(f"frames without points: {without} of {summary.frames_processed} ({text})")
        if not opts.imu_topic and opts.node.engine.require_gyro:
            notes.append(f"no IMU topic and require_gyro is true: {NO_IMU_HINT}")
        late = summary.counts.get("frames_imu_late", 0)
        if late:
            queue = opts.node.queue_size
            notes.append(
                f"{late} frames were processed before the IMU covering them arrived (it comes "
                f"later in the bag than the next image): keep them waiting with "
                f"-p queue_size:={max(2 * queue, 4)} (now {queue})"
            )
    for key, n in sorted(summary.counts.items()):
        if key.startswith("undecodable ") and n:
            topic = key.removeprefix("undecodable ")
            notes.append(f"warning: {n} messages on {topic} could not be read (skipped)")
    skipped = {k: n for k, n in summary.counts.items() if k in _SKIPS and n}
    if skipped:
        text = ", ".join(f"{_SKIPS[k]} {n}" for k, n in sorted(skipped.items()))
        last = f" (the last: {summary.last_skip_reason})" if summary.last_skip_reason else ""
        notes.append(f"warning: images not processed: {text}{last}")
    missing = summary.counts.get("images_missing", 0)
    if missing:
        notes.append(
            f"{missing} images missing between the recorded image stamps (lost before the "
            f"recorder: camera driver or transport; {summary.images} in the bag)"
        )
    if summary.extrinsic_source == "default":
        notes.append(
            "warning: no camera-IMU rotation given and none in /tf_static: used the identity; "
            + EXTRINSIC_HOWTO
        )
    tf = summary.tf_static_rotation_xyzw
    if summary.extrinsic_source == "option" and tf is not None:
        angle = rotation_angle_deg(summary.camera_to_imu_rotation_xyzw, tf)
        if angle > GIVEN_VS_TF_DEG:
            notes.append(
                f"warning: the camera-IMU rotation given is {angle:.1f} deg from the bag's "
                "/tf_static one (the given one was used; leave it out to use /tf_static)"
            )
    if summary.calibration_warning is not None:
        notes.append(f"warning: camera-IMU calibration: {summary.calibration_warning}")
    return notes


#: a given camera-IMU rotation farther than this from the bag's /tf_static is said, deg
GIVEN_VS_TF_DEG = 1.0


def rotation_angle_deg(a_xyzw: Sequence[float], b_xyzw: Sequence[float]) -> float:
    """Angle of the rotation between two quaternions (x, y, z, w), degrees (as
    owl_calibrate compares its estimate with /tf_static)."""
    ra = quat_xyzw_to_matrix(np.asarray(a_xyzw, dtype=np.float64))
    rb = quat_xyzw_to_matrix(np.asarray(b_xyzw, dtype=np.float64))
    return math.degrees(float(np.linalg.norm(so3_log(ra @ rb.T))))


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``owl_process``; returns the exit status."""
    args = build_parser().parse_args(argv)
    keep_freed_memory()
    one_blas_thread()
    try:
        opts = options_from_args(args)
    except ParameterError as err:
        for line in err.lines:
            print(f"{PROG}: error: {line}", file=sys.stderr)
        return 2
    except ProcessError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    try:
        summary = process_bag(
            args.in_bag, args.output, opts, progress=None if args.quiet else sys.stderr
        )
    except (BagError, ProcessError, ParameterError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted, nothing written", file=sys.stderr)
        return 130
    if summary.damage is not None:
        print(
            f"{PROG}: error: {summary.damage} (the {summary.frames_processed} frames before "
            f"the damage were written to {summary.out_path})",
            file=sys.stderr,
        )
        return 1
    for line in summary_notes(summary, opts):
        print(f"{PROG}: {line}", file=sys.stderr)
    if summary.frames_processed == 0:
        print(
            f"{PROG}: error: no frame processed of the {summary.images} images on "
            f"{opts.image_topic} (the output {summary.out_path} holds the diagnostics)",
            file=sys.stderr,
        )
        return 1
    if not args.quiet:
        print(
            f"{PROG}: wrote {summary.out_path}: {summary.frames_processed} frames, "
            f"{summary.frames_with_points} with points, {len(summary.headings)} headings, "
            f"{summary.points} points in {summary.elapsed_s:.1f} s (extrinsic from "
            f"{summary.extrinsic_source})",
            file=sys.stderr,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
