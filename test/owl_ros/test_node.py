"""Node ``owl`` over real DDS: two processes (the node, owl_replay) and a test subscriber.

rmw_fastrtps_cpp on a private ROS_DOMAIN_ID per test (``ros_domain_env``). One 320x240,
1.5 s bag is rendered per module and also run through owl_process for reference headings.
"""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistWithCovarianceStamped, Vector3Stamped
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter as RclpyParameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image, PointCloud2
from visualization_msgs.msg import Marker

from bags.cli import make_bag
from bags.io import BagReader
from msg_adapters.diagnostics import msg_to_records
from msg_adapters.pointcloud import OWL_FIELDS, cloud_speed, cloud_to_array
from msg_adapters.stamps import header_to_ns
from owl_ros.node import OwlNode
from owl_ros.params import ParameterError
from owl_ros.process import ProcessOptions, Summary, process_bag
from owl_ros.tools.latency import proc_tree
from owl_ros.tools.live import LiveNode
from owl_ros.topics import RESULT_TOPICS

pytestmark = [pytest.mark.dds, pytest.mark.slow]

SECONDS = 2.0
# A 20 Hz camera: the engine costs about 25 ms per 320x240 frame on a slow CI core (one
# thread), and the replayer and the test's subscriber share the 2 cores with the node, so
# at 30 Hz the node ran at the edge and dropped frames whenever the machine was busy. These
# tests check behaviour at real rate; throughput and latency limits are owl_latency's.
RATE_HZ = 20
WARMUP_FRAMES = 10  # tracks need 5 frames; the first frames also pay for lazy imports
INPUTS = ("/camera/image_raw", "/camera/camera_info", "/imu/data")
REMAPS = ("image:=/camera/image_raw", "camera_info:=/camera/camera_info", "imu:=/imu/data")
TWIST = "/ground_truth/twist"
CONFIG = Path(__file__).resolve().parents[2] / "config" / "owl.yaml"
ROTATION = "camera_to_imu_rotation_xyzw:=[-0.5,0.5,-0.5,0.5]"
# The test machine is shared by several jobs (2 cores): a deeper queue than the default
# lets the node ride out moments of CPU starvation. Frames it still drops for a newer one
# are counted by the node and accounted for by the checks (check_clouds' ``dropped``);
# throughput and latency are measured by owl_ros.tools.latency.
QUEUE = "queue_size:=8"
# Longer than Fast DDS's default heartbeat period (3 s), after which a writer resends a
# reliable sample its reader missed.
REPAIR_S = 4.0


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("node") / "street"
    args = ["street", str(out), "--seconds", str(SECONDS), "--rate", str(RATE_HZ)]
    args += ["--width", "320", "--height", "240"]
    assert make_bag.main([*args, "--quiet", "--seed", "7"]) == 0
    return out


@pytest.fixture(scope="module")
def reference(bag: Path, tmp_path_factory: pytest.TempPathFactory) -> Summary:
    return process_bag(bag, tmp_path_factory.mktemp("node_ref") / "owl", ProcessOptions())


@pytest.fixture(scope="module")
def frame_stamps(bag: Path) -> list[int]:
    with BagReader(bag) as reader:
        return [raw.log_time_ns for raw in reader.messages(["/camera/image_raw"])]


class Collector:
    """A test node in its own rclpy context, spinning in a thread, recording outputs."""

    def __init__(self, domain: int) -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("owl_test_collector", context=self.context)
        self.clouds: list[Any] = []
        self.headings: list[Any] = []
        self.diagnostics: list[Any] = []
        self._diagnostics_at = 0.0  # time.monotonic() of the newest diagnostics
        qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(PointCloud2, "/owl/points", self.clouds.append, qos)
        self.node.create_subscription(Vector3Stamped, "/owl/heading", self.headings.append, qos)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, qos)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _on_diagnostics(self, msg: Any) -> None:
        self.diagnostics.append(msg)
        self._diagnostics_at = time.monotonic()

    def _spin(self) -> None:
        while not self._stop and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def wait_for(self, what: Callable[[], bool], timeout: float, why: str) -> None:
        deadline = time.monotonic() + timeout
        while not what():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout} s waiting for {why}")
            time.sleep(0.05)

    def wait_settled(self, count: int, timeout: float = 15.0, quiet_s: float = 1.0) -> None:
        """Until at least ``count`` clouds arrived, none for ``quiet_s``, a diagnostics
        message came after the last cloud, and either it counts no more processed frames
        than clouds arrived or ``REPAIR_S`` more have passed (a reliable sample lost on the
        way is resent at the next DDS heartbeat: quiet alone does not mean delivered)."""
        deadline = time.monotonic() + timeout
        seen, since = -1, time.monotonic()
        while time.monotonic() < deadline:
            n = len(self.clouds)
            quiet = time.monotonic() - since
            if n != seen:
                seen, since = n, time.monotonic()
            elif n >= count and quiet >= quiet_s and self._diagnostics_at > since:
                if self.processed() <= n or quiet >= quiet_s + REPAIR_S:
                    return
            time.sleep(0.05)
        raise AssertionError(
            f"timed out: {len(self.clouds)} clouds, expected >= {count}; the node's newest "
            f"diagnostics count {self.processed()} processed frames"
        )

    def processed(self) -> int:
        """frames_processed_total of the newest ``owl: processing`` status (-1 if none)."""
        return self._processing_count("frames_processed_total")

    def dropped(self) -> int:
        """Frames that never reached the engine, from the newest diagnostics (0 if none):
        those the node dropped for a newer one (``dropped_queue_full_total``) and those lost
        before it (``images_missing_total``, between the stamps it received: a best-effort
        image lost on a loaded machine). Current after ``wait_settled``."""
        if not self.diagnostics:
            return 0
        lost = int(self.status("input")[2]["images_missing_total"])
        return max(self._processing_count("dropped_queue_full_total"), 0) + lost

    def _processing_count(self, key: str) -> int:
        return int(self.status("processing")[2][key]) if self.diagnostics else -1

    def wait_for_node(self, timeout: float = 20.0) -> None:
        """Until the node's publications and this node's subscriptions have matched."""
        self.wait_for(
            lambda: (
                self.node.count_publishers("/owl/points") > 0
                and self.node.count_publishers("/owl/heading") > 0
            ),
            timeout,
            "node 'owl' publishers",
        )
        time.sleep(0.5)  # let the publisher side finish matching too

    def call(self, srv_type: Any, name: str, request: Any, timeout: float = 10.0) -> Any:
        client = self.node.create_client(srv_type, name)
        self.wait_for(lambda: client.service_is_ready(), timeout, f"service {name}")
        future = client.call_async(request)
        self.wait_for(future.done, timeout, f"reply of {name}")
        self.node.destroy_client(client)
        return future.result()

    def set_parameter(self, name: str, value: Any) -> Any:
        pv = ParameterValue()
        if isinstance(value, bool):
            pv.type, pv.bool_value = ParameterType.PARAMETER_BOOL, value
        elif isinstance(value, int):
            pv.type, pv.integer_value = ParameterType.PARAMETER_INTEGER, value
        elif isinstance(value, float):
            pv.type, pv.double_value = ParameterType.PARAMETER_DOUBLE, value
        elif isinstance(value, str):
            pv.type, pv.string_value = ParameterType.PARAMETER_STRING, value
        else:
            pv.type, pv.double_array_value = ParameterType.PARAMETER_DOUBLE_ARRAY, list(value)
        request = SetParameters.Request(parameters=[Parameter(name=name, value=pv)])
        return self.call(SetParameters, "/owl/set_parameters", request).results[0]

    def status(self, name: str) -> tuple[int, str, dict[str, str]]:
        """(level, message, values) of the newest diagnostics status ``owl: <name>``."""
        _, records = msg_to_records(self.diagnostics[-1])
        rec = next(r for r in records if r.name == f"owl: {name}")
        return int(rec.level), rec.message, rec.value_map()

    def close(self) -> None:
        self._stop = True
        self._thread.join(timeout=5)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def collector(ros_domain_env: dict[str, str]) -> Iterator[Collector]:
    c = Collector(int(ros_domain_env["ROS_DOMAIN_ID"]))
    yield c
    c.close()


def start_node(env: dict[str, str], *ros_args: str) -> LiveNode:
    """owl_node with the shipped config/owl.yaml, the bag's topics and extra -p values."""
    args = ["--params-file", str(CONFIG)]
    for remap in REMAPS:
        args += ["-r", remap]
    args += ["-p", ROTATION, "-p", "diagnostics_period_s:=0.5", "-p", QUEUE]
    for item in ros_args:
        args += ["-p", item]
    return LiveNode(args, env=env, stdout=subprocess.PIPE).start()


def truth_speeds(bag: Path) -> dict[int, float]:
    """Image stamp -> ground-truth camera speed, m/s."""
    from geometry_msgs.msg import TwistStamped
    from rclpy.serialization import deserialize_message

    out = {}
    with BagReader(bag) as reader:
        for raw in reader.messages([TWIST]):
            msg = deserialize_message(raw.data, TwistStamped)
            v = msg.twist.linear
            out[header_to_ns(msg.header)] = math.sqrt(v.x * v.x + v.y * v.y + v.z * v.z)
    return out


def replay(env: dict[str, str], bag: Path, *extra: str) -> None:
    topics = [] if "--topics" in extra else ["--topics", *INPUTS]
    cmd = [sys.executable, "-m", "bags.cli.replay", str(bag), *topics, "-q"]
    # --wait-for-subscribers also waits bags.cli.replay.MATCH_SETTLE_S for the node's readers
    cmd += ["--wait-for-subscribers", "--wait-timeout", "20", *extra]
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60, check=False)
    assert run.returncode == 0, run.stderr


def stop_node(node: LiveNode) -> tuple[int, str]:
    """SIGINT, then (exit code, stderr)."""
    code, err = node.stop(timeout_s=15)
    assert not node.killed, f"node did not exit after SIGINT: {err}"
    return code, err


#: frames with points a live run must give at least (the contract checks read the last
#: one; two show it was not a lone frame). On a slow machine newest-wins may keep only a
#: handful: the looping-bag test's second loop kept 4 of 12 on a 2-core VM at 107 ms a frame
MIN_FULL = 2


def newest_wins_latency_bound_ms(slowest_cycle_ms: float, queue: int = 2) -> float:
    """Bound on a frame's arrival -> publication latency, ms, with a newest-wins queue of
    ``queue`` frames: the rest of the worker's current frame, at most ``queue - 1`` queued
    ahead of it, and its own, each at most one worker cycle (conversion, engine, messages,
    publishing: ``frame_cycle_ms_max``), plus one more cycle and 50 ms for handing over IMU
    batches between cycles. The slowest cycle of the whole run bounds it: a frame's wait
    may span two diagnostics windows."""
    return (queue + 2) * slowest_cycle_ms + 50


def check_clouds(
    clouds: Sequence[Any], stamps: list[int], diagnostics: Any = None, dropped: int = 0
) -> dict[int, Any]:
    """Contract checks; returns stamp -> cloud. Of the frames after warm-up that reached the
    engine (``dropped``: :meth:`Collector.dropped`, the node's own counts of frames dropped
    for a newer one, newest wins when the machine is busy, and of images lost before it),
    >= 90 % gave points, and at least ``MIN_FULL`` did. How many frames a node
    keeps at the real rate is the machine's speed, a benchmark figure (``owl_latency``),
    not asserted here: on a 2-core VM slower than usual it kept 12 to 14 of 31."""
    by_stamp = {header_to_ns(c.header): c for c in clouds}
    assert set(by_stamp) <= set(stamps)  # headers are the images' headers
    after = stamps[WARMUP_FRAMES:]
    full = [t for t in after if t in by_stamp and by_stamp[t].width > 0]
    why = ""
    if diagnostics is not None and diagnostics.diagnostics:
        why = " ".join(f"{s}: {diagnostics.status(s)}" for s in ("processing", "gyro", "input"))
    missing = [i for i, t in enumerate(stamps) if t not in by_stamp]
    empty = [i for i, t in enumerate(stamps) if t in by_stamp and by_stamp[t].width == 0]
    kept = len(after) - dropped
    assert len(full) >= max(0.9 * kept, MIN_FULL), (
        f"{len(full)} of {len(after)} gave points, {dropped} dropped for a newer frame or "
        f"lost before the node (frames without a cloud: {missing}, with an empty one: "
        f"{empty}); {why}"
    )
    for c in clouds:
        assert c.header.frame_id == "camera_optical_frame"
        assert [f.name for f in c.fields] == [name for name, _, _ in OWL_FIELDS]
    pts = cloud_to_array(by_stamp[full[-1]])
    assert np.all(np.isfinite(pts["range_over_speed"])) and np.all(pts["range_over_speed"] > 0)
    return by_stamp


def check_headings(headings: Sequence[Any], reference: Summary) -> int:
    """Headings agree with owl_process within the engine's stated uncertainty."""
    ref = {
        int(t): (h, s)
        for t, h, s in zip(
            reference.heading_stamps_ns,
            reference.headings,
            reference.heading_sigma_rad,
            strict=True,
        )
    }
    compared = 0
    for msg in headings:
        stamp = header_to_ns(msg.header)
        if stamp not in ref:
            continue
        h, sigma = ref[stamp]
        v = np.array([msg.vector.x, msg.vector.y, msg.vector.z])
        err = math.acos(np.clip(v @ h, -1.0, 1.0))
        # two estimates of the same heading, each with 1-sigma `sigma`: 4 combined sigmas
        assert err < 4 * math.sqrt(2) * sigma, (stamp, math.degrees(err), math.degrees(sigma))
        compared += 1
    return compared


def test_replay_at_real_rate(
    ros_domain_env: dict[str, str],
    collector: Collector,
    bag: Path,
    reference: Summary,
    frame_stamps: list[int],
) -> None:
    node = start_node(ros_domain_env)
    try:
        collector.wait_for_node()
        replay(ros_domain_env, bag)
        collector.wait_settled(1)  # the last diagnostics period is within the quiet second
    finally:
        code, err = stop_node(node)
    assert code == 0, err
    assert "Traceback" not in err
    dropped = collector.dropped()
    check_clouds(collector.clouds, frame_stamps, collector, dropped)
    compared = check_headings(collector.headings, reference)
    assert compared >= 0.9 * (len(reference.headings) - dropped), (compared, dropped)
    _, _, values = collector.status("processing")
    # every frame accounted for: processed, or dropped for a newer one (counted)
    assert int(values["frames_processed_total"]) + dropped >= 0.9 * len(frame_stamps)
    assert float(values["latency_ms_p50"]) > 0 or values["latency_ms_p50"] == "nan"


def test_dense_outputs_from_the_node_process_and_its_child_ends_with_it(
    ros_domain_env: dict[str, str], collector: Collector, bag: Path
) -> None:
    """owl_node with ``dense: true``: the dense images come from its ``owl-dense`` child
    process, which ends when the node does (SIGINT)."""
    images: list[Any] = []
    qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
    collector.node.create_subscription(Image, "/owl/range_over_speed", images.append, qos)
    node = start_node(ros_domain_env, "dense:=true", "dense_width:=160", "dense_height:=120")
    try:
        collector.wait_for_node()
        replay(ros_domain_env, bag)
        collector.wait_settled(1)
        collector.wait_for(lambda: len(images) >= 1, 15.0, "a dense image")
        children = set(proc_tree(node.pid)[1:])
        names = {Path(f"/proc/{c}/comm").read_text().strip() for c in children}
    finally:
        code, err = stop_node(node)
    assert code == 0, err
    assert "Traceback" not in err
    assert names == {"owl-dense"}, names
    assert not [c for c in children if Path(f"/proc/{c}").exists()], "owl-dense outlived the node"
    assert images[-1].encoding == "32FC1" and (images[-1].height, images[-1].width) == (120, 160)
    _, _, values = collector.status("dense")
    assert int(values["dense_frames_total"]) >= 1 and int(values["dense_errors_total"]) == 0


def test_replay_with_sim_time_and_clock(
    ros_domain_env: dict[str, str],
    collector: Collector,
    bag: Path,
    reference: Summary,
    frame_stamps: list[int],
) -> None:
    # also the metric scale: ground-truth twist as the speed source
    node = start_node(
        ros_domain_env,
        "use_sim_time:=true",
        "speed_source:=twist",
        f"speed_topic:={TWIST}",
    )
    try:
        collector.wait_for_node()
        replay(ros_domain_env, bag, "--clock", "--topics", *INPUTS, TWIST)
        collector.wait_settled(1)
    finally:
        code, err = stop_node(node)
    assert code == 0, err
    dropped = collector.dropped()
    by_stamp = check_clouds(collector.clouds, frame_stamps, collector, dropped)
    compared = check_headings(collector.headings, reference)
    assert compared >= 0.9 * (len(reference.headings) - dropped), (compared, dropped)
    speeds = truth_speeds(bag)
    metric = [c for c in by_stamp.values() if c.width > 0]
    for cloud in metric:  # x y z in metres, and the cloud says with which speed
        assert cloud_speed(cloud_to_array(cloud)) == pytest.approx(
            speeds[header_to_ns(cloud.header)], rel=1e-6
        )
    # diagnostics are stamped with the node's clock: the bag's (simulated) time
    stamps = [header_to_ns(d.header) for d in collector.diagnostics]
    in_bag = [t for t in stamps if frame_stamps[0] - 10**9 <= t <= frame_stamps[-1] + 10**9]
    assert in_bag, stamps
    assert all(t <= frame_stamps[-1] + 10**9 for t in stamps)  # never wall time


def test_help_lists_parameters() -> None:
    run = subprocess.run(
        [sys.executable, "-m", "owl_ros.node", "--help"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert run.returncode == 0
    assert "camera_to_imu_rotation_xyzw" in run.stdout and "read-only" in run.stdout
    said = " ".join(run.stdout.split("Parameters:")[0].split())  # the wrapped header
    assert all(f" {t.name}," in said for t in RESULT_TOPICS), said


@pytest.mark.parametrize(
    ("param", "expect"),
    [
        ("max_features:=-5", "parameter max_features"),
        ("camera_to_imu_rotation_xyzw:=[0.0,0.0,1.0]", "must have 4 elements"),
        ("queue_size:=0", "parameter queue_size"),
    ],
)
def test_invalid_parameter_at_start_one_line(
    ros_domain_env: dict[str, str], param: str, expect: str
) -> None:
    cmd = [sys.executable, "-m", "owl_ros.node", "--ros-args", "-p", param]
    run = subprocess.run(
        cmd, env=ros_domain_env, capture_output=True, text=True, timeout=60, check=False
    )
    assert run.returncode != 0
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1, run.stderr
    assert lines[0].startswith("owl_node: error: ") and expect in lines[0]


def test_runtime_parameters_qos_events_and_time_jump(
    ros_domain_env: dict[str, str],
    collector: Collector,
    bag: Path,
    frame_stamps: list[int],
) -> None:
    # a subscriber asking for transient-local durability: incompatible with owl/heading
    latched = QoSProfile(
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    collector.node.create_subscription(Vector3Stamped, "/owl/heading", lambda _: None, latched)
    node = start_node(ros_domain_env)
    try:
        collector.wait_for_node()
        bad = collector.set_parameter("max_features", -1)
        assert not bad.successful and "max_features" in bad.reason
        bad = collector.set_parameter("camera_to_imu_rotation_xyzw", [0.0, 0.0, 1.0])
        assert not bad.successful
        assert "camera_to_imu_rotation_xyzw: must have 4 elements" in bad.reason
        bad = collector.set_parameter("min_track_frames", 11)  # > fit_frames (10)
        assert not bad.successful and "min_track_frames" in bad.reason
        ro = collector.set_parameter("image_transport", "compressed")
        assert not ro.successful and "read-only" in ro.reason.lower()
        ok = collector.set_parameter("max_features", 600)
        assert ok.successful, ok.reason
        got = collector.call(
            GetParameters, "/owl/get_parameters", GetParameters.Request(names=["max_features"])
        )
        assert got.values[0].integer_value == 600

        # the input publisher goes away and comes back with the same (earlier) stamps
        replay(ros_domain_env, bag)
        collector.wait_settled(1)
        first, dropped = len(collector.clouds), collector.dropped()
        replay(ros_domain_env, bag)
        collector.wait_settled(first + 1)
        dropped = collector.dropped() - dropped
    finally:
        code, err = stop_node(node)
    assert code == 0, err
    # recovered without a restart
    check_clouds(collector.clouds[first:], frame_stamps, collector, dropped)
    _, _, proc = collector.status("processing")
    assert int(proc["time_jumps_total"]) >= 1
    assert "engine reset" in proc["last_time_jump"]
    _, _, inputs = collector.status("input")
    assert int(inputs["qos_events_total"]) >= 1
    assert "owl/heading" in inputs["qos_last_event"] and "DURABILITY" in inputs["qos_last_event"]


def test_overload_newest_frame_wins_latency_bounded(
    ros_domain_env: dict[str, str], collector: Collector, bag: Path, frame_stamps: list[int]
) -> None:
    """Input at 5x real rate (100 Hz) with the default queue: drops counted, latency
    bounded."""
    debug: list[Any] = []
    collector.node.create_subscription(
        Image, "/owl/debug_image", debug.append, QoSProfile(depth=5)
    )
    cmd_args = []
    for remap in REMAPS:
        cmd_args += ["-r", remap]
    cmd_args += ["-p", ROTATION, "-p", "diagnostics_period_s:=0.3"]
    node = LiveNode(cmd_args, env=ros_domain_env, stdout=subprocess.PIPE).start()
    try:
        collector.wait_for_node()
        replay(ros_domain_env, bag, "--rate", "5")
        collector.wait_settled(1)
    finally:
        code, err = stop_node(node)
    assert code == 0, err
    stamps = [header_to_ns(c.header) for c in collector.clouds]
    assert stamps == sorted(stamps) and set(stamps) <= set(frame_stamps)
    _, _, proc = collector.status("processing")
    dropped = int(proc["dropped_queue_full_total"])
    assert dropped > 0 and len(stamps) + dropped <= len(frame_stamps)
    # newest wins (default queue_size 2): latency bounded in worker cycles
    windows = [
        next(r for r in msg_to_records(d)[1] if r.name == "owl: processing").value_map()
        for d in collector.diagnostics
    ]
    cycles = [float(v["frame_cycle_ms_max"]) for v in windows]
    bound = newest_wins_latency_bound_ms(max(c for c in cycles if not math.isnan(c)))
    for values in windows:
        p95 = float(values["latency_ms_p95"])
        if not math.isnan(p95):
            assert p95 <= bound, (bound, values)
    # the debug image was built while subscribed: header of its frame, tracks drawn
    assert debug and debug[-1].encoding == "bgr8"
    assert header_to_ns(debug[-1].header) in set(stamps)


def test_a_10_ms_imu_lag_warns_in_diagnostics_and_is_logged_once(
    ros_domain_env: dict[str, str], collector: Collector, tmp_path: Path
) -> None:
    """owl_node over DDS, fed a handheld walk whose IMU lags the images by 10 ms while the
    offset is configured 0: ``owl: gyro`` WARNs with the online estimate (within 1 ms of
    10 ms: about three of its sigma at this length), and the node logs it once. 3.5 s at
    20 Hz: two comparisons (every 30 processed frames), so one frame dropped under load
    still leaves one."""
    lag = tmp_path / "handheld"
    args = ["handheld", str(lag), "--seconds", "3.5", "--rate", str(RATE_HZ)]
    args += ["--width", "320", "--height", "240", "--time-offset", "0.01", "--quiet"]
    assert make_bag.main(args) == 0
    node = start_node(ros_domain_env)
    try:
        collector.wait_for_node()
        replay(ros_domain_env, lag)
        collector.wait_settled(1)
    finally:
        code, err = stop_node(node)
    assert code == 0, err
    warnings = [
        rec.value_map()
        for msg in collector.diagnostics
        for rec in msg_to_records(msg)[1]
        if rec.name == "owl: gyro" and rec.level == 1 and "calibration" in rec.message
    ]
    assert warnings, "no calibration WARN in /diagnostics"
    first = warnings[0]
    assert first["calibration_ok"] == "False" and first["calibration_source"] == "online"
    assert abs(float(first["calibration_offset_s"]) - 0.01) < 0.001, first
    assert err.count("camera-IMU calibration:") == 1, err


# ---- QoS of the node object itself (in this process, its own context and domain) ----------


def qos_of(node: Any, topic: str, publishers: bool) -> list[str]:
    """Reliability of ``node``'s own publishers (or subscriptions) on ``topic``."""
    infos = (
        node.get_publishers_info_by_topic if publishers else node.get_subscriptions_info_by_topic
    )
    return [i.qos_profile.reliability.name for i in infos(topic) if i.node_name == node.get_name()]


def test_every_publication_reports_an_incompatible_subscriber(
    rclpy_context: Context,
    make_owl: Callable[..., OwlNode],
    capfd: pytest.CaptureFixture[str],
) -> None:
    """A transient-local subscriber can never get a volatile publisher's messages: the node
    says so for each of its outputs (the log and owl: input's qos_events_total), the heading
    with covariance and the marker included."""
    node = make_owl()
    peer = rclpy.create_node("owl_test_latched_peer", context=rclpy_context)
    latched = QoSProfile(
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    kinds = {
        "/owl/points": PointCloud2,
        "/owl/heading": Vector3Stamped,
        "/owl/heading_with_covariance": TwistWithCovarianceStamped,
        "/owl/heading_marker": Marker,
        "/owl/gyro_bias": Vector3Stamped,
        "/owl/debug_image": Image,
        "/diagnostics": DiagnosticArray,
    }
    assert {t.bag for t in RESULT_TOPICS} <= set(kinds)
    for topic, kind in kinds.items():
        peer.create_subscription(kind, topic, lambda _: None, latched)
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)
    executor.add_node(peer)
    log = ""
    try:
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and node._pipeline.totals.qos_events < len(kinds):
            executor.spin_once(timeout_sec=0.05)
        time.sleep(0.2)  # the worker hands the last event to the pipeline
        out = capfd.readouterr()
        log = out.out + out.err
    finally:
        executor.shutdown()
        peer.destroy_node()
    for topic in kinds:
        assert f"{topic.lstrip('/')}: incompatible QoS with a peer" in log, (topic, log)
    assert node._pipeline.totals.qos_events == len(kinds)
    assert "publication /owl/points: incompatible QoS" in log  # the resolved name


def test_qos_overrides_set_the_qos_and_an_unknown_one_is_warned_about(
    make_owl: Callable[..., OwlNode], capfd: pytest.CaptureFixture[str]
) -> None:
    node = make_owl(
        RclpyParameter(
            "qos_overrides./camera/image_raw.subscription.reliability", value="reliable"
        ),
        RclpyParameter("qos_overrides./owl/points.publisher.reliability", value="best_effort"),
        RclpyParameter("qos_overrides./owl/points.publisher.durability", value="transient_local"),
        remaps=["image:=/camera/image_raw"],
    )
    # the resolved (remapped) name, as rclcpp and rclpy nodes take them
    assert qos_of(node, "/camera/image_raw", publishers=False) == ["RELIABLE"]
    assert qos_of(node, "/camera_info", publishers=False) == ["BEST_EFFORT"]  # its own profile
    assert qos_of(node, "/owl/points", publishers=True) == ["BEST_EFFORT"]
    assert qos_of(node, "/owl/heading", publishers=True) == ["RELIABLE"]
    name = "qos_overrides./imu.subscription.depth"
    assert node.get_parameter(name).value == 200  # declared with the node's own default
    assert node.describe_parameters([name])[0].read_only
    out = capfd.readouterr()
    log = out.out + out.err
    unused = "parameter qos_overrides./owl/points.publisher.durability: no such QoS override"
    assert log.count(unused) == 1, log


@pytest.mark.parametrize(
    ("name", "value", "expect"),
    [
        ("qos_overrides./imu.subscription.depth", -3, "depth must be >= 1"),
        ("qos_overrides./owl/heading.publisher.reliability", "sometimes", "`sometimes`"),
    ],
)
def test_a_bad_qos_override_is_a_parameter_error(
    make_owl: Callable[..., OwlNode], name: str, value: Any, expect: str
) -> None:
    with pytest.raises(ParameterError) as err:
        make_owl(RclpyParameter(name, value=value))
    (line,) = err.value.lines
    assert line.startswith(f"parameters {name.rsplit('.', 1)[0]}.*: ") and expect in line, line


@pytest.mark.parametrize("topic", ["wheel odom", "odom//twist"])
def test_an_invalid_speed_topic_is_a_parameter_error(
    make_owl: Callable[..., OwlNode], topic: str
) -> None:
    """Caught by the parameter check ("wheel odom") or when it is resolved ("odom//twist"):
    one line naming the parameter, as owl_node prints it, instead of a traceback."""
    with pytest.raises(ParameterError) as err:
        make_owl(
            RclpyParameter("speed_source", value="twist"),
            RclpyParameter("speed_topic", value=topic),
        )
    (line,) = err.value.lines
    assert line.startswith("parameter speed_topic: ") and repr(topic) in line, line
