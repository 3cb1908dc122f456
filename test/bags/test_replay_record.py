"""owl_replay and owl_record: options and errors, CDR header stamps, and replay -> record
over real DDS (rmw_fastrtps, separate processes) byte for byte."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Imu

from bags.cli.record import RecordError, header_stamp_ns
from bags.cli.record import parse_options as parse_record
from bags.cli.replay import MATCH_SETTLE_S, ReplayError, split_ros_args
from bags.cli.replay import parse_options as parse_replay
from bags.io import BagReader, BagWriter, typestore
from msg_adapters.image import array_to_image
from msg_adapters.stamps import make_header

PY = sys.executable
START_NS = 1_700_000_000_000_000_000


# ------------------------------------------------------------------------------- helpers


def _write_bag(path: Path, seconds: float = 1.0, tf_static: bool = True) -> None:
    """Image 10 Hz (mono8 80x60), CameraInfo 10 Hz, IMU 200 Hz, a /tf_static message.

    Images and IMU messages come from rclpy (serialize_message), the rest from rosbags:
    both must come out of the replay byte for byte.
    """
    ts = typestore()
    rng = np.random.default_rng(0)
    with BagWriter(path) as bag:
        bag.add_topic("/camera/image_raw", "sensor_msgs/msg/Image", qos="sensor")
        bag.add_topic("/camera/camera_info", "sensor_msgs/msg/CameraInfo", qos="sensor")
        bag.add_topic("/imu/data", "sensor_msgs/msg/Imu", qos="sensor")
        if tf_static:
            bag.add_topic("/tf_static", "tf2_msgs/msg/TFMessage", qos="latched")
            bag.write("/tf_static", START_NS, ts.types["tf2_msgs/msg/TFMessage"](transforms=[]))
        n_imu = int(seconds * 200)
        for i in range(n_imu):
            t = START_NS + i * 5_000_000
            imu = Imu(header=make_header(t, "imu"))
            imu.angular_velocity.x, imu.angular_velocity.z = rng.normal(size=2).tolist()
            bag.write_raw("/imu/data", t + 100_000, serialize_message(imu))
            if i % 20 == 0:
                img = rng.integers(0, 256, (60, 80), dtype=np.uint8)
                msg = array_to_image(img, "mono8", make_header(t, "camera_optical"))
                bag.write_raw("/camera/image_raw", t + 2_000_000, serialize_message(msg))
                info = _camera_info(ts, t)
                bag.write("/camera/camera_info", t + 2_000_000, info)


def _camera_info(ts, t: int):
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    roi = ts.types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    k = np.array([100.0, 0, 40, 0, 100, 30, 0, 0, 1])
    return ts.types["sensor_msgs/msg/CameraInfo"](
        header=Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id="camera_optical"),
        height=60,
        width=80,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=k,
        r=np.eye(3).reshape(9),
        p=np.hstack([k.reshape(3, 3), np.zeros((3, 1))]).reshape(12),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def _by_topic(path: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    with BagReader(path) as bag:
        for raw in bag.messages():
            out.setdefault(raw.topic, []).append(raw)
    return out


def _same_cdr(got: bytes, sent: bytes) -> bool:
    """The recorded bytes are the sent bytes, up to DDS payload padding.

    RTPS pads a serialized payload to a multiple of 4 bytes and rmw_fastrtps hands raw
    subscribers the padded payload (encapsulation options stay 0), so a 365-byte
    CameraInfo arrives as 368 bytes: the same CDR followed by 3 zero bytes.
    """
    pad = -len(sent) % 4
    return got[: len(sent)] == sent and got[len(sent) :] == bytes(pad)


def _in_write_order(path: Path, topic: str) -> list[tuple[int, bytes]]:
    """(log time, data) of one topic in the order owl_record wrote them (the mcap reader,
    file order: with --stamp header and --loop, log times repeat and log-time order would
    interleave the loops)."""
    (file,) = path.glob("*.mcap")
    with file.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        return [
            (msg.log_time, bytes(msg.data))
            for _, channel, msg in reader.iter_messages(log_time_order=False)
            if channel.topic == topic
        ]


def _run_cli(module: str, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [PY, "-m", module, *args], capture_output=True, text=True, timeout=60, env=env
    )


def _start(module: str, *args: str, env: dict) -> subprocess.Popen:
    return subprocess.Popen(
        [PY, "-m", module, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def _wait_line(proc: subprocess.Popen, needle: str, timeout: float = 20.0) -> str:
    """Read the process's stderr until a line containing ``needle`` (or fail)."""
    deadline = time.monotonic() + timeout
    seen = []
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        seen.append(line)
        if needle in line:
            return line
    proc.kill()
    pytest.fail(f"no {needle!r} from {proc.args}: {''.join(seen)}")


def _one_error_line(stderr: str, *needles: str) -> None:
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, stderr
    assert "Traceback" not in stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


# ------------------------------------------------------------------- options and errors


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["b", "--rate", "-1"], "--rate must be a positive number, got -1.0"),
        (["b", "--rate", "0"], "got 0.0"),
        (["b", "--clock-hz", "0"], "--clock-hz"),
        (["b", "--remap", "/a=/b"], "FROM:=TO, got '/a=/b'"),
        (["b", "--start-delay", "-2"], "got -2.0"),
        (["b", "--qos-depth", "0"], "got 0"),
        (["b", "--remap", "/imu/data:=/imu-data"], "invalid --remap topic name '/imu-data': "),
        (["b", "--remap", "/a:=/b//c"], "must not contain repeated '/'"),
    ],
)
def test_replay_option_errors(argv, match):
    with pytest.raises(ReplayError, match=match):
        parse_replay(argv)


def test_replay_waits_for_readers_to_settle_after_the_match():
    assert parse_replay(["b"]).start_delay_s == 0.0
    assert parse_replay(["b", "--wait-for-subscribers"]).start_delay_s == MATCH_SETTLE_S > 0
    assert parse_replay(["b", "--wait-for-subscribers", "--start-delay", "0"]).start_delay_s == 0


def test_replay_options_normalise_names():
    opts = parse_replay(["bag", "--topics", "imu", "/cam", "--remap", "cam:=/image", "-r", "2"])
    assert opts.topics == ("/imu", "/cam")
    assert opts.remap == (("/cam", "/image"),)
    assert opts.rate == 2.0


def test_split_ros_args_keeps_our_remap():
    own, ros = split_ros_args(
        ["bag", "--remap", "/a:=/b", "--ros-args", "-p", "use_sim_time:=true", "--", "-l"]
    )
    assert own == ["bag", "--remap", "/a:=/b", "-l"]
    assert ros == ["--ros-args", "-p", "use_sim_time:=true", "--"]


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["out", "/a", "a"], "topic /a given twice"),
        (["out", "/a", "--duration", "0"], "--duration must be > 0 seconds, got 0.0"),
        (["out", "/a", "--max-messages", "0"], "got 0"),
        (["out", "bad name"], "invalid topic name 'bad name'"),
        (["out", "/imu-data"], "invalid topic name '/imu-data': topic name must not contain"),
    ],
)
def test_record_option_errors(argv, match):
    with pytest.raises(RecordError, match=match):
        parse_record(argv)


def test_header_stamp_from_cdr_bytes_both_byte_orders():
    stamp = START_NS + 123_456_789
    data = serialize_message(Imu(header=make_header(stamp, "imu")))
    assert data[:2] == b"\x00\x01"  # CDR little endian
    assert header_stamp_ns(data) == stamp
    sec, nsec = divmod(stamp, 10**9)
    big = b"\x00\x00\x00\x00" + sec.to_bytes(4, "big", signed=True) + nsec.to_bytes(4, "big")
    assert header_stamp_ns(big) == stamp
    assert header_stamp_ns(data[:8]) is None


def test_replay_missing_path_one_line(tmp_path):
    res = _run_cli("bags.cli.replay", str(tmp_path / "nope"))
    assert res.returncode == 1
    _one_error_line(res.stderr, "owl_replay: error:", "nope")


def test_replay_non_bag_one_line(tmp_path):
    junk = tmp_path / "notes.txt"
    junk.write_text("not a bag\n")
    res = _run_cli("bags.cli.replay", str(junk))
    assert res.returncode == 1
    _one_error_line(res.stderr, "owl_replay: error:", "not a bag", "notes.txt")


def test_replay_truncated_bag_one_line(tmp_path):
    bag = tmp_path / "bag"
    _write_bag(bag, seconds=0.2, tf_static=False)
    mcap = next(bag.glob("*.mcap"))
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    res = _run_cli("bags.cli.replay", str(bag))
    assert res.returncode == 1
    _one_error_line(res.stderr, "owl_replay: error:", "bag")


def test_replay_bad_option_and_unknown_topic(tmp_path):
    res = _run_cli("bags.cli.replay", "x", "--rate", "-3")
    assert res.returncode == 2
    _one_error_line(res.stderr, "--rate", "-3")
    bag = tmp_path / "bag"
    _write_bag(bag, seconds=0.1, tf_static=False)
    res = _run_cli("bags.cli.replay", str(bag), "--topics", "/nope")
    assert res.returncode == 1
    _one_error_line(res.stderr, "topic /nope is not in bag")


def test_replay_invalid_remap_target_one_line(tmp_path):
    bag = tmp_path / "bag"
    _write_bag(bag, seconds=0.1, tf_static=False)
    res = _run_cli("bags.cli.replay", str(bag), "--remap", "/imu/data:=/imu-data")
    assert res.returncode == 2
    _one_error_line(res.stderr, "owl_replay: error: invalid --remap topic name '/imu-data'")


def test_record_refuses_existing_output(tmp_path):
    bag = tmp_path / "bag"
    _write_bag(bag, seconds=0.1, tf_static=False)
    res = _run_cli("bags.cli.record", str(bag), "/imu/data")
    assert res.returncode == 1
    _one_error_line(res.stderr, "owl_record: error:", "exists")


def test_help():
    for module in ("bags.cli.replay", "bags.cli.record"):
        res = _run_cli(module, "--help")
        assert res.returncode == 0 and "usage:" in res.stdout


# --------------------------------------------------------------------------- over DDS


@pytest.mark.dds
@pytest.mark.slow
def test_replay_to_record_byte_for_byte_in_order(tmp_path, ros_domain_env):
    src, out = tmp_path / "src", tmp_path / "out"
    _write_bag(src, seconds=1.0)
    rec = _start(
        "bags.cli.record",
        str(out),
        "/camera/image_raw",
        "/camera/camera_info",
        "/imu/data",
        env=ros_domain_env,
    )
    _wait_line(rec, "recording to")
    t0 = time.monotonic()
    rep = _run_cli("bags.cli.replay", str(src), "--wait-for-subscribers", env=ros_domain_env)
    assert rep.returncode == 0, rep.stderr
    assert "Traceback" not in rep.stderr
    # tf2_msgs has no Python package here: skipped with one warning, not an error
    assert "skipping /tf_static" in rep.stderr
    rec.send_signal(signal.SIGINT)
    stdout, stderr = rec.communicate(timeout=30)
    assert rec.returncode == 0, stderr
    assert "recorded 220 messages" in stdout

    sent, got = _by_topic(src), _by_topic(out)
    assert set(got) == {"/camera/image_raw", "/camera/camera_info", "/imu/data"}
    for topic, msgs in got.items():
        assert len(msgs) == len(sent[topic]), topic
        for i, (m, ref) in enumerate(zip(msgs, sent[topic], strict=True)):
            assert _same_cdr(m.data, ref.data), (topic, i, len(m.data), len(ref.data))
        assert msgs[0].msgtype == sent[topic][0].msgtype
    # receive times follow the recorded pace at rate 1: never faster than the bag
    # (replay sleeps until each message is due); the upper bound is generous for CI load
    imu_span = (got["/imu/data"][-1].log_time_ns - got["/imu/data"][0].log_time_ns) / 1e9
    bag_span = (sent["/imu/data"][-1].log_time_ns - sent["/imu/data"][0].log_time_ns) / 1e9
    assert imu_span >= 0.95 * bag_span
    assert imu_span <= time.monotonic() - t0


@pytest.mark.dds
@pytest.mark.slow
def test_loop_remap_clock_and_sigint_on_both(tmp_path, ros_domain_env):
    src, out = tmp_path / "src", tmp_path / "out"
    _write_bag(src, seconds=0.5, tf_static=False)
    rec = _start(
        "bags.cli.record", str(out), "/image", "/clock", "--stamp", "header", env=ros_domain_env
    )
    _wait_line(rec, "recording to")
    rep = _start(
        "bags.cli.replay",
        str(src),
        "--topics",
        "/camera/image_raw",
        "--remap",
        "/camera/image_raw:=/image",
        "--clock",
        "--loop",
        "--rate",
        "4",
        "--wait-for-subscribers",
        env=ros_domain_env,
    )
    _wait_line(rep, "loop 3", timeout=30)  # progress line (not a tty: printed per loop)
    rep.send_signal(signal.SIGINT)
    _, rep_err = rep.communicate(timeout=30)
    assert rep.returncode == 0, rep_err
    assert "Traceback" not in rep_err
    rec.send_signal(signal.SIGTERM)
    _, rec_err = rec.communicate(timeout=30)
    assert rec.returncode == 0, rec_err

    sent = [m.data for m in _by_topic(src)["/camera/image_raw"]]
    got = _in_write_order(out, "/image")
    images = [data for _, data in got]
    assert len(images) >= 2 * len(sent)
    expected_order = (sent * (len(images) // len(sent) + 1))[: len(images)]
    assert all(_same_cdr(g, e) for g, e in zip(images, expected_order, strict=True))
    # --stamp header: each image's log time is its header stamp
    with BagReader(src) as bag:
        headers = [bag.deserialize(m).header.stamp for m in bag.messages(["/camera/image_raw"])]
    stamps = [h.sec * 10**9 + h.nanosec for h in headers]
    assert [t for t, _ in got] == (stamps * (len(images) // len(sent) + 1))[: len(images)]
    # /clock carries bag time: inside the bag's span, and it jumps back at each loop
    with BagReader(src) as bag:
        first, last = bag.start_ns, bag.end_ns
    with BagReader(out) as bag:
        clocks = [bag.deserialize(m).clock for m in bag.messages(["/clock"])]
    ns = np.array([c.sec * 10**9 + c.nanosec for c in clocks], dtype=np.int64)
    assert ns.min() >= first and ns.max() <= last
    assert np.count_nonzero(np.diff(ns) < 0) >= 2


@pytest.mark.dds
def test_record_sigint_without_publishers_leaves_a_readable_empty_bag(tmp_path, ros_domain_env):
    out = tmp_path / "empty"
    rec = _start("bags.cli.record", str(out), "/nobody/publishes", env=ros_domain_env)
    _wait_line(rec, "recording to")
    rec.send_signal(signal.SIGINT)
    stdout, stderr = rec.communicate(timeout=30)
    assert rec.returncode == 0, stderr
    assert "recorded 0 messages" in stdout
    with BagReader(out) as bag:
        assert bag.message_count == 0 and bag.topics == {}
    assert (out / "metadata.yaml").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


@pytest.mark.dds
def test_subscription_qos_matches_each_publisher(ros_domain_env):
    import rclpy
    from rclpy.qos import (
        DurabilityPolicy,
        QoSProfile,
        ReliabilityPolicy,
        qos_profile_sensor_data,
    )
    from std_msgs.msg import String

    from bags.cli.record import subscription_qos

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    try:
        node = rclpy.create_node("qos_probe", context=ctx)
        node.create_publisher(String, "/be", qos_profile_sensor_data)
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node.create_publisher(String, "/tl", latched)
        node.create_publisher(String, "/rel", 10)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not all(
            node.get_publishers_info_by_topic(t) for t in ("/be", "/tl", "/rel")
        ):
            time.sleep(0.05)
        be, kind_be = subscription_qos(node.get_publishers_info_by_topic("/be"), 7)
        tl, kind_tl = subscription_qos(node.get_publishers_info_by_topic("/tl"), 7)
        rel, kind_rel = subscription_qos(node.get_publishers_info_by_topic("/rel"), 7)
        assert (kind_be, kind_tl, kind_rel) == ("sensor", "latched", "reliable")
        assert be.reliability == ReliabilityPolicy.BEST_EFFORT and be.depth == 7
        assert tl.durability == DurabilityPolicy.TRANSIENT_LOCAL
        assert tl.reliability == ReliabilityPolicy.RELIABLE
        assert rel.durability == DurabilityPolicy.VOLATILE
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.mark.dds
def test_record_write_error_keeps_what_was_recorded(tmp_path, ros_domain_env, limited_run):
    """Files cannot grow past 2 MiB (RLIMIT_FSIZE: writes beyond fail with EFBIG, as on a
    full disk): the recorder stops at the failed write, closes the bag with what is on
    disk and says so in one line."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    out = tmp_path / "rec"
    argv = ["-m", "bags.cli.record", str(out), "/cam", "-q"]
    rec = limited_run(argv, 2 * 2**20, popen=True, env=ros_domain_env)
    rng = np.random.default_rng(1)
    sent = []
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_domain_env["ROS_DOMAIN_ID"]))
    try:
        node = rclpy.create_node("cam", context=ctx)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        pub = node.create_publisher(Image, "/cam", qos)
        deadline = time.monotonic() + 10
        while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)  # the recorder's reader matches this writer
        # 300 kB images (incompressible): the 2nd MCAP chunk (past 2 MiB) cannot be written
        for i in range(40):
            if rec.poll() is not None:
                break
            img = rng.integers(0, 256, (480, 640), dtype=np.uint8)
            msg = array_to_image(img, "mono8", make_header(START_NS + i * 10**8, "cam"))
            pub.publish(msg)
            sent.append(img.tobytes())
            time.sleep(0.05)
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    try:
        stdout, stderr = rec.communicate(timeout=30)
    finally:
        rec.kill()  # if it did not stop by itself (no-op once it has exited)
    assert rec.returncode == 1, stderr
    assert stdout == ""
    _one_error_line(stderr, f"owl_record: error: cannot write bag {out}: File too large; closed")
    with BagReader(out) as bag:  # a finished bag: read without recovery
        got = [bag.deserialize(raw) for raw in bag.messages()]
    assert 1 <= len(got) < len(sent)
    assert f"closed it with the {len(got)} messages written before" in stderr
    # the first images, in order (rclpy leaves CDR padding bytes undefined: compare fields)
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in got]
    assert stamps == [START_NS + i * 10**8 for i in range(len(got))]
    assert [bytes(m.data) for m in got] == sent[: len(got)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]
