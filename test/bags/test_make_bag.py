"""owl_make_bag: the bag holds exactly what the in-memory simulation renders (read back with
rosbags and with the `mcap` reader), and bad input gives one line and leaves nothing."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from bags.cli.make_bag import BARREL, main
from bags.io import BagReader
from bags.sim import scenarios
from bags.sim.scenarios import SimOptions
from bags.sim.sensors import ImuOptions

ARGS = ["--seconds", "0.5", "--rate", "10", "--width", "160", "--height", "120", "--quiet"]


def _sim(name: str, **kw) -> scenarios.Simulation:
    imu = ImuOptions(
        time_offset_s=kw.pop("time_offset_s", 0.0), gyro_bias=kw.pop("gyro_bias", (0, 0, 0))
    )
    opts = SimOptions(seconds=0.5, rate_hz=10.0, width=160, height=120, imu=imu)
    return scenarios.get(name).simulate(replace(opts, **kw))


def test_bag_round_trip_matches_simulation(tmp_path: Path, mcap_read) -> None:
    out = tmp_path / "mover_bag"
    argv = [
        "mover",
        str(out),
        *ARGS,
        "--time-offset",
        "0.005",
        "--gyro-bias",
        "0.01",
        "--seed",
        "4",
    ]
    assert main(argv) == 0
    b = 0.01 / math.sqrt(3)
    sim = _sim("mover", time_offset_s=0.005, gyro_bias=(b, b, b), seed=4)
    frames = list(sim.frames())
    with BagReader(out) as bag:
        topics = bag.topics
        assert {t: (i.msgtype, i.count) for t, i in topics.items()} == {
            "/camera/image_raw": ("sensor_msgs/msg/Image", 6),
            "/camera/camera_info": ("sensor_msgs/msg/CameraInfo", 6),
            "/imu/data": ("sensor_msgs/msg/Imu", sim.imu.stamp_ns.size),
            "/tf_static": ("tf2_msgs/msg/TFMessage", 1),
            "/ground_truth/twist": ("geometry_msgs/msg/TwistStamped", 6),
            "/ground_truth/range": ("sensor_msgs/msg/Image", 6),
            "/ground_truth/moving_mask": ("sensor_msgs/msg/Image", 6),
        }
        assert topics["/tf_static"].qos_kind == "latched"
        assert topics["/imu/data"].qos_kind == "sensor"
        raws = list(bag.messages())
        assert [r.log_time_ns for r in raws] == sorted(r.log_time_ns for r in raws)
        assert raws[0].topic == "/tf_static"
        msgs = {t: [] for t in topics}
        for raw in raws:
            msgs[raw.topic].append((raw.log_time_ns, bag.deserialize(raw)))

    for k, f in enumerate(frames):
        ns, img = msgs["/camera/image_raw"][k]
        stamp = img.header.stamp.sec * 10**9 + img.header.stamp.nanosec
        assert ns == stamp == f.stamp_ns and img.header.frame_id == "camera_optical_frame"
        assert (img.encoding, img.width, img.height, img.step) == ("mono8", 160, 120, 160)
        np.testing.assert_array_equal(np.asarray(img.data).reshape(120, 160), f.image)
        _, rng = msgs["/ground_truth/range"][k]
        assert (rng.encoding, rng.step, rng.is_bigendian) == ("32FC1", 640, 0)
        got = np.frombuffer(bytes(rng.data), dtype="<f4").reshape(120, 160)
        np.testing.assert_array_equal(got, f.range_m)
        _, mask = msgs["/ground_truth/moving_mask"][k]
        np.testing.assert_array_equal(np.asarray(mask.data).reshape(120, 160) == 255, f.mask)
        _, tw = msgs["/ground_truth/twist"][k]
        assert tw.header.stamp == img.header.stamp
        lin, ang = tw.twist.linear, tw.twist.angular
        np.testing.assert_array_equal([lin.x, lin.y, lin.z], f.velocity)
        np.testing.assert_array_equal([ang.x, ang.y, ang.z], f.omega)
        _, info = msgs["/camera/camera_info"][k]
        np.testing.assert_array_equal(info.k, np.asarray(sim.camera.K).reshape(-1))
        assert info.distortion_model == "plumb_bob" and not np.any(info.d)
    assert sum(f.mask.sum() for f in frames) > 0

    imu = msgs["/imu/data"]
    np.testing.assert_array_equal([ns for ns, _ in imu], sim.imu.stamp_ns)
    gyro = np.array(
        [[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for _, m in imu]
    )
    np.testing.assert_array_equal(gyro, sim.imu.angular_velocity)
    acc = np.array(
        [
            [m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]
            for _, m in imu
        ]
    )
    np.testing.assert_array_equal(acc, sim.imu.linear_acceleration)
    assert imu[0][1].header.frame_id == "imu_link"
    assert imu[0][1].orientation_covariance[0] == -1.0  # REP 145: no orientation
    # IMU stamp = camera stamp + offset: the first IMU sample precedes the first image
    assert sim.imu_time_offset_ns == 5_000_000
    assert imu[0][0] < frames[0].stamp_ns + 5_000_000 - 50_000_000

    ((_, tf),) = msgs["/tf_static"]
    t = tf.transforms[0]
    assert (t.header.frame_id, t.child_frame_id) == ("imu_link", "camera_optical_frame")
    q = t.transform.rotation
    assert (q.x, q.y, q.z, q.w) == (-0.5, 0.5, -0.5, 0.5)

    # the independent mcap reader sees the same messages
    m = mcap_read(out)
    assert len(m) == len(raws)
    assert [(x.topic, x.log_time_ns, x.data) for x in m] == [
        (r.topic, r.log_time_ns, r.data) for r in raws
    ]
    first_img = next(x.decoded for x in m if x.topic == "/camera/image_raw")
    np.testing.assert_array_equal(
        np.frombuffer(bytes(first_img.data), np.uint8).reshape(120, 160), frames[0].image
    )
    meta = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    opts = json.loads(meta["custom_data"]["owl_make_bag"])
    assert opts["scenario"] == "mover" and opts["seed"] == 4 and opts["time_offset"] == 0.005


def test_rgb_distorted_bag(tmp_path: Path, mcap_read) -> None:
    out = tmp_path / "rgb"
    argv = ["street", str(out), *ARGS, "--encoding", "rgb8", "--distortion", "barrel"]
    assert main(argv) == 0
    sim = _sim("street", encoding="rgb8", distortion=BARREL)
    f0 = sim.frame(0)
    with BagReader(out) as bag:
        assert "/ground_truth/moving_mask" not in bag.topics
        img = bag.deserialize(next(bag.messages(["/camera/image_raw"])))
        info = bag.deserialize(next(bag.messages(["/camera/camera_info"])))
    assert (img.encoding, img.step) == ("rgb8", 480)
    np.testing.assert_array_equal(np.asarray(img.data).reshape(120, 160, 3), f0.image)
    np.testing.assert_array_equal(info.d, BARREL)
    assert len(mcap_read(out)) > 0


def _one_line_error(capsys, argv, match: str, code: int = 2) -> None:
    assert main(argv) == code
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert match in err, err


def test_bad_input_one_line_nothing_written(tmp_path: Path, capsys) -> None:
    out = tmp_path / "bag"
    _one_line_error(capsys, ["nope", str(out)], "unknown scenario 'nope'")
    _one_line_error(capsys, ["street", str(out), "--rate", "-5"], "rate out of range: -5.0")
    _one_line_error(capsys, ["street", str(out), "--width", "0"], "width must be a positive")
    _one_line_error(capsys, ["street", str(out), "--height", "x"], "--height")
    _one_line_error(capsys, ["street", str(out), "--gyro-bias", "1,2"], "--gyro-bias")
    _one_line_error(capsys, ["street"], "need SCENARIO and OUT_BAG")
    _one_line_error(
        capsys, ["street", str(out), "--rolling-shutter-readout", "-1"], "readout must be in"
    )
    assert list(tmp_path.iterdir()) == []
    assert main(["still", str(out), *ARGS]) == 0
    before = (out / "metadata.yaml").read_text()
    _one_line_error(capsys, ["still", str(out), *ARGS], "exists", code=1)  # as every tool
    assert (out / "metadata.yaml").read_text() == before
    assert main(["still", str(out), *ARGS, "--seconds", "0.3", "--overwrite"]) == 0
    with BagReader(out) as bag:
        assert bag.topics["/camera/image_raw"].count == 4
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]  # no temporary left


def test_write_error_one_line_and_no_temporary_left(tmp_path: Path, limited_run) -> None:
    # files cannot grow past 100 kB: the first MCAP chunk (1 MiB of messages) written
    # while rendering fails with EFBIG, as it fails with ENOSPC on a full disk
    out = tmp_path / "bag"
    size = ["--width", "320", "--height", "240"]  # 3 images of 75-300 kB a frame
    res = limited_run(["-m", "bags.cli.make_bag", "cube", str(out), *ARGS, *size], 100_000)
    assert res.returncode == 1
    assert res.stderr.strip() == f"owl_make_bag: error: cannot write bag {out}: File too large"
    assert list(tmp_path.iterdir()) == []  # the temporary output is removed


def test_rolling_shutter_option_renders_rows_at_their_times(tmp_path: Path) -> None:
    out = tmp_path / "rs"
    assert main(["brisk", str(out), *ARGS, "--rolling-shutter-readout", "0.03"]) == 0
    sim = _sim("brisk", rolling_shutter_readout_s=0.03)
    with BagReader(out) as bag:
        meta = json.loads(bag.custom_data["owl_make_bag"])
        first = bag.deserialize(next(bag.messages(["/camera/image_raw"])))
    assert meta["rolling_shutter_readout"] == 0.03
    image = np.frombuffer(bytes(first.data), dtype=np.uint8).reshape(first.height, first.width)
    np.testing.assert_array_equal(image, sim.frame(0).image)


def test_gyro_bias_scalar_is_magnitude_along_diagonal(tmp_path: Path) -> None:
    out = tmp_path / "b"
    assert main(["still", str(out), *ARGS, "--gyro-bias", "0.03", "--gyro-noise", "0"]) == 0
    with BagReader(out) as bag:
        m = bag.deserialize(next(bag.messages(["/imu/data"])))
    w = np.array([m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z])
    np.testing.assert_allclose(w, [0.03 / math.sqrt(3)] * 3, rtol=1e-12)


def test_list_help_and_module_entry(tmp_path: Path, capsys) -> None:
    assert main(["--list"]) == 0
    listing = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in listing] == scenarios.names()
    assert main(["--help"]) == 0
    assert "--gyro-bias" in capsys.readouterr().out
    proc = subprocess.run(
        [sys.executable, "-m", "bags.cli.make_bag", "street", str(tmp_path / "b"), "--rate", "0"],
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip() == "owl_make_bag: error: rate out of range: 0.0"
    assert not (tmp_path / "b").exists()
