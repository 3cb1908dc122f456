"""owl_soak (``make soak``): a rendered bag looped at 30 Hz through a live ``owl_node``.

Renders a scenario bag (``owl_make_bag``, default street, 4 s, 320x240: the size at which
the node keeps up with 30 Hz on a 2-core machine shared with other jobs; the frames it
drops when those jobs take the CPU are counted and reported), starts
``owl_node`` in its own process on a private ROS domain and feeds it the bag's image,
camera_info and IMU messages over real DDS, looped, at the recorded pace, for
``--minutes`` (default 10). Two ways of looping:

- ``--loop-mode restamp`` (default): the bag's messages are published from this process
  with every loop's header stamps shifted by the clip length, so time only moves forward
  (as on a robot) and the engine is never reset by the loop: tracks, bias estimate and
  buffers run for the whole soak;
- ``--loop-mode replay``: ``owl_replay --loop`` plays the bag unchanged: time jumps back
  at every loop and the node resets its engine each time (bag-loop behaviour).

Measured while it runs:

- the node's RSS (``VmRSS`` from ``/proc/<pid>/status``) and CPU time (``/proc/<pid>/stat``)
  every ``--sample`` seconds;
- per frame, from the node's ``/diagnostics`` (one window per second): the engine's wall
  time per frame (``processing_ms_mean``), frames processed, frames dropped, latency.

Report (table, or one JSON object with ``--json``): RSS at the end of the warm-up and at
the end, growth in % (goal < 10 %); per-frame time in the first and the last segment
(minute) after warm-up (goal: no growth, i.e. < 10 % more). The per-frame figure judged
is the 10th percentile of the engine's per-frame time over the segment's one-second
windows: other jobs on a shared machine only ever add time to a frame, so a low
percentile follows the node's own work (a growing cost raises it too) while medians and
CPU time per frame (both reported) also move with the machine's load. Exit status 0 when
both goals are met, 1 when one fails or the node dies, 2 on bad options.

    python -m owl_ros.tools.soak                     # 10 minutes (make soak)
    python -m owl_ros.tools.soak --minutes 0.5 --json
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import astuple, dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from bags.cli import OneLineErrorParser
from owl_ros.tools.errors import LiveNodeError, SoakError
from owl_ros.tools.latency import proc_cpu_s, proc_rss_mb
from owl_ros.tools.live import LiveNode

PROG = "owl_soak"
INPUTS = ("/camera/image_raw", "/camera/camera_info", "/imu/data")
TF_STATIC = "/tf_static"
CONFIG = Path(__file__).resolve().parents[2] / "config" / "owl.yaml"
#: goals of issue 7: RSS growth after warm-up and per-frame time growth, fractions.
RSS_GOAL = 0.10
FRAME_TIME_GOAL = 0.10
#: longest warm-up, s (shorter runs: a fifth of the run).
WARMUP_MAX_S = 60.0


@dataclass(frozen=True)
class SoakOptions:
    """What to run.

    Attributes:
        minutes: soak duration (publishing), minutes.
        width, height: rendered image size, px.
        rate_hz: camera frame rate of the rendered bag, Hz.
        speed: play the bag this many times faster (restamp: stamps compressed and gyro
            rates scaled, a consistent faster camera; replay: owl_replay --rate).
        clip_s: rendered bag length (one loop), s.
        scenario: owl_make_bag scenario.
        loop_mode: "restamp" (time moves forward) or "replay" (owl_replay --loop).
        warmup_s: excluded from the growth figures, s (None: min(60 s, a fifth of the run)).
        sample_s: RSS/CPU sampling period, s.
        domain: ROS_DOMAIN_ID (None: a private one from the process id).
        node_params: extra owl_node parameters, "NAME:=VALUE".
        log_dir: where the bag and the node's log go (None: a temporary directory).
        quiet: no progress lines.
    """

    minutes: float = 10.0
    width: int = 320
    height: int = 240
    rate_hz: float = 30.0
    speed: float = 1.0
    clip_s: float = 4.0
    scenario: str = "street"
    loop_mode: str = "restamp"
    warmup_s: float | None = None
    sample_s: float = 1.0
    domain: int | None = None
    node_params: tuple[str, ...] = ()
    log_dir: str | None = None
    quiet: bool = False

    @property
    def duration_s(self) -> float:
        """Soak duration, s."""
        return self.minutes * 60.0

    @property
    def warmup(self) -> float:
        """Warm-up actually used, s."""
        if self.warmup_s is not None:
            return self.warmup_s
        return min(WARMUP_MAX_S, self.duration_s / 5.0)


@dataclass(frozen=True)
class Sample:
    """One /proc sample of the node: seconds since the soak started, RSS MiB, CPU s."""

    t_s: float
    rss_mib: float
    cpu_s: float


@dataclass(frozen=True)
class Window:
    """One ``owl: processing`` diagnostics window as received (t_s since the start)."""

    t_s: float
    processing_ms: float
    processed_total: int
    with_points_total: int
    dropped_total: int
    time_jumps_total: int
    latency_ms_p95: float
    processing_ms_max: float = math.nan
    images_total: int = 0
    frame_cycle_ms_max: float = math.nan


@dataclass
class _Run:
    samples: list[Sample] = field(default_factory=list)
    windows: list[Window] = field(default_factory=list)
    images_sent: int = 0
    clouds: int = 0
    node_exit: int | None = None


# ------------------------------------------------------------------------------ report


def _interp(times: Sequence[float], values: Sequence[float], t_s: float) -> float:
    return float(np.interp(t_s, np.asarray(times), np.asarray(values, dtype=np.float64)))


def _max_finite(values: Iterable[float]) -> float:
    """Largest finite value, NaN if there is none."""
    return max((v for v in values if math.isfinite(v)), default=math.nan)


def _segment(run: _Run, t0: float, t1: float) -> dict[str, float]:
    """Per-frame figures between t0 and t1 (s since start): node CPU seconds and frames
    processed are both interpolated at t0 and t1 (samples every second, diagnostics
    windows every second), so their ratio covers the same interval."""
    wins = [w for w in run.windows if t0 <= w.t_s <= t1]
    st = [s.t_s for s in run.samples]
    wt = [w.t_s for w in run.windows]

    def cpu(t: float) -> float:
        return _interp(st, [s.cpu_s for s in run.samples], t)

    def frames(t: float) -> float:
        return _interp(wt, [w.processed_total for w in run.windows], t)

    def dropped(t: float) -> float:
        return _interp(wt, [w.dropped_total for w in run.windows], t)

    n = frames(t1) - frames(t0)
    proc = [w.processing_ms for w in wins if math.isfinite(w.processing_ms)]
    lat = [w.latency_ms_p95 for w in wins if math.isfinite(w.latency_ms_p95)]
    return {
        "t0_s": t0,
        "t1_s": t1,
        "rss_mib": _interp(st, [s.rss_mib for s in run.samples], t1),
        "processing_ms": float(np.median(proc)) if proc else math.nan,
        "processing_ms_p10": float(np.percentile(proc, 10)) if proc else math.nan,
        "processing_ms_max": _max_finite(w.processing_ms_max for w in wins),
        "frame_cycle_ms_max": _max_finite(w.frame_cycle_ms_max for w in wins),
        "cpu_ms_per_frame": 1e3 * (cpu(t1) - cpu(t0)) / n if n > 0 else math.nan,
        "frames_per_s": n / (t1 - t0) if t1 > t0 else math.nan,
        "dropped": round(dropped(t1) - dropped(t0)),
        "latency_ms_p95": float(np.median(lat)) if lat else math.nan,
    }


def _growth(first: float, last: float) -> float:
    return (last - first) / first if first > 0 and math.isfinite(last) else math.nan


def _json_num(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _json_num(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_json_num(v) for v in x]
    return x


def make_report(opts: SoakOptions, run: _Run, elapsed_s: float) -> dict[str, Any]:
    """The soak report (JSON-ready; NaN -> None) from the samples and windows.

    Raises:
        SoakError: no samples after the warm-up (run too short) or no diagnostics.
    """
    warm = opts.warmup
    post = [s for s in run.samples if s.t_s >= warm]
    if len(post) < 2 or not run.windows:
        raise SoakError(
            f"too few samples after the {warm:g} s warm-up ({len(post)} RSS samples, "
            f"{len(run.windows)} diagnostics windows): run longer"
        )
    end = min(elapsed_s, run.samples[-1].t_s, run.windows[-1].t_s)
    span = end - warm
    # whole loops per segment (the per-frame cost follows the scene within a loop)
    loops = max(1, math.floor((60.0 if span >= 180.0 else span / 4.0) / opts.clip_s))
    seg = min(loops * opts.clip_s, span)
    edges = [warm + k * seg for k in range(max(1, math.floor(span / seg + 1e-9)) + 1)]
    edges[-1] = end  # a remainder shorter than a segment joins the last one
    segments = [_segment(run, a, b) for a, b in itertools.pairwise(edges)]
    # the goals compare whole loops: the first and the last `seg` seconds after warm-up
    first, last = _segment(run, warm, warm + seg), _segment(run, end - seg, end)
    rss0, rss1 = post[0].rss_mib, post[-1].rss_mib
    t = np.array([s.t_s for s in post])
    r = np.array([s.rss_mib for s in post])
    slope = float(np.polyfit(t, r, 1)[0]) * 60.0 if len(post) >= 3 else math.nan
    rss_growth = _growth(rss0, rss1)
    cpu_growth = _growth(first["cpu_ms_per_frame"], last["cpu_ms_per_frame"])
    wall_growth = _growth(first["processing_ms"], last["processing_ms"])
    p10_growth = _growth(first["processing_ms_p10"], last["processing_ms_p10"])
    rss_ok = math.isfinite(rss_growth) and rss_growth < RSS_GOAL
    time_ok = math.isfinite(p10_growth) and p10_growth < FRAME_TIME_GOAL
    lastw = run.windows[-1]
    frames = {
        "images_sent": run.images_sent,
        "clouds_received": run.clouds,
        "processed": lastw.processed_total,
        "with_points": lastw.with_points_total,
        "images_received": lastw.images_total,
        "dropped_queue_full": lastw.dropped_total,
        "time_jumps": lastw.time_jumps_total,
        "kept_up": lastw.processed_total / run.images_sent if run.images_sent else math.nan,
    }
    report = {
        "config": {
            "minutes": opts.minutes,
            "elapsed_s": elapsed_s,
            "warmup_s": warm,
            "segment_s": seg,
            "width": opts.width,
            "height": opts.height,
            "rate_hz": opts.rate_hz,
            "speed": opts.speed,
            "input_rate_hz": opts.rate_hz * opts.speed,
            "clip_s": opts.clip_s,
            "scenario": opts.scenario,
            "loop_mode": opts.loop_mode,
            "sample_s": opts.sample_s,
            "cpus": os.cpu_count(),
        },
        "rss": {
            "samples": len(run.samples),
            "warmup_mib": rss0,
            "warmup_t_s": post[0].t_s,
            "end_mib": rss1,
            "end_t_s": post[-1].t_s,
            "max_mib": float(r.max()),
            "growth_percent": 100.0 * rss_growth,
            "slope_mib_per_min": slope,
            "goal_percent": 100.0 * RSS_GOAL,
            "ok": rss_ok,
        },
        "frame_time": {
            "cpu_ms_per_frame_first": first["cpu_ms_per_frame"],
            "cpu_ms_per_frame_last": last["cpu_ms_per_frame"],
            "cpu_growth_percent": 100.0 * cpu_growth,
            "processing_ms_first": first["processing_ms"],
            "processing_ms_last": last["processing_ms"],
            "processing_growth_percent": 100.0 * wall_growth,
            "processing_ms_p10_first": first["processing_ms_p10"],
            "processing_ms_p10_last": last["processing_ms_p10"],
            "growth_percent": 100.0 * p10_growth,
            "goal_percent": 100.0 * FRAME_TIME_GOAL,
            "ok": time_ok,
        },
        "frames": frames,
        "segments": segments,
        "samples": [[s.t_s, s.rss_mib, s.cpu_s] for s in run.samples],
        "windows": [list(astuple(w)) for w in run.windows],
        "ok": rss_ok and time_ok,
    }
    return _json_num(report)  # type: ignore[no-any-return]


def report_lines(report: dict[str, Any]) -> list[str]:
    """The report as a text table."""
    c, r, f, n = report["config"], report["rss"], report["frame_time"], report["frames"]

    def num(x: Any, fmt: str = ".1f") -> str:
        return "n/a" if x is None else format(x, fmt)

    lines = [
        f"{PROG}: {c['elapsed_s'] / 60:.1f} min, {c['scenario']} {c['width']}x{c['height']} "
        f"at {c['input_rate_hz']:g} Hz, loop mode {c['loop_mode']}, warm-up {c['warmup_s']:g} s, "
        f"{c['cpus']} CPUs",
        "  segment      RSS MiB  engine ms/frame p10 / median  CPU ms/frame  frames/s  dropped"
        "  lat p95 ms",
    ]
    for s in report["segments"]:
        lines.append(
            f"  {s['t0_s']:5.0f}-{s['t1_s']:<5.0f}  {num(s['rss_mib']):>7}  "
            f"{num(s['processing_ms_p10'], '.2f'):>20} / {num(s['processing_ms'], '.2f'):<6}  "
            f"{num(s['cpu_ms_per_frame'], '.2f'):>12}  "
            f"{num(s['frames_per_s']):>8}  {s['dropped']:>7}  {num(s['latency_ms_p95']):>10}"
        )
    verdict = {True: "OK", False: "FAIL"}
    lines += [
        f"  RSS: {num(r['warmup_mib'])} MiB after warm-up -> {num(r['end_mib'])} MiB at the end "
        f"({num(r['growth_percent'], '+.2f')} %, slope {num(r['slope_mib_per_min'], '+.3f')} "
        f"MiB/min; goal < {r['goal_percent']:g} %): {verdict[r['ok']]}",
        f"  per-frame time (engine, p10): {num(f['processing_ms_p10_first'], '.2f')} -> "
        f"{num(f['processing_ms_p10_last'], '.2f')} ms ({num(f['growth_percent'], '+.1f')} %; "
        f"goal < {f['goal_percent']:g} %): {verdict[f['ok']]}; median "
        f"{num(f['processing_ms_first'], '.2f')} -> {num(f['processing_ms_last'], '.2f')} ms "
        f"({num(f['processing_growth_percent'], '+.1f')} %), node CPU per frame "
        f"{num(f['cpu_ms_per_frame_first'], '.2f')} -> {num(f['cpu_ms_per_frame_last'], '.2f')}"
        f" ms ({num(f['cpu_growth_percent'], '+.1f')} %)",
        f"  frames: {n['images_sent']} sent, {n['processed']} processed "
        f"({num(n['kept_up'] and 100 * n['kept_up'])} %), {n['with_points']} with points, "
        f"{n['dropped_queue_full']} dropped (queue full, counted by the node; "
        f"{n['images_received']} received), {n['time_jumps']} time jumps",
    ]
    return lines


# ------------------------------------------------------------------------------ running


def _rotation_from_bag(bag_path: Path) -> tuple[float, float, float, float]:
    """camera_to_imu_rotation_xyzw from the bag's /tf_static (as owl_process does)."""
    from bags.io import BagReader
    from owl_ros.process import tf_rotation

    with BagReader(bag_path) as bag:
        transforms: list[Any] = []
        for raw in bag.messages([TF_STATIC]):
            transforms.extend(bag.deserialize(raw).transforms)
        imu = next(bag.messages(["/imu/data"]))
        cam = next(bag.messages(["/camera/camera_info"]))
        imu_frame = bag.deserialize(imu).header.frame_id
        cam_frame = bag.deserialize(cam).header.frame_id
    found = tf_rotation(transforms, imu_frame, cam_frame)
    return found if found is not None else (0.0, 0.0, 0.0, 1.0)


def _load_clip(bag_path: Path) -> tuple[list[tuple[int, str, Any]], int]:
    """The inputs as (offset ns from the first image, topic, rclpy message), in log-time
    order, restricted to one loop; and the loop length, ns."""
    from rclpy.serialization import deserialize_message

    from bags.io import BagReader
    from msg_adapters.msgtypes import message_class
    from msg_adapters.stamps import header_to_ns

    with BagReader(bag_path) as bag:
        classes = {t: message_class(bag.topics[t].msgtype) for t in INPUTS}
        msgs = [
            (raw.topic, deserialize_message(raw.data, classes[raw.topic]))
            for raw in bag.messages(list(INPUTS))
        ]
    images = [header_to_ns(m.header) for t, m in msgs if t == INPUTS[0]]
    period = (images[-1] - images[0]) // max(len(images) - 1, 1)
    clip_ns = images[-1] - images[0] + period
    out = []
    for topic, msg in msgs:
        offset = header_to_ns(msg.header) - images[0]
        if 0 <= offset < clip_ns:
            out.append((offset, topic, msg))
    out.sort(key=lambda e: (e[0], e[1] != INPUTS[2]))  # IMU before the image at a tie
    return out, clip_ns


class _Feeder(threading.Thread):
    """Publishes the clip looped with stamps shifted per loop (restamp mode)."""

    def __init__(
        self, node: Any, clip: list[tuple[int, str, Any]], clip_ns: int, speed: float = 1.0
    ) -> None:
        super().__init__(name="owl-soak-feeder", daemon=True)
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image, Imu

        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        kinds = {INPUTS[0]: Image, INPUTS[1]: CameraInfo, INPUTS[2]: Imu}
        self.pubs = {t: node.create_publisher(k, t, qos) for t, k in kinds.items()}
        self.clip, self.clip_ns, self.speed = clip, clip_ns, speed
        for _, topic, msg in clip if speed != 1.0 else ():
            if topic == INPUTS[2]:  # a faster camera turns faster: scale the gyro
                w = msg.angular_velocity
                w.x, w.y, w.z = w.x * speed, w.y * speed, w.z * speed
        self.stop = threading.Event()
        self.images_sent = 0
        self.end_mono = math.inf

    def ready(self) -> bool:
        return all(p.get_subscription_count() > 0 for p in self.pubs.values())

    def run(self) -> None:
        from msg_adapters.stamps import ns_to_stamp

        base = time.time_ns()  # stamps on the wall clock: stamp -> publish latency is real
        mono0 = time.monotonic()
        loop = 0
        while not self.stop.is_set():
            for offset, topic, msg in self.clip:
                at = round((loop * self.clip_ns + offset) / self.speed)
                due = mono0 + at * 1e-9
                if due >= self.end_mono:
                    return
                while not self.stop.is_set() and (wait := due - time.monotonic()) > 0:
                    time.sleep(min(wait, 0.05))
                if self.stop.is_set():
                    return
                msg.header.stamp = ns_to_stamp(base + at)
                self.pubs[topic].publish(msg)
                if topic == INPUTS[0]:
                    self.images_sent += 1
            loop += 1


def _parse_window(values: dict[str, str], t_s: float, images: int) -> Window:
    """A Window from the ``owl: processing`` values; ``images``: the node's images_total
    (``owl: input``) of the same report."""

    def f(key: str) -> float:
        try:
            return float(values.get(key, "nan"))
        except ValueError:
            return math.nan

    def i(key: str) -> int:
        v = f(key)
        return int(v) if math.isfinite(v) else 0

    return Window(
        t_s,
        f("processing_ms_mean"),
        i("frames_processed_total"),
        i("frames_with_points_total"),
        i("dropped_queue_full_total"),
        i("time_jumps_total"),
        f("latency_ms_p95"),
        f("processing_ms_max"),
        images,
        f("frame_cycle_ms_max"),
    )


def _progress(stream: TextIO, opts: SoakOptions, run: _Run, t_s: float) -> None:
    s = run.samples[-1] if run.samples else None
    w = run.windows[-1] if run.windows else None
    text = f"[{PROG}] {t_s / 60:5.1f}/{opts.minutes:g} min"
    if s is not None:
        text += f"  RSS {s.rss_mib:.1f} MiB"
    if w is not None:
        text += f"  {w.processed_total} frames, engine {w.processing_ms:.2f} ms/frame"
        text += f", {w.dropped_total} dropped"
    stream.write(text + "\n")
    stream.flush()


def run_soak(opts: SoakOptions, stream: TextIO = sys.stderr) -> dict[str, Any]:
    """Render, run the node, feed it, measure; returns the report (see make_report).

    Raises:
        SoakError: the node did not start or died, or the run was too short to report.
    """
    from bags.cli import make_bag

    with tempfile.TemporaryDirectory(prefix="owl_soak_") as tmp:
        work = Path(opts.log_dir) if opts.log_dir else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        bag = work / "soak_bag"
        args = [opts.scenario, str(bag), "--seconds", str(opts.clip_s), "--overwrite"]
        args += ["--width", str(opts.width), "--height", str(opts.height)]
        args += ["--rate", str(opts.rate_hz), "--seed", "7", "--quiet"]
        if make_bag.main(args) != 0:
            raise SoakError(f"could not render scenario {opts.scenario!r}")
        return _run_with_bag(opts, bag, work / "owl_node.log", stream)


def _run_with_bag(opts: SoakOptions, bag: Path, log_path: Path, stream: TextIO) -> dict[str, Any]:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from msg_adapters.diagnostics import msg_to_records

    domain = opts.domain if opts.domain is not None else 150 + os.getpid() % 80
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    q = _rotation_from_bag(bag)
    cmd = ["--params-file", str(CONFIG)] if CONFIG.is_file() else []
    cmd += ["-r", f"image:={INPUTS[0]}", "-r", f"camera_info:={INPUTS[1]}"]
    cmd += ["-r", f"imu:={INPUTS[2]}", "-p", "diagnostics_period_s:=1.0"]
    cmd += ["-p", f"camera_to_imu_rotation_xyzw:=[{q[0]},{q[1]},{q[2]},{q[3]}]"]
    for item in opts.node_params:
        cmd += ["-p", item]
    clip, clip_ns = _load_clip(bag) if opts.loop_mode == "restamp" else ([], 0)
    run = _Run()
    log = log_path.open("w")
    live = LiveNode(cmd, env=env, stdout=log, stderr=subprocess.STDOUT).start()
    node_pid = live.pid
    context = Context()
    rclpy.init(args=[PROG], context=context, domain_id=domain)
    node = rclpy.create_node("owl_soak", context=context)
    t0 = [time.monotonic()]

    def on_diag(msg: Any) -> None:
        records = {rec.name: rec.value_map() for rec in msg_to_records(msg)[1]}
        if "owl: processing" in records:
            images = records.get("owl: input", {}).get("images_total", "0")
            window = _parse_window(
                records["owl: processing"], time.monotonic() - t0[0], int(float(images))
            )
            run.windows.append(window)

    def on_cloud(_msg: Any) -> None:
        run.clouds += 1

    images_seen = [0]  # replay mode: images owl_replay published, as seen here

    def on_image(_raw: bytes) -> None:
        images_seen[0] += 1

    reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, reliable)
    node.create_subscription(PointCloud2, "/owl/points", on_cloud, reliable)
    feeder = _Feeder(node, clip, clip_ns, opts.speed) if opts.loop_mode == "restamp" else None
    if feeder is None:
        from sensor_msgs.msg import Image

        node.create_subscription(Image, INPUTS[0], on_image, reliable, raw=True)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spinning = threading.Event()
    spinner = threading.Thread(
        target=lambda: [executor.spin_once(timeout_sec=0.05) for _ in iter(spinning.is_set, True)],
        daemon=True,
    )
    spinner.start()
    replayer: subprocess.Popen[bytes] | None = None
    try:
        try:
            live.wait_until(
                lambda: (
                    node.count_publishers("/owl/points") > 0 and (feeder is None or feeder.ready())
                ),
                what="up",
            )
        except LiveNodeError as err:
            raise SoakError(f"{err} ({log_path})") from None
        time.sleep(0.5)
        t0[0] = time.monotonic()
        run.windows.clear()
        if feeder is not None:
            feeder.end_mono = t0[0] + opts.duration_s
            feeder.start()
        else:
            replay_cmd = [sys.executable, "-m", "bags.cli.replay", str(bag), "--loop", "-q"]
            replay_cmd += ["--rate", str(opts.speed)]
            replayer = subprocess.Popen(
                [*replay_cmd, "--topics", *INPUTS],
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=log,
            )
        next_sample = t0[0]
        next_progress = t0[0] + 30.0
        end = t0[0] + opts.duration_s
        while (now := time.monotonic()) < end:
            if not live.running():
                raise SoakError(
                    f"owl_node died after {now - t0[0]:.0f} s with code {live.returncode} "
                    f"({log_path})"
                )
            if now >= next_sample:
                run.samples.append(
                    Sample(now - t0[0], proc_rss_mb(node_pid), proc_cpu_s(node_pid))
                )
                next_sample += opts.sample_s
            if not opts.quiet and now >= next_progress:
                _progress(stream, opts, run, now - t0[0])
                next_progress += 30.0
            time.sleep(max(min(next_sample - time.monotonic(), 0.2), 0.0))
        elapsed = time.monotonic() - t0[0]
        run.samples.append(Sample(elapsed, proc_rss_mb(node_pid), proc_cpu_s(node_pid)))
        if feeder is not None:
            feeder.stop.set()
            feeder.join(timeout=5)
            run.images_sent = feeder.images_sent
        if replayer is not None:
            replayer.send_signal(signal.SIGINT)
            replayer.wait(timeout=15)
            run.images_sent = images_seen[0]
        time.sleep(1.5)  # the last diagnostics window (frames queued at the end)
    finally:
        if feeder is not None:
            feeder.stop.set()
        if replayer is not None and replayer.poll() is None:
            replayer.kill()
        run.node_exit, _ = live.stop(timeout_s=15)
        log.close()
        spinning.set()
        spinner.join(timeout=2)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    if run.node_exit != 0:
        raise SoakError(f"owl_node exited with code {run.node_exit} after SIGINT ({log_path})")
    report = make_report(opts, run, elapsed)
    report["config"]["node_log"] = str(log_path) if opts.log_dir else None
    return report


# ------------------------------------------------------------------------------ CLI


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    p = OneLineErrorParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=10.0, help="soak duration (default 10)")
    p.add_argument("--width", type=int, default=320, help="image width, px (default 320)")
    p.add_argument("--height", type=int, default=240, help="image height, px (default 240)")
    p.add_argument("--rate", type=float, default=30.0, help="frame rate, Hz (default 30)")
    p.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="play S times faster (default 1): e.g. an overload test; restamp mode scales the "
        "stamps and gyro rates, replay mode passes --rate",
    )
    p.add_argument("--clip-seconds", type=float, default=4.0, help="bag length, s (default 4)")
    p.add_argument("--scenario", default="street", help="owl_make_bag scenario (default street)")
    p.add_argument(
        "--loop-mode",
        choices=("restamp", "replay"),
        default="restamp",
        help="restamp: time moves forward across loops (default); replay: owl_replay --loop "
        "(time jumps back, engine reset at every loop)",
    )
    p.add_argument("--warmup", type=float, default=None, metavar="S", help="warm-up, s")
    p.add_argument("--sample", type=float, default=1.0, metavar="S", help="RSS sampling, s")
    p.add_argument("--domain", type=int, default=None, help="ROS_DOMAIN_ID (default private)")
    p.add_argument(
        "-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
        help="extra owl_node parameter, repeatable",
    )  # fmt: skip
    p.add_argument("--log-dir", default=None, help="keep the bag and the node log here")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    return p


def options_from_args(ns: argparse.Namespace) -> SoakOptions:
    """Parsed arguments -> SoakOptions; SoakError naming a bad value."""
    checks = [
        ("--minutes", ns.minutes, ns.minutes > 0 and math.isfinite(ns.minutes)),
        ("--width", ns.width, ns.width >= 32),
        ("--height", ns.height, ns.height >= 32),
        ("--rate", ns.rate, ns.rate > 0 and math.isfinite(ns.rate)),
        ("--speed", ns.speed, 0 < ns.speed <= 20),
        ("--clip-seconds", ns.clip_seconds, ns.clip_seconds >= 0.5),
        ("--sample", ns.sample, ns.sample > 0),
        ("--warmup", ns.warmup, ns.warmup is None or 0 <= ns.warmup < ns.minutes * 60),
        ("--domain", ns.domain, ns.domain is None or 0 <= ns.domain <= 232),
    ]
    for name, value, ok in checks:
        if not ok:
            raise SoakError(f"{name} out of range: {value}")
    for item in ns.param:
        if ":=" not in item:
            raise SoakError(f"--param expects NAME:=VALUE, got {item!r}")
    return SoakOptions(
        minutes=float(ns.minutes),
        width=int(ns.width),
        height=int(ns.height),
        rate_hz=float(ns.rate),
        speed=float(ns.speed),
        clip_s=float(ns.clip_seconds),
        scenario=ns.scenario,
        loop_mode=ns.loop_mode,
        warmup_s=ns.warmup,
        sample_s=float(ns.sample),
        domain=ns.domain,
        node_params=tuple(ns.param),
        log_dir=ns.log_dir,
        quiet=ns.quiet or False,
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``owl_soak`` (``make soak``); 0 = both goals met."""
    from bags.sim import scenarios

    ns = build_parser().parse_args(argv)
    try:
        opts = options_from_args(ns)
        if opts.scenario not in scenarios.names():
            raise SoakError(
                f"unknown scenario {opts.scenario!r} (have: {', '.join(scenarios.names())})"
            )
    except SoakError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    try:
        report = run_soak(opts)
    except SoakError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    if ns.json:
        print(json.dumps(report))
    else:
        for line in report_lines(report):
            print(line)
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
