"""owl_make_bag SCENARIO OUT_BAG: render a synthetic scenario with ground truth to a bag.

The bag is a rosbag2 directory (metadata.yaml + .mcap) with:

============================  ===============================  =========================
topic                         type                             content
============================  ===============================  =========================
/camera/image_raw             sensor_msgs/msg/Image            mono8 or rgb8
/camera/camera_info           sensor_msgs/msg/CameraInfo       plumb_bob (D zeros if none)
/imu/data                     sensor_msgs/msg/Imu              frame imu_link, REP 145
/tf_static                    tf2_msgs/msg/TFMessage           imu_link -> camera_optical_frame
/ground_truth/twist           geometry_msgs/msg/TwistStamped   camera frame, image stamps
/ground_truth/range           sensor_msgs/msg/Image            32FC1 metres (+inf = sky)
/ground_truth/moving_mask     sensor_msgs/msg/Image            mono8, 255 = moving (mover)
============================  ===============================  =========================

Camera messages are logged at their image stamps, IMU messages at their IMU stamps
(camera stamp + ``--time-offset``). ``/tf_static`` is recorded with transient-local QoS.
``metadata.yaml`` ``custom_data`` holds the scenario name and every option as JSON
(key ``owl_make_bag``).

Rolling shutter (``--rolling-shutter-readout T``, seconds): row v of each image is rendered
at its own time, image stamp + (v / height) x T (the stamp is the time of row 0, as
``rolling_shutter_readout_s`` of node ``owl`` assumes). ``/ground_truth/twist`` is the
camera's at the stamp; ``/ground_truth/range`` holds, per pixel, the distance from the
camera centre at the stamp to the scene point the pixel sees (at its row's time): the
snapshot at the stamp the engine's outputs refer to. The IMU runs T past the last frame.

Gyro bias (``--gyro-bias``, IMU frame, rad/s): one number B is a bias of magnitude B along
``(1, 1, 1)/sqrt(3)`` (each axis B/sqrt(3)); three comma-separated numbers are the vector.

Run ``python -m bags.cli.make_bag --help`` (console script ``owl_make_bag``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from geometry_msgs.msg import TwistStamped

from bags import layout
from bags.cli import OneLineErrorParser
from bags.errors import BagError, ScenarioError
from bags.io import BagWriter, typestore
from bags.sim import scenarios
from bags.sim.scenarios import CAMERA_FRAME, IMU_FRAME, Frame, SimOptions, Simulation
from bags.sim.sensors import ImuOptions
from msg_adapters.camera_info import camera_model_to_info
from msg_adapters.image import array_to_image
from msg_adapters.imu import gyro_to_imus
from msg_adapters.stamps import make_header
from owl_core.errors import OwlError
from owl_core.types import GyroSamples

PROG = "owl_make_bag"
#: A moderate barrel distortion for ``--distortion barrel`` (plumb_bob k1 k2 p1 p2 k3).
BARREL = (-0.25, 0.07, 0.0005, -0.0003, 0.0)

#: The synthetic bag's topics (the standard layout without the gyro-bias truth).
TOPICS = layout.subset("image", "info", "imu", "tf", "twist", "range", "mask")


def _floats(text: str, name: str, sizes: tuple[int, ...]) -> tuple[float, ...]:
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        msg = f"{name} must be comma-separated numbers, got {text!r}"
        raise argparse.ArgumentTypeError(msg) from None
    if len(values) not in sizes or not all(math.isfinite(v) for v in values):
        msg = f"{name} needs {' or '.join(map(str, sizes))} finite numbers, got {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return values


def _gyro_bias(text: str) -> tuple[float, float, float]:
    v = _floats(text, "--gyro-bias", (1, 3))
    if len(v) == 1:
        b = v[0] / math.sqrt(3.0)
        return (b, b, b)
    return (v[0], v[1], v[2])


def _distortion(text: str) -> tuple[float, ...]:
    if text == "none":
        return ()
    if text == "barrel":
        return BARREL
    return _floats(text, "--distortion", (5,))


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    p = OneLineErrorParser(
        prog=PROG,
        description="Render a synthetic OWL scenario (images, IMU, ground truth) to a rosbag2 "
        "MCAP directory. Scenarios: " + ", ".join(scenarios.names()) + " (see --list).",
    )
    p.add_argument("scenario", nargs="?", help="scenario name (see --list)")
    p.add_argument("out_bag", nargs="?", help="output rosbag2 directory (must not exist)")
    p.add_argument("--list", action="store_true", help="list the scenarios and exit")
    p.add_argument("--seconds", type=float, default=3.0, help="duration, s (default 3)")
    p.add_argument("--rate", type=float, default=30.0, help="camera frame rate, Hz (default 30)")
    p.add_argument("--width", type=int, default=640, help="image width, px (default 640)")
    p.add_argument("--height", type=int, default=480, help="image height, px (default 480)")
    p.add_argument("--hfov", type=float, default=70.0, help="horizontal FOV, deg (default 70)")
    p.add_argument("--seed", type=int, default=0, help="seed of image and IMU noise (default 0)")
    p.add_argument("--noise", type=float, default=2.0, help="image noise sigma, grey levels")
    p.add_argument("--scale", type=float, default=None, help="scene/path scale (see --list)")
    p.add_argument("--supersample", type=int, default=2, help="edge sub-samples per axis (1-4)")
    p.add_argument("--encoding", choices=("mono8", "rgb8"), default="mono8", help="image encoding")
    p.add_argument(
        "--distortion",
        type=_distortion,
        default=(),
        metavar="none|barrel|K1,K2,P1,P2,K3",
        help="plumb_bob lens distortion (default none)",
    )
    p.add_argument("--imu-rate", type=float, default=400.0, help="IMU rate, Hz (default 400)")
    p.add_argument(
        "--gyro-bias",
        type=_gyro_bias,
        default=(0.0, 0.0, 0.0),
        metavar="B|BX,BY,BZ",
        help="constant gyro bias, IMU frame, rad/s: one number = magnitude along (1,1,1)/sqrt(3), "
        "three = the vector (default 0)",
    )
    p.add_argument(
        "--gyro-noise", type=float, default=0.001, help="gyro white noise per sample, rad/s"
    )
    p.add_argument(
        "--gyro-bias-walk", type=float, default=0.0, help="gyro bias random walk, rad/s/sqrt(s)"
    )
    p.add_argument(
        "--accel-noise", type=float, default=0.02, help="accelerometer noise per sample, m/s^2"
    )
    p.add_argument(
        "--time-offset",
        type=float,
        default=0.0,
        help="IMU stamp - camera stamp for simultaneous events, s (default 0)",
    )
    p.add_argument(
        "--rolling-shutter-readout",
        type=float,
        default=0.0,
        metavar="T",
        help="rolling-shutter readout time, s: row v seen at stamp + (v / height) T "
        "(default 0: global shutter)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    return p


def _image_msg(ns: int, array: np.ndarray, encoding: str) -> Any:
    if encoding == "32FC1":
        array = array.astype(np.float32)
    return array_to_image(array, encoding, header=make_header(ns, CAMERA_FRAME))


def camera_info_msg(ns: int, sim: Simulation) -> Any:
    """sensor_msgs/CameraInfo of the simulated camera (plumb_bob; D zeros if undistorted)."""
    return camera_model_to_info(sim.camera, header=make_header(ns, CAMERA_FRAME))


def imu_msgs(sim: Simulation) -> Iterator[tuple[int, Any]]:
    """(stamp_ns, sensor_msgs/Imu) for every IMU sample (no orientation: covariance[0] = -1)."""
    imu = sim.imu
    o = sim.imu_options
    msgs = gyro_to_imus(
        GyroSamples(imu.stamp_ns, imu.angular_velocity),
        IMU_FRAME,
        linear_acceleration=imu.linear_acceleration,
        angular_velocity_covariance=np.diag([o.gyro_noise**2] * 3).reshape(-1),
        linear_acceleration_covariance=np.diag([o.accel_noise**2] * 3).reshape(-1),
    )
    yield from zip(imu.stamp_ns.tolist(), msgs, strict=True)


def tf_static_msg(ns: int, sim: Simulation) -> Any:
    """The IMU -> camera optical frame transform (rotation = camera_to_imu_rotation_xyzw).

    A rosbags message: tf2_msgs has no rclpy wheel on PyPI, so this one message is built
    with the typestore (msg_adapters builds the others).
    """
    ts = typestore().types
    q = sim.camera_to_imu_xyzw
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    stamp = ts["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    tr = ts["geometry_msgs/msg/Transform"](
        translation=ts["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        rotation=ts["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )
    stamped = ts["geometry_msgs/msg/TransformStamped"](
        header=ts["std_msgs/msg/Header"](stamp=stamp, frame_id=IMU_FRAME),
        child_frame_id=CAMERA_FRAME,
        transform=tr,
    )
    return ts["tf2_msgs/msg/TFMessage"](transforms=[stamped])


def twist_msg(frame: Frame) -> Any:
    """Ground-truth camera twist (camera optical frame) at the image stamp."""
    msg = TwistStamped(header=make_header(frame.stamp_ns, CAMERA_FRAME))
    t = msg.twist
    t.linear.x, t.linear.y, t.linear.z = (float(v) for v in frame.velocity)
    t.angular.x, t.angular.y, t.angular.z = (float(v) for v in frame.omega)
    return msg


def write_bag(
    sim: Simulation,
    out: str | Path,
    *,
    overwrite: bool = False,
    progress: bool = False,
    custom: dict[str, str] | None = None,
) -> int:
    """Render ``sim`` into the bag ``out``; returns the number of messages written.

    Messages are written in log-time order. On any exception nothing is left at ``out``.
    """
    encoding = sim.options.encoding
    has_mask = bool(sim.scenario.movers)
    t_start = time.monotonic()
    n_frames = sim.options.num_frames
    with BagWriter(out, overwrite=overwrite) as bag:
        for key, (topic, msgtype, qos) in TOPICS.items():
            if key != "mask" or has_mask:
                bag.add_topic(topic, msgtype, qos)
        for k, v in (custom or {}).items():
            bag.set_custom_data(k, v)
        first = min(int(sim.imu.stamp_ns[0]), int(sim.frame_stamps_ns[0]))
        bag.write(TOPICS["tf"][0], first, tf_static_msg(first, sim))
        imu_iter = imu_msgs(sim)
        pending = next(imu_iter, None)
        for frame in sim.frames():
            while pending is not None and pending[0] <= frame.stamp_ns:
                bag.write(TOPICS["imu"][0], pending[0], pending[1])
                pending = next(imu_iter, None)
            ns = frame.stamp_ns
            bag.write(TOPICS["image"][0], ns, _image_msg(ns, frame.image, encoding))
            bag.write(TOPICS["info"][0], ns, camera_info_msg(ns, sim))
            bag.write(TOPICS["twist"][0], ns, twist_msg(frame))
            bag.write(TOPICS["range"][0], ns, _image_msg(ns, frame.range_m, "32FC1"))
            if has_mask:
                mask = np.where(frame.mask, 255, 0).astype(np.uint8)
                bag.write(TOPICS["mask"][0], ns, _image_msg(ns, mask, "mono8"))
            if progress:
                elapsed = time.monotonic() - t_start
                done = frame.index + 1
                if done == n_frames or done % max(1, n_frames // 10) == 0:
                    eta = elapsed / done * (n_frames - done)
                    print(
                        f"{PROG}: {sim.scenario.name}: frame {done}/{n_frames}, "
                        f"{elapsed:.1f} s elapsed, ~{eta:.1f} s left",
                        file=sys.stderr,
                        flush=True,
                    )
        while pending is not None:
            bag.write(TOPICS["imu"][0], pending[0], pending[1])
            pending = next(imu_iter, None)
        return bag.count


def options_from_args(args: argparse.Namespace) -> SimOptions:
    """SimOptions from parsed arguments (raises ScenarioError on impossible values)."""
    imu = ImuOptions(
        rate_hz=args.imu_rate,
        gyro_noise=args.gyro_noise,
        gyro_bias=args.gyro_bias,
        gyro_bias_walk=args.gyro_bias_walk,
        accel_noise=args.accel_noise,
        time_offset_s=args.time_offset,
    )
    return SimOptions(
        seconds=args.seconds,
        rate_hz=args.rate,
        width=args.width,
        height=args.height,
        hfov_deg=args.hfov,
        distortion=tuple(args.distortion),
        encoding=args.encoding,
        seed=args.seed,
        noise_sigma=args.noise,
        supersample=args.supersample,
        scale=args.scale,
        imu=imu,
        rolling_shutter_readout_s=args.rolling_shutter_readout,
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``owl_make_bag``; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as done:  # --help, or a usage error already printed on one line
        return done.code if isinstance(done.code, int) else 2
    if args.list:
        width = max(len(n) for n in scenarios.names())
        for name, text in scenarios.DESCRIPTIONS.items():
            print(f"{name:<{width}}  {text}")
        return 0
    if not args.scenario or not args.out_bag:
        print(f"{PROG}: error: need SCENARIO and OUT_BAG (or --list)", file=sys.stderr)
        return 2
    try:
        scenario = scenarios.get(args.scenario)
        options = options_from_args(args)
        sim = scenario.simulate(options)
        custom = {
            "owl_make_bag": json.dumps(
                {
                    "scenario": args.scenario,
                    "scale": sim.scale,
                    **{k: v for k, v in vars(args).items() if k not in ("list", "quiet")},
                },
                sort_keys=True,
            )
        }
        BagWriter(args.out_bag, overwrite=args.overwrite)  # refuse early, before rendering
        t0 = time.monotonic()
        count = write_bag(
            sim, args.out_bag, overwrite=args.overwrite, progress=not args.quiet, custom=custom
        )
    except (ScenarioError, OwlError) as err:  # a bad option value
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    except BagError as err:  # the output exists / cannot be written: as every tool, 1
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted, nothing written", file=sys.stderr)
        return 130
    if not args.quiet:
        print(
            f"{PROG}: wrote {args.out_bag}: {options.num_frames} frames, {len(sim.imu.stamp_ns)} "
            f"IMU samples, {count} messages in {time.monotonic() - t0:.1f} s",
            file=sys.stderr,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
