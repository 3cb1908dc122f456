"""owl_calibrate on rendered bags: images + IMU in, extrinsic, offset and bias out."""

from __future__ import annotations

import math
import os
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bags.cli.importers.cli import main as import_main
from bags.cli.make_bag import write_bag
from bags.sim import scenarios
from bags.sim.scenarios import SimOptions
from bags.sim.sensors import ImuOptions, random_camera_to_imu
from owl_core.geometry import matrix_to_quat_xyzw, quat_xyzw_to_matrix, so3_log
from owl_ros import calibrate
from owl_ros.params import build_options
from owl_ros.process import _params_file

# 2 s at 30 Hz, 320x240: the shortest rotation_only recording that keeps the rotation
# within 0.3 deg and the offset within 2 ms (10 random mounts: see the README)
BAG = SimOptions(seconds=2.0, rate_hz=30.0, width=320, height=240, supersample=1)


@pytest.fixture(scope="module")
def rich_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray, float, tuple]:
    rng = np.random.default_rng(15)
    r = random_camera_to_imu(rng)
    offset = float(rng.uniform(-0.05, 0.05))
    bias = tuple(float(b) for b in rng.uniform(-0.02, 0.02, 3))
    imu = ImuOptions(
        camera_to_imu_xyzw=tuple(matrix_to_quat_xyzw(r)), time_offset_s=offset, gyro_bias=bias
    )
    sim = scenarios.get("rotation_only").simulate(replace(BAG, imu=imu, seed=15))
    path = tmp_path_factory.mktemp("calib") / "rich"
    write_bag(sim, path)
    return path, r, offset, bias


@pytest.mark.slow
def test_recovers_the_extrinsic_and_offset(
    rich_bag: tuple[Path, np.ndarray, float, tuple],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    path, r, offset, bias = rich_bag
    out = tmp_path / "calib.yaml"
    assert calibrate.main([str(path), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    q = re.search(r"camera_to_imu_rotation_xyzw:=\[([^\]]+)\]", text)
    d = re.search(r"imu_time_offset:=(\S+)", text)
    assert q and d, text
    r_est = quat_xyzw_to_matrix(np.array([float(v) for v in q.group(1).split(",")]))
    err_deg = math.degrees(float(np.linalg.norm(so3_log(r_est @ r.T))))
    assert err_deg < 0.3
    assert abs(float(d.group(1)) - offset) < 2e-3
    assert "1-sigma" in text and "deg" in text and "ms" in text
    # the bag's /tf_static holds the true rotation: the reported angle is the error
    angle = re.search(r"angle to /tf_static's rotation: (\S+) deg", text)
    assert angle and abs(float(angle.group(1)) - err_deg) < 2e-3
    # the YAML is a params file owl_process / the node accept, with the same values
    values = _params_file(str(out))
    opts = build_options(values)
    np.testing.assert_allclose(
        quat_xyzw_to_matrix(np.array(opts.engine.camera_to_imu_rotation_xyzw)), r_est, atol=1e-5
    )
    assert opts.engine.imu_time_offset_s == pytest.approx(float(d.group(1)), abs=1e-5)
    np.testing.assert_allclose(opts.engine.initial_bias_imu, bias, atol=2e-3)
    # an existing output is not overwritten
    before = out.read_text()
    assert calibrate.main([str(path), "-o", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    assert out.read_text() == before
    # --overwrite replaces it whole (temporary file + os.replace: none left behind)
    out.write_text("old\n")
    assert calibrate.main([str(path), "-o", str(out), "--overwrite", "-q"]) == 0
    capsys.readouterr()
    assert out.read_text() == before  # the same estimate again
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calib.yaml"]


@pytest.mark.slow
def test_one_axis_recording_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sim = scenarios.get("pan_only").simulate(
        replace(BAG, seconds=1.0, rate_hz=25.0, supersample=1)
    )
    path = tmp_path / "pan"
    write_bag(sim, path)
    out = tmp_path / "calib.yaml"
    assert calibrate.main([str(path), "-o", str(out)]) == 3
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "one axis only" in lines[0] and "tilt" in lines[0]
    assert captured.out == "" and not out.exists()


def test_bad_input_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert calibrate.main([str(tmp_path / "missing")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("owl_calibrate: error:")
    assert calibrate.main([str(tmp_path), "--max-offset", "-1"]) == 2
    assert "max_offset_s" in capsys.readouterr().err


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_output_that_is_or_lies_in_the_input_is_refused_even_with_overwrite(
    rich_bag: tuple[Path, np.ndarray, float, tuple],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A bag that calibrates: -o naming its .mcap with --overwrite replaced the recording
    with the YAML. Every case is refused before reading the bag."""
    bag = rich_bag[0]
    before = _files(bag)
    mcap = bag / "rich.mcap"
    cases = [
        ([str(bag), "-o", str(mcap), "--overwrite"], "is inside the input"),
        ([str(bag), "-o", str(bag / "metadata.yaml"), "--overwrite"], "inside"),
        ([str(mcap), "-o", str(mcap), "--overwrite"], "the output is the input"),
        ([str(bag), "-o", str(bag.parent), "--overwrite"], "contains the input"),
        # checked before calibrating (it used to calibrate, then crash on the write)
        ([str(bag), "-o", str(tmp_path / "missing" / "c.yaml")], "does not exist"),
        ([str(bag), "-o", str(tmp_path), "--overwrite"], "is a directory"),
    ]
    for argv, what in cases:
        assert calibrate.main(argv) == 2, argv
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("owl_calibrate: error:"), lines
        assert what in lines[0] and argv[2] in lines[0], lines
        assert captured.out == ""  # refused before calibrating
    assert _files(bag) == before
    assert not (tmp_path / "missing").exists()


def test_topic_of_the_wrong_type_or_encoding_is_one_line(
    rich_bag: tuple[Path, np.ndarray, float, tuple], capsys: pytest.CaptureFixture[str]
) -> None:
    bag = rich_bag[0]
    cases = [
        # an IMU topic as the images: was "has 0 frames"
        (
            ["--image-topic", "/imu/data"],
            "image topic /imu/data has type sensor_msgs/msg/Imu, "
            "expected sensor_msgs/msg/Image or sensor_msgs/msg/CompressedImage",
        ),
        # images as the IMU: was an AttributeError traceback
        (
            ["--imu-topic", "/camera/image_raw"],
            "imu topic /camera/image_raw has type "
            "sensor_msgs/msg/Image, expected sensor_msgs/msg/Imu",
        ),
        (
            ["--camera-info-topic", "/imu/data"],
            "camera_info topic /imu/data has type "
            "sensor_msgs/msg/Imu, expected sensor_msgs/msg/CameraInfo",
        ),
        # a 32FC1 range image: was an UnsupportedEncodingError traceback
        (
            ["--image-topic", "/ground_truth/range"],
            "image topic /ground_truth/range: image.encoding '32FC1'",
        ),
    ]
    for extra, what in cases:
        assert calibrate.main([str(bag), *extra]) == 1, extra
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("owl_calibrate: error:"), lines
        assert what in lines[0], lines


SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "realsense_walk"


@pytest.mark.slow
def test_realsense_walk_refused_and_within_its_sigma_of_kalibr(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The real walk turns mostly about one axis (RMS 0.154, 0.082, 0.056 rad/s about its
    principal axes): the default 0.1 rad/s second-axis threshold refuses it. Forced with a
    0.05 rad/s threshold, the estimate must lie within 3 of its own 1-sigma (the norm over
    the three axes) of Kalibr's T_BS, and the offset inside the search range: a bound the
    estimate states itself (measured: 6.99 deg against a 4.0 deg 1-sigma norm, -53 ms)."""
    if not (SHARED / "mav0").is_dir():
        msg = f"shared recording realsense_walk not found ({SHARED})"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    bag = tmp_path / "walk"
    assert import_main([str(SHARED), str(bag), "-q"]) == 0  # /tf_static = Kalibr's T_BS
    assert calibrate.main([str(bag)]) == 3
    assert "one axis only" in capsys.readouterr().err
    assert calibrate.main([str(bag), "--min-second-axis-rate", "0.05"]) == 0
    text = capsys.readouterr().out
    sig = re.search(r"1-sigma about IMU x y z: \[([^\]]+)\] deg", text)
    angle = re.search(r"angle to /tf_static's rotation: (\S+) deg", text)
    offset = re.search(r"imu_time_offset:=(\S+)", text)
    assert sig and angle and offset, text
    sigma_norm = float(np.linalg.norm([float(v) for v in sig.group(1).split(",")]))
    assert float(angle.group(1)) < 3.0 * sigma_norm
    assert abs(float(offset.group(1))) < 0.2
