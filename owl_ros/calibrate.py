"""owl_calibrate BAG: camera-IMU rotation, time offset and gyro bias from a recording.

No calibration target and no ground truth: the rotation the images show from frame to
frame is aligned with the integrated gyro (``owl_core.calibration``). Reads the image
(raw or compressed), camera_info and IMU topics; prints the parameter lines with their
1-sigma uncertainties, and with ``-o FILE`` writes a ROS 2 parameter file for node
``owl`` in any namespace (``/**: ros__parameters: ...``) usable with ``--params-file``
by ``owl_node`` and ``owl_process`` (checked before calibrating: an existing file only
with ``--overwrite``, never the input bag or a file inside it, in an existing directory;
written all at once, see :func:`bags.io.write_text_atomic`). When the bag has
``/tf_static``, also prints the angle between its camera-IMU rotation and the estimate. A
recording whose rotation does not excite two axes is refused in one line (exit 3) that
says what motion to record.

Exit status: 0 done, 1 bad bag / calibration impossible, 2 bad command line,
3 not excited (record again).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bags.cli import OneLineErrorParser
from bags.errors import BagError
from bags.io import BagReader, check_output, write_text_atomic
from msg_adapters.camera_info import camera_info_to_model
from msg_adapters.errors import AdapterError
from msg_adapters.image import compressed_to_frame, image_to_frame
from msg_adapters.imu import imus_to_gyro
from owl_core import calibration as cal
from owl_core.camera import CameraModel
from owl_core.errors import OwlError
from owl_core.geometry import quat_xyzw_to_matrix, so3_log
from owl_core.types import GyroSamples, ImageFrame
from owl_ros.process import ROLE_TYPES, TF_STATIC, ProcessOptions, tf_rotation
from owl_ros.roles import Role

PROG = "owl_calibrate"


class CalibrateError(Exception):
    """Bad input for owl_calibrate (one line naming the topic, path or value)."""


@dataclass(frozen=True)
class BagCalibration:
    """What :func:`calibrate_bag` found.

    Attributes:
        result: the estimate and its uncertainties.
        frames: images read.
        seconds: recording length covered by the images, s.
        tf_angle_deg: angle between the estimate and /tf_static's rotation, degrees
            (None when the bag has none).
        tf_rotation_xyzw: /tf_static's camera-to-IMU rotation (None when absent).
        elapsed_s: CPU time of the whole run (decode, track, fit), s.
    """

    result: cal.CalibrationResult
    frames: int
    seconds: float
    tf_angle_deg: float | None
    tf_rotation_xyzw: tuple[float, float, float, float] | None
    elapsed_s: float


def _read(
    path: str | Path, image_topic: str, info_topic: str, imu_topic: str
) -> tuple[list[ImageFrame], CameraModel, GyroSamples, tuple[float, ...] | None]:
    """Decode the bag's images, camera model, gyro samples and /tf_static rotation.

    Each topic's message type is checked before anything is read (image: Image or
    CompressedImage, camera_info: CameraInfo, imu: Imu); a message the adapters refuse
    (e.g. an unsupported image encoding) is a CalibrateError naming its topic.
    """
    with BagReader(path) as bag:
        topics = bag.topics
        have = ", ".join(sorted(topics)) or "no topics"
        for role, topic in ((Role.IMAGE, image_topic), (Role.CAMERA_INFO, info_topic)):
            if topic not in topics:
                raise CalibrateError(f"{role} topic {topic} is not in bag {path} (has: {have})")
        if imu_topic not in topics:
            raise CalibrateError(
                f"imu topic {imu_topic} is not in bag {path} (has: {have}): owl_calibrate "
                "needs the gyro"
            )
        roles = {Role.IMAGE: image_topic, Role.CAMERA_INFO: info_topic, Role.IMU: imu_topic}
        for role, topic in roles.items():
            msgtype = topics[topic].msgtype
            if msgtype not in ROLE_TYPES[role]:
                raise CalibrateError(
                    f"{role} topic {topic} has type {msgtype}, expected "
                    f"{' or '.join(ROLE_TYPES[role])}"
                )
        compressed = topics[image_topic].msgtype.endswith("CompressedImage")
        read = [image_topic, info_topic, imu_topic]
        if TF_STATIC in topics:
            read.append(TF_STATIC)
        frames: list[ImageFrame] = []
        imus: list[Any] = []
        transforms: list[Any] = []
        camera: CameraModel | None = None
        camera_frame = ""
        imu_frame: str | None = None
        last = -1
        for raw in bag.messages(read):
            msg = bag.deserialize(raw)
            if raw.topic == imu_topic:
                if imu_frame is None:
                    imu_frame = msg.header.frame_id
                imus.append(msg)
            elif raw.topic == info_topic:
                if camera is None:
                    try:
                        camera = camera_info_to_model(msg)
                    except AdapterError as err:
                        raise CalibrateError(f"camera_info topic {info_topic}: {err}") from None
                    camera_frame = msg.header.frame_id
            elif raw.topic == TF_STATIC:
                transforms.extend(msg.transforms)
            else:
                try:
                    frame = compressed_to_frame(msg) if compressed else image_to_frame(msg)
                except AdapterError as err:
                    raise CalibrateError(f"image topic {image_topic}: {err}") from None
                if frame.stamp_ns > last:  # repeated or backwards stamps are skipped
                    frames.append(frame)
                    last = frame.stamp_ns
    if camera is None:
        raise CalibrateError(f"camera_info topic {info_topic} has no messages")
    if len(imus) < 2:
        raise CalibrateError(f"imu topic {imu_topic} has {len(imus)} messages (need >= 2)")
    try:
        gyro = imus_to_gyro(imus)
    except AdapterError as err:
        raise CalibrateError(f"imu topic {imu_topic}: {err}") from None
    tf = tf_rotation(transforms, imu_frame, camera_frame) if transforms else None
    return frames, camera, gyro, tf


def calibrate_bag(
    path: str | Path,
    options: cal.CalibrationOptions | None = None,
    image_topic: str = ProcessOptions.image_topic,
    camera_info_topic: str = ProcessOptions.camera_info_topic,
    imu_topic: str = ProcessOptions.imu_topic,
) -> BagCalibration:
    """Estimate the camera-IMU rotation, time offset and gyro bias of a bag.

    Raises:
        BagError: not a bag. CalibrateError: a topic missing, empty, of the wrong message
            type or holding a message the adapters refuse (e.g. an image encoding).
        owl_core.calibration.NotExcitedError: the motion does not excite two axes.
        owl_core.errors.CalibrationError: too few usable frames, no gyro overlap.
    """
    t0 = time.process_time()
    frames, camera, gyro, tf = _read(path, image_topic, camera_info_topic, imu_topic)
    if len(frames) < 2:
        raise CalibrateError(f"image topic {image_topic} has {len(frames)} frames (need >= 2)")
    for frame in frames:
        if frame.image.shape != (camera.height, camera.width):
            raise CalibrateError(
                f"image size {frame.image.shape[1]}x{frame.image.shape[0]} does not match "
                f"camera_info {camera.width}x{camera.height}"
            )
    opts = options if options is not None else cal.CalibrationOptions()
    rot = cal.track_rotations(frames, camera, opts)
    result = cal.calibrate(rot, gyro, opts)
    angle = None
    if tf is not None:
        r_tf = quat_xyzw_to_matrix(np.asarray(tf))
        angle = math.degrees(float(np.linalg.norm(so3_log(result.camera_to_imu @ r_tf.T))))
    seconds = (frames[-1].stamp_ns - frames[0].stamp_ns) * 1e-9
    return BagCalibration(
        result,
        len(frames),
        seconds,
        angle,
        tf,  # type: ignore[arg-type]
        time.process_time() - t0,
    )


def _fmt(values: Sequence[float], digits: int = 6) -> str:
    return "[" + ", ".join(f"{v:.{digits}f}" for v in values) + "]"


def parameter_lines(found: BagCalibration) -> list[str]:
    """The ``NAME:=VALUE  # 1-sigma`` lines (``-p`` syntax of owl_process / ros2 run)."""
    r = found.result
    sig_deg = np.degrees(r.rotation_sigma_rad)
    return [
        f"camera_to_imu_rotation_xyzw:={_fmt(r.camera_to_imu_xyzw)}"
        f"  # 1-sigma about IMU x y z: {_fmt(sig_deg, 3)} deg",
        f"imu_time_offset:={r.time_offset_s:.5f}  # 1-sigma {r.time_offset_sigma_s * 1e3:.2f} ms",
        f"initial_bias_imu:={_fmt(r.gyro_bias)}  # 1-sigma {_fmt(r.gyro_bias_sigma)} rad/s",
    ]


def params_yaml(found: BagCalibration, source: str) -> str:
    """A ROS 2 parameter file for node ``owl`` holding the three estimates."""
    r = found.result
    sig_deg = np.degrees(r.rotation_sigma_rad)
    lines = [
        f"# Written by {PROG} from {source}: {found.frames} frames, {found.seconds:.1f} s,",
        f"# {r.intervals_used} frame intervals fitted. Load with --params-file ('/**': the",
        "# node in any namespace).",
        "/**:",
        "  ros__parameters:",
        f"    # 1-sigma of the rotation about IMU x y z: {_fmt(sig_deg, 3)} deg",
        f"    camera_to_imu_rotation_xyzw: {_fmt(r.camera_to_imu_xyzw)}",
        f"    # IMU stamp - camera stamp, s; 1-sigma {r.time_offset_sigma_s * 1e3:.2f} ms",
        f"    imu_time_offset: {r.time_offset_s:.6f}",
        f"    # gyro bias, IMU frame, rad/s; 1-sigma {_fmt(r.gyro_bias_sigma)}",
        f"    initial_bias_imu: {_fmt(r.gyro_bias)}",
    ]
    return "\n".join(lines) + "\n"


def check_params_output(output: str | os.PathLike[str], bag: str, overwrite: bool) -> None:
    """Refuse ``-o`` before calibrating: the input bag itself or a path inside it (even with
    ``overwrite``: replacing it would destroy the recording), an existing file without
    ``overwrite``, a directory, or a file in a directory that does not exist.

    Raises:
        OutputOverlapError: the output is, is inside or contains the input ``bag``.
        BagExistsError: the output exists and ``overwrite`` is False.
        CalibrateError: the output is a directory, or its directory does not exist.
    """
    out = Path(output)
    check_output(out, [bag], overwrite=overwrite)
    if out.is_dir():
        raise CalibrateError(f"output {out} is a directory (give a file name for the YAML)")
    if not out.parent.is_dir():
        raise CalibrateError(f"output directory {out.parent} does not exist (for {out})")


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    p = OneLineErrorParser(
        prog=PROG,
        description="Estimate camera_to_imu_rotation_xyzw, imu_time_offset and the gyro bias "
        "from a recording with images and IMU (no calibration target): turn the camera "
        "about at least two axes while recording.",
    )
    p.add_argument("bag", help="input rosbag2 directory or .mcap file")
    p.add_argument("-o", "--output", default=None, help="write a --params-file YAML here")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --output")
    p.add_argument("--image-topic", default=ProcessOptions.image_topic, help="%(default)s")
    p.add_argument(
        "--camera-info-topic", default=ProcessOptions.camera_info_topic, help="%(default)s"
    )
    p.add_argument("--imu-topic", default=ProcessOptions.imu_topic, help="%(default)s")
    p.add_argument(
        "--max-offset",
        type=float,
        default=cal.CalibrationOptions.max_offset_s,
        metavar="S",
        help="search the time offset within +-S seconds (default %(default)s)",
    )
    p.add_argument(
        "--max-features",
        type=int,
        default=cal.CalibrationOptions.max_features,
        help="features tracked per frame (default %(default)s)",
    )
    p.add_argument(
        "--min-second-axis-rate",
        type=float,
        default=cal.CalibrationOptions.min_second_axis_rate,
        metavar="RAD_S",
        help="refuse when the RMS rate about the second rotation axis is below this "
        "(default %(default)s rad/s)",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="only the parameter lines")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``owl_calibrate``; returns the exit status."""
    args = build_parser().parse_args(argv)
    out = Path(args.output) if args.output else None
    try:
        if out is not None:  # before the (long) calibration
            check_params_output(out, args.bag, args.overwrite)
        opts = cal.CalibrationOptions(
            max_offset_s=args.max_offset,
            max_features=args.max_features,
            min_second_axis_rate=args.min_second_axis_rate,
        )
    except (BagError, CalibrateError, OwlError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    try:
        found = calibrate_bag(
            args.bag, opts, args.image_topic, args.camera_info_topic, args.imu_topic
        )
    except cal.NotExcitedError as err:
        print(f"{PROG}: not excited: {err}", file=sys.stderr)
        return 3
    except (BagError, CalibrateError, OwlError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted, nothing written", file=sys.stderr)
        return 130
    for line in parameter_lines(found):
        print(line)
    r = found.result
    if not args.quiet:
        if found.tf_angle_deg is not None:
            print(f"# angle to /tf_static's rotation: {found.tf_angle_deg:.3f} deg")
        rates = ", ".join(f"{v:.3f}" for v in r.rms_rates)
        print(
            f"# {found.frames} frames over {found.seconds:.1f} s, {r.intervals_used} intervals "
            f"fitted; RMS rate about the principal axes {rates} rad/s; whitened residual "
            f"RMS {r.residual_rms:.2f}; {found.elapsed_s:.1f} s CPU"
        )
    if out is not None:
        try:
            check_params_output(out, args.bag, args.overwrite)  # it may have changed meanwhile
            write_text_atomic(out, params_yaml(found, Path(args.bag).name))
        except (BagError, CalibrateError) as err:
            print(f"{PROG}: error: {err}", file=sys.stderr)
            return 2
        except OSError as err:
            print(f"{PROG}: error: cannot write {out}: {err.strerror or err}", file=sys.stderr)
            return 1
        if not args.quiet:
            print(f"# wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
