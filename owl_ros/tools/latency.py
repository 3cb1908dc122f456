"""owl_latency: image-in to cloud-out latency, throughput, CPU and RSS of a live ``owl_node``.

Renders a scenario once (in memory; by default as long as the run, see
:func:`clip_seconds`), starts ``owl_node`` in its own process on a private ROS domain, and
publishes the clip (looped when shorter than the run) over real DDS at wall-clock pace with header
stamps = the wall-clock publication time (camera_info and IMU alongside, IMU at its own
rate, stamps shifted each loop so time only moves forward). A subscriber in this process
takes the arrival time of each ``owl/points`` cloud minus its header stamp: the latency
from image publication to cloud reception, DDS included. ``--speed`` plays the clip faster
(stamps compressed and gyro rates scaled to stay consistent) to find the highest input
rate the node keeps up with. CPU (all threads of the node process) and RSS come from
``/proc``.

    python -m owl_ros.tools.latency --width 640 --height 480 --rate 30 --seconds 10
    python -m owl_ros.tools.latency --speed 1 1.5 2 3    # 30, 45, 60, 90 Hz input
    python -m owl_ros.tools.latency --case vga30 --case vga60 --case hd30 --runs 3

``--case`` selects a standard input (size, rate, features) and its real-time targets
(:data:`CASES`); each run's line says which targets it meets, and with ``--runs N`` a last
line per case gives the medians over the runs. ``--max-features N`` measures a case with N
features instead (the other settings of the node with ``-p NAME:=VALUE``):

    python -m owl_ros.tools.latency --case vga30 --runs 3 --max-features 500 \
        -p tracker_lk_deformation_correction:=false

The publishing side uses :mod:`bags.dds`'s Fast DDS profile (a 16 MiB shared-memory
segment, as a camera driver publishing 720p should; ``--default-transport`` measures
without it). Each result also says where frames were lost: ``node_images`` against
``counted_sent`` (before the node's callback: transport), ``node_dropped_queue`` (the node
was busy), and ``publish_late_ms_p95`` (this tool's own publisher falling behind).

``measure(...)`` returns a :class:`Measurement` for reuse by the benchmark.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bags.cli import OneLineErrorParser
from bags.dds import prefer_large_image_profile
from owl_ros.tools.live import LiveNode

PROG = "owl_latency"
#: measure()'s default warm-up before the window, s.
WARMUP_S = 2.0
#: The node figures read from ``/diagnostics``: three counters and the engine time (see
#: :class:`Measurement`).
_DIAGNOSTIC_KEYS = (
    "images_total",
    "dropped_queue_full_total",
    "frames_processed_total",
    "processing_ms_mean",
)
#: Wait after the window for the node's next diagnostics (published at 1 Hz), s.
_DIAGNOSTICS_WAIT_S = 1.5


@dataclass(frozen=True)
class LatencyCase:
    """A standard input of the live node and the targets it should meet.

    Attributes:
        width, height: image size, px. rate_hz: camera rate, Hz. max_features: count.
        min_kept_up: fraction of frames that must get a cloud.
        max_p95_ms: latency p95 bound, ms (None: no bound).
        max_cpu_percent: node CPU bound, % of one core (None: no bound).
    """

    width: int
    height: int
    rate_hz: float
    max_features: int
    min_kept_up: float
    max_p95_ms: float | None = None
    max_cpu_percent: float | None = None


#: The standard inputs: VGA at 30 and 60 Hz, 720p at 30 Hz (a common robot camera).
CASES = {
    "vga30": LatencyCase(640, 480, 30.0, 1000, 0.995, 33.0, 60.0),
    "vga60": LatencyCase(640, 480, 60.0, 1000, 0.99, 25.0),
    "hd30": LatencyCase(1280, 720, 30.0, 1000, 0.99),
}


@dataclass(frozen=True)
class Measurement:
    """One run of the node at one input rate.

    Attributes:
        input_rate_hz: image rate published, Hz.
        width, height: image size, px. max_features: node parameter.
        images_sent: images published during the measurement window.
        clouds: clouds received for them.
        kept_up: clouds / images (1.0 = every frame processed).
        latency_ms_p50, latency_ms_p95, latency_ms_max: publication -> reception, ms.
        cpu_percent: node CPU time (with its dense process) / wall time over the window,
            % of one core.
        rss_mb: node resident set size at the end (with its dense process), MiB.
        points_per_cloud: mean points per non-empty cloud.
        counted_sent: images published between the node's first ``/diagnostics`` in the
            window and its last one (the span its counters below cover).
        node_images: images the node received in that span (its ``images_total``);
            fewer than ``counted_sent``: lost in transport.
        node_dropped_queue: of those, dropped from its full newest-wins queue (the node
            was busy: ``dropped_queue_full_total``).
        node_processed: frames it processed in that span (``frames_processed_total``).
        node_engine_ms: the node's engine wall time per processed frame (median over the
            window's ``/diagnostics`` of its ``processing_ms_mean``), ms; against the
            frame interval it says whether the engine or the rest of the node is short.
        publish_late_ms_p95: p95 of how late this tool published an image after its
            stamp (its own loop falling behind; included in the latency), ms.
        images_per_frame: of each ``image_topics`` topic (e.g. a dense output), the
            messages received for the window's images per image sent (1.0: one for
            every frame); empty without ``image_topics``.
    """

    input_rate_hz: float
    width: int
    height: int
    max_features: int
    images_sent: int
    clouds: int
    kept_up: float
    latency_ms_p50: float
    latency_ms_p95: float
    latency_ms_max: float
    cpu_percent: float
    rss_mb: float
    points_per_cloud: float
    counted_sent: int = -1
    node_images: int = -1
    node_dropped_queue: int = -1
    node_processed: int = -1
    node_engine_ms: float = float("nan")
    publish_late_ms_p95: float = float("nan")
    images_per_frame: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class _Clip:
    images: list[tuple[int, Any]]  # (stamp offset ns, sensor_msgs/Image)
    imus: list[tuple[int, Any, np.ndarray]]  # (stamp offset ns, Imu, rate (3,))
    info: Any
    duration_ns: int
    rotation: tuple[float, float, float, float]


def render_clip(scenario: str, seconds: float, width: int, height: int, rate: float) -> _Clip:
    """Render ``scenario`` into rclpy messages with stamps relative to the first frame."""
    from bags.sim import scenarios
    from bags.sim.scenarios import CAMERA_FRAME, IMU_FRAME, SimOptions
    from msg_adapters.camera_info import camera_model_to_info
    from msg_adapters.image import array_to_image
    from msg_adapters.imu import gyro_to_imus
    from msg_adapters.stamps import header_to_ns, make_header

    sim = scenarios.get(scenario).simulate(
        SimOptions(seconds=seconds, width=width, height=height, rate_hz=rate)
    )
    start = int(sim.frame_stamps_ns[0])
    images = [
        (
            f.stamp_ns - start,
            array_to_image(f.image, "mono8", header=make_header(f.stamp_ns, CAMERA_FRAME)),
        )
        for f in sim.frames()
    ]
    gyro = sim.gyro_samples()
    imus = [
        (header_to_ns(m.header) - start, m, gyro.angular_velocity[i])
        for i, m in enumerate(gyro_to_imus(gyro, IMU_FRAME))
    ]
    duration = images[-1][0] + round(1e9 / rate)
    imus = [x for x in imus if 0 <= x[0] < duration]
    info = camera_model_to_info(sim.camera, make_header(start, CAMERA_FRAME))
    return _Clip(images, imus, info, duration, sim.camera_to_imu_xyzw)


def proc_tree(pid: int) -> list[int]:
    """Process ``pid`` and its live descendants (the node's dense process; not the
    zombies, which have ended), breadth first, from /proc."""
    out = [pid]
    for p in out:  # grows while walked
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = [int(k) for k in (task / "children").read_text().split()]
            except OSError:  # the task ended meanwhile
                continue
            out += [k for k in kids if _state(k) not in ("Z", "")]
    return out


def _state(pid: int) -> str:
    """The state letter of process ``pid`` (R, S, Z...), "" when it is gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return ""


def proc_cpu_s(pid: int) -> float:
    """User + system CPU time of process ``pid`` and its live descendants (all their
    threads), s, from /proc: the node's CPU includes its dense process."""
    total = 0
    for p in proc_tree(pid):
        try:
            stat = Path(f"/proc/{p}/stat").read_text()
        except OSError:
            if p == pid:
                raise
            continue  # a child that ended meanwhile
        fields = stat.rsplit(")", 1)[1].split()  # after the command name (may hold spaces)
        total += int(fields[11]) + int(fields[12])
    return total / os.sysconf("SC_CLK_TCK")


def proc_rss_mb(pid: int) -> float:
    """Resident set size (VmRSS) of process ``pid`` and its live descendants, MiB (shared
    pages counted in each), from /proc; NaN when ``pid`` is absent."""
    sizes = [_rss_mb(p) for p in proc_tree(pid)]
    return float(sum(x for x in sizes[1:] if x == x) + sizes[0])


def _rss_mb(pid: int) -> float:
    """VmRSS of one process, MiB; NaN when absent."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return float("nan")
    for line in text.splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def measure(
    clip: _Clip,
    speed: float = 1.0,
    seconds: float = 10.0,
    warmup_s: float = WARMUP_S,
    max_features: int = 1000,
    domain: int | None = None,
    node_args: Sequence[str] = (),
    image_topics: Sequence[str] = (),
) -> Measurement:
    """Run owl_node, publish ``clip`` looped at ``speed`` x its rate, measure (see module)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import Vector3
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import CameraInfo, Image, Imu, PointCloud2

    from msg_adapters.stamps import header_to_ns, ns_to_stamp

    dom = domain if domain is not None else 150 + os.getpid() % 80
    env = {**os.environ, "ROS_DOMAIN_ID": str(dom)}
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    q = clip.rotation
    cmd = [
        "-r",
        "image:=/lat/image",
        "-r",
        "camera_info:=/lat/camera_info",
        "-r",
        "imu:=/lat/imu",
    ]
    cmd += ["-p", f"camera_to_imu_rotation_xyzw:=[{q[0]},{q[1]},{q[2]},{q[3]}]"]
    cmd += ["-p", f"max_features:={max_features}", *node_args]
    live = LiveNode(cmd, env=env).start()
    node_pid = live.pid
    context = Context()
    rclpy.init(args=[PROG], context=context, domain_id=dom)
    node = rclpy.create_node("owl_latency", context=context)
    arrivals: list[tuple[int, int, int]] = []  # (stamp, arrival wall ns, points)

    def on_cloud(msg: Any) -> None:
        arrivals.append((header_to_ns(msg.header), time.time_ns(), int(msg.width)))

    node.create_subscription(
        PointCloud2,
        "/owl/points",
        on_cloud,
        QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE),
    )
    # the node's figures of _DIAGNOSTIC_KEYS in /diagnostics, with their arrival times
    snapshots: list[tuple[int, dict[str, float]]] = []

    def on_diagnostics(msg: Any) -> None:
        found = {
            kv.key: float(kv.value)
            for status in msg.status
            for kv in status.values
            if kv.key in _DIAGNOSTIC_KEYS
        }
        if found:
            snapshots.append((time.time_ns(), found))

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
    image_stamps: dict[str, list[int]] = {topic: [] for topic in image_topics}
    for topic in image_topics:  # e.g. a dense output, which is built only while subscribed
        node.create_subscription(
            Image,
            topic,
            lambda msg, got=image_stamps[topic]: got.append(header_to_ns(msg.header)),
            QoSProfile(depth=10),
        )
    pub_img = node.create_publisher(Image, "/lat/image", qos_profile_sensor_data)
    pub_info = node.create_publisher(CameraInfo, "/lat/camera_info", qos_profile_sensor_data)
    pub_imu = node.create_publisher(Imu, "/lat/imu", QoSProfile(depth=100))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    stop = threading.Event()
    spinner = threading.Thread(
        target=lambda: [executor.spin_once(timeout_sec=0.05) for _ in iter(stop.is_set, True)],
        daemon=True,
    )
    spinner.start()
    sent: list[int] = []
    late_ms: list[float] = []
    published: list[int] = []  # wall time of every image publication, ns
    try:
        live.wait_until(
            lambda: (
                pub_img.get_subscription_count() > 0 and node.count_publishers("/owl/points") > 0
            )
        )
        time.sleep(1.0)
        events = sorted(
            [(t, 0, m, None) for t, m in clip.images] + [(t, 1, m, w) for t, m, w in clip.imus],
            key=lambda e: (e[0], e[1]),
        )
        clip_ns = clip.duration_ns
        t0 = time.time_ns() + 200_000_000
        end = t0 + round((warmup_s + seconds) * 1e9)
        window = t0 + round(warmup_s * 1e9)
        cpu0 = wall0 = None
        loop = 0
        while time.time_ns() < end and live.running():
            for offset, kind, msg, rate in events:
                stamp = t0 + round((loop * clip_ns + offset) / speed)
                wait = (stamp - time.time_ns()) * 1e-9
                if wait > 0:
                    time.sleep(wait)
                if cpu0 is None and stamp >= window:
                    cpu0, wall0 = proc_cpu_s(node_pid), time.monotonic()
                msg.header.stamp = ns_to_stamp(stamp)
                if kind == 0:
                    clip.info.header.stamp = msg.header.stamp
                    published.append(time.time_ns())
                    pub_img.publish(msg)
                    pub_info.publish(clip.info)
                    if stamp >= window:
                        sent.append(stamp)
                        late_ms.append((time.time_ns() - stamp) * 1e-6)
                else:
                    w = rate * speed
                    msg.angular_velocity = Vector3(x=float(w[0]), y=float(w[1]), z=float(w[2]))
                    pub_imu.publish(msg)
                if stamp >= end:
                    break
            loop += 1
        time.sleep(1.0)
        cpu1, wall1 = proc_cpu_s(node_pid), time.monotonic()
        rss = proc_rss_mb(node_pid)
        time.sleep(_DIAGNOSTICS_WAIT_S)  # the counters after the last frame
    finally:
        stop.set()
        spinner.join(timeout=2)
        live.stop(timeout_s=10)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    sent_set = set(sent)
    got = [(s, a, n) for s, a, n in arrivals if s in sent_set]
    lat = np.array([(a - s) * 1e-6 for s, a, _ in got]) if got else np.array([np.nan])
    pts = [n for _, _, n in got if n > 0]
    cpu = 100.0 * (cpu1 - cpu0) / (wall1 - wall0) if cpu0 is not None and wall0 else np.nan
    frame_ns = clip.images[1][0] - clip.images[0][0]
    return Measurement(
        input_rate_hz=round(1e9 / frame_ns * speed, 2),
        width=int(clip.info.width),
        height=int(clip.info.height),
        max_features=max_features,
        images_sent=len(sent),
        clouds=len(got),
        kept_up=len(got) / max(len(sent), 1),
        latency_ms_p50=float(np.percentile(lat, 50)),
        latency_ms_p95=float(np.percentile(lat, 95)),
        latency_ms_max=float(np.max(lat)),
        cpu_percent=float(cpu),
        rss_mb=rss,
        points_per_cloud=float(np.mean(pts)) if pts else 0.0,
        **_node_counts(snapshots, window, published),
        publish_late_ms_p95=float(np.percentile(late_ms, 95)) if late_ms else float("nan"),
        images_per_frame={
            t: len(sent_set.intersection(v)) / max(len(sent), 1) for t, v in image_stamps.items()
        },
    )


def _node_counts(
    snapshots: Sequence[tuple[int, dict[str, float]]], window_ns: int, published: Sequence[int]
) -> dict[str, Any]:
    """The node's counters between its first diagnostics at or after ``window_ns`` and
    its last, and the images published in that span (-1 each without two snapshots)."""
    inside = [(t, c) for t, c in snapshots if t >= window_ns]
    if len(inside) < 2:
        return {}
    (t0, c0), (t1, c1) = inside[0], inside[-1]
    pub = np.asarray(published, dtype=np.int64)

    def delta(key: str) -> int:
        return round(c1.get(key, 0.0) - c0.get(key, 0.0))

    engine = [c["processing_ms_mean"] for _, c in inside[1:] if "processing_ms_mean" in c]
    engine = [v for v in engine if np.isfinite(v)]
    return {
        "counted_sent": int(np.count_nonzero((pub > t0) & (pub <= t1))),
        "node_images": delta("images_total"),
        "node_dropped_queue": delta("dropped_queue_full_total"),
        "node_processed": delta("frames_processed_total"),
        "node_engine_ms": float(np.median(engine)) if engine else float("nan"),
    }


def meets(case: LatencyCase, m: Measurement) -> dict[str, bool]:
    """Which of ``case``'s targets the measurement ``m`` meets (name -> bool)."""
    out = {"kept_up": m.kept_up >= case.min_kept_up}
    if case.max_p95_ms is not None:
        out["latency_p95"] = m.latency_ms_p95 <= case.max_p95_ms
    if case.max_cpu_percent is not None:
        out["cpu"] = m.cpu_percent <= case.max_cpu_percent
    return out


def median_measurement(runs: Sequence[Measurement]) -> dict[str, float]:
    """Per-field medians of several runs of the same input (numeric fields)."""
    rows = [asdict(m) for m in runs]
    out = {
        k: float(np.median([r[k] for r in rows]))
        for k, v in rows[0].items()
        if not isinstance(v, dict)
    }
    for topic in rows[0]["images_per_frame"]:
        out[f"images_per_frame {topic}"] = float(
            np.median([r["images_per_frame"][topic] for r in rows])
        )
    return out


def clip_seconds(args: argparse.Namespace, speed: float | None = None) -> float:
    """The clip to render, s: ``--clip-seconds``, else long enough that the publisher does
    not loop before the window ends (warm-up, window and half a second, played at ``speed``,
    by default the highest ``--speed``). A looped clip jumps back to its first image, which
    a camera never does: the engine loses every track there and pays about 100 to 180 CPU ms
    a loop re-tracking (street, 640x480, 1000 features), so a 2 s loop cost the node several
    frames of 60."""
    if args.clip_seconds is not None:
        return float(args.clip_seconds)
    return (WARMUP_S + args.seconds + 0.5) * (max(args.speed) if speed is None else speed)


def _run_case(name: str, args: argparse.Namespace, node_args: list[str]) -> None:
    case = CASES[name]
    seconds = clip_seconds(args, 1.0)  # a case plays at its own rate
    clip = render_clip(args.scenario, seconds, case.width, case.height, case.rate_hz)
    runs = []
    for i in range(args.runs):
        m = measure(
            clip,
            1.0,
            args.seconds,
            max_features=args.max_features or case.max_features,
            node_args=node_args,
            image_topics=args.subscribe_image,
        )
        runs.append(m)
        print(json.dumps({"case": name, "run": i + 1, **asdict(m), "meets": meets(case, m)}))
    if args.runs > 1:
        med = median_measurement(runs)
        ok = {
            "kept_up": med["kept_up"] >= case.min_kept_up,
            **(
                {"latency_p95": med["latency_ms_p95"] <= case.max_p95_ms}
                if case.max_p95_ms is not None
                else {}
            ),
            **(
                {"cpu": med["cpu_percent"] <= case.max_cpu_percent}
                if case.max_cpu_percent is not None
                else {}
            ),
        }
        print(json.dumps({"case": name, "median_of": args.runs, **med, "meets": ok}), flush=True)


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface (every option with its help)."""
    p = OneLineErrorParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default="street", help="scenario (owl_make_bag --list)")
    p.add_argument("--width", type=int, default=640, help="image width, px (default 640)")
    p.add_argument("--height", type=int, default=480, help="image height, px (default 480)")
    p.add_argument("--rate", type=float, default=30.0, help="clip frame rate, Hz (default 30)")
    p.add_argument(
        "--clip-seconds", type=float, default=None,
        help="rendered clip, s (default: the warm-up and the window at the highest --speed, "
        "so the window sees one continuous motion; a shorter clip loops, and each loop jumps "
        "back to its first image: a scene cut the engine re-tracks from scratch)",
    )  # fmt: skip
    p.add_argument("--seconds", type=float, default=10.0, help="measurement window, s")
    p.add_argument(
        "--max-features", type=int, default=None,
        help="owl_node max_features (default 1000; with --case it replaces the case's 1000, "
        "and the targets are still judged)",
    )  # fmt: skip
    p.add_argument(
        "--speed", type=float, nargs="+", default=[1.0],
        help="rate factors: the clip is played this many times faster (default 1)",
    )  # fmt: skip
    p.add_argument(
        "-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
        help="extra owl_node parameter, repeatable",
    )  # fmt: skip
    p.add_argument(
        "--case",
        action="append",
        choices=sorted(CASES),
        default=[],
        help="standard input with targets (repeatable; replaces --width/--height/--rate/"
        "--speed): "
        + ", ".join(f"{k} {c.width}x{c.height}@{c.rate_hz:g}Hz" for k, c in CASES.items()),
    )
    p.add_argument("--runs", type=int, default=1, help="runs per --case (medians printed)")
    p.add_argument(
        "--subscribe-image", action="append", default=[], metavar="TOPIC",
        help="also subscribe to this sensor_msgs/Image topic of the node (e.g. "
        "/owl/range_over_speed with -p dense:=true), repeatable",
    )  # fmt: skip
    p.add_argument(
        "--default-transport", action="store_true",
        help="publish with Fast DDS's default transports (512 KiB shared-memory segment; "
        "larger images go over UDP) instead of bags.dds's 16 MiB segment",
    )  # fmt: skip
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; prints one JSON object per measured speed or case run (progress on
    stderr)."""
    p = build_parser()
    args = p.parse_args(argv)
    if args.runs < 1:
        p.error(f"--runs must be >= 1, got {args.runs}")
    if args.max_features is not None and args.max_features < 1:
        p.error(f"--max-features must be >= 1, got {args.max_features}")
    for item in args.param:  # the tool sets it, and records it in every measurement
        if item.split(":=", 1)[0].strip() == "max_features":
            p.error(f"-p {item}: give the feature count as --max-features, not as -p")

    def say(text: str) -> None:
        if not args.quiet:
            print(f"{PROG}: {text}", file=sys.stderr, flush=True)

    if not args.default_transport:  # this process publishes the images (a camera driver)
        profile = prefer_large_image_profile()
        if profile is not None:
            say(f"Fast DDS profile {profile} (16 MiB shared-memory segment)")

    if args.case:
        node_args = [x for item in args.param for x in ("-p", item)]
        for name in args.case:
            features = args.max_features or CASES[name].max_features
            say(
                f"case {name} with {features} features: {args.runs} run(s) of about "
                f"{args.seconds + WARMUP_S + 3:.0f} s"
            )
            _run_case(name, args, node_args)
        return 0
    seconds = clip_seconds(args)
    say(f"rendering {seconds:g} s of {args.scenario} at {args.width}x{args.height}")
    clip = render_clip(args.scenario, seconds, args.width, args.height, args.rate)
    for i, speed in enumerate(args.speed, 1):
        node_args = [x for item in args.param for x in ("-p", item)]
        say(
            f"[{i}/{len(args.speed)}] {args.rate * speed:g} Hz input: starting owl_node, then "
            f"about {args.seconds + WARMUP_S + 3:.0f} s of replay"
        )
        m = measure(
            clip,
            speed,
            args.seconds,
            max_features=args.max_features or 1000,
            node_args=node_args,
            image_topics=args.subscribe_image,
        )
        say(
            f"[{i}/{len(args.speed)}] {m.clouds}/{m.images_sent} clouds, latency p50 "
            f"{m.latency_ms_p50:.0f} ms"
        )
        print(json.dumps(asdict(m)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
