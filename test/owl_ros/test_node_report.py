"""owl_ros.node_report and what node ``owl`` says: start-up line, parameter errors in one
line, throttled warnings naming the silent topic (one real owl_node process)."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from rclpy.parameter import Parameter

from owl_ros import node_report
from owl_ros.node_report import SilenceWatch

NODE = [sys.executable, "-m", "owl_ros.node"]
CONFIG = Path(__file__).resolve().parents[2] / "config" / "owl.yaml"


def test_integer_overrides_become_doubles_for_double_parameters() -> None:
    overrides = {
        "pixel_noise_px": Parameter("pixel_noise_px", Parameter.Type.INTEGER, 1),
        "camera_to_imu_rotation_xyzw": Parameter(
            "camera_to_imu_rotation_xyzw", Parameter.Type.INTEGER_ARRAY, [0, 0, 0, 1]
        ),
        "max_features": Parameter("max_features", Parameter.Type.INTEGER, 100),
    }
    assert sorted(node_report.coerce_overrides(overrides)) == [
        "camera_to_imu_rotation_xyzw",
        "pixel_noise_px",
    ]
    assert overrides["pixel_noise_px"].type_ == Parameter.Type.DOUBLE
    assert overrides["camera_to_imu_rotation_xyzw"].value == [0.0, 0.0, 0.0, 1.0]
    assert overrides["max_features"].type_ == Parameter.Type.INTEGER  # an int stays an int


def test_unknown_parameters_typo_is_an_error_with_the_close_match() -> None:
    errors, warnings = node_report.unknown_parameters(
        ["max_feature", "use_sim_time", "qos_overrides./x.depth", "frobnicate", "max_features"]
    )
    assert errors == ["parameter max_feature: unknown parameter (did you mean max_features?)"]
    assert warnings == ["parameter frobnicate: unknown parameter, ignored"]


def test_silence_watch_names_the_topic_and_throttles() -> None:
    watch = SilenceWatch({"image": "/cam/img", "imu": "/imu"}, after_s=3.0, period_s=10.0)
    assert watch.check(0.0, {"image": 0, "imu": 0}, "") == []
    assert watch.check(2.0, {"image": 0, "imu": 5}, "") == []  # IMU moved: not silent
    lines = watch.check(3.5, {"image": 0, "imu": 5}, "")
    assert lines == [
        "image topic /cam/img: nothing received for 4 s "
        "(check the topic name / remap and the publisher's QoS)"
    ]
    assert watch.check(6.0, {"image": 0, "imu": 5}, "") != []  # imu now silent 4 s
    assert watch.check(7.0, {"image": 0, "imu": 5}, "") == []  # both said < 10 s ago
    assert len(watch.check(13.6, {"image": 0, "imu": 5}, "")) == 1  # image again
    assert watch.check(14.0, {"image": 1, "imu": 6}, "no points: no gyro samples") == [
        "frames without points: no points: no gyro samples"
    ]
    # a camera that stopped is said per topic ("nothing since message N"), not again as
    # frames without points
    stopped = "no frames processed: no images in this period (1 received, 0 processed since start)"
    lines = watch.check(30.0, {"image": 1, "imu": 6}, stopped)
    assert lines and not any(line.startswith("frames without points") for line in lines)


def test_silence_watch_memory_stays_bounded() -> None:
    """Reasons carry changing values (a stamp, a count): what was said a period ago is
    forgotten, so a node running for days keeps a handful of entries, not one per line."""
    watch = SilenceWatch({"image": "/cam/img"}, after_s=3.0, period_s=10.0)
    for k in range(200):
        reason = f"no points: image stamp {k} ns repeated"
        assert watch.check(10.0 * k, {"image": k}, reason) == [f"frames without points: {reason}"]
    assert len(watch._said) <= 2


def _node(
    args: list[str], env: dict[str, str], seconds: float, until: str = "", after_s: float = 0.0
) -> tuple[int, str]:
    """Run owl_node; stop it ``after_s`` s after a line containing ``until`` (at most
    ``seconds`` s in all; 0 = let it exit by itself). Returns (exit status, output)."""
    proc = subprocess.Popen(
        [*NODE, "--ros-args", *args], env=env, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    lines: list[str] = []
    seen = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            if until and until in line:
                seen.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    if seconds > 0:
        if until:
            seen.wait(seconds)
            time.sleep(after_s)
        else:
            time.sleep(seconds)
        proc.send_signal(signal.SIGINT)
    proc.wait(timeout=60)
    reader.join(timeout=10)
    return proc.returncode, "".join(lines)


@pytest.mark.dds
def test_node_bad_parameters_and_files_one_line(ros_domain_env: dict[str, str]) -> None:
    for args, expect in (
        (["-p", "max_feature:=100"], "did you mean max_features?"),
        (["--params-file", "/nonexistent.yaml"], "--params-file /nonexistent.yaml: no such"),
    ):
        code, out = _node(args, ros_domain_env, 0)
        lines = out.strip().splitlines()
        assert code == 2 and len(lines) == 1 and "Traceback" not in out, out
        assert lines[0].startswith("owl_node: error:") and expect in lines[0], out


@pytest.mark.dds
def test_node_start_up_line_and_silent_topic_warnings(
    ros_domain_env: dict[str, str], tmp_path: Path
) -> None:
    env = {**ros_domain_env, "RCUTILS_CONSOLE_OUTPUT_FORMAT": "[{severity}] {message}"}
    # an integer for a double and an integer array for a double array are accepted
    args = ["-r", "image:=/cam/img", "-r", "__ns:=/robot", "-p", "pixel_noise_px:=1"]
    args += ["-p", "camera_to_imu_rotation_xyzw:=[0,0,0,1]", "-p", "diagnostics_period_s:=0.5"]
    # wait (the machine may be loaded) for the first silence warning, then 4 s more
    code, out = _node(args, env, 60.0, until="image topic /cam/img: nothing", after_s=4.0)
    assert code == 0, out
    lines = out.splitlines()
    (start,) = [ln for ln in lines if ln.startswith("[INFO] listening on")]
    assert "image /cam/img, camera_info /robot/camera_info, imu /robot/imu" in start
    assert "publishing /robot/owl/points, /robot/owl/heading" in start
    assert "/robot/owl/heading_with_covariance, /robot/owl/gyro_bias, /diagnostics" in start
    assert "camera_to_imu_rotation_xyzw [0, 0, 0, 1] from parameter" in start
    assert "speed from none" in start
    silent = [ln for ln in lines if ln.startswith("[WARN] image topic /cam/img: nothing")]
    # silent after 3 s, then repeated at most every 10 s: once in the 4 s that followed
    assert len(silent) == 1, out
    assert any(ln.startswith("[WARN] imu topic /robot/imu: nothing") for ln in lines), out
    # no extrinsic given: the identity, with a warning saying how to set it
    code, out = _node([], env, 60.0, until="listening on", after_s=0.5)
    assert "from default (identity)" in out and "using the identity" in out, out
    # a parameter file as owl_calibrate writes it ('/**'), and the shipped one (no
    # rotation: it does not hide TF's), reach the node in a namespace too
    calib = tmp_path / "calib.yaml"
    calib.write_text(
        "/**:\n  ros__parameters:\n    camera_to_imu_rotation_xyzw: [0.0, 0.0, 0.6, 0.8]\n"
    )
    expected = ((calib, "[0, 0, 0.6, 0.8] from parameter"), (CONFIG, "[0, 0, 0, 1] from default"))
    for params, says in expected:
        args = ["-r", "__ns:=/robot1", "--params-file", str(params)]
        code, out = _node(args, env, 60.0, until="listening on", after_s=0.5)
        (start,) = [ln for ln in out.splitlines() if ln.startswith("[INFO] listening on")]
        assert "imu /robot1/imu" in start and f"camera_to_imu_rotation_xyzw {says}" in start, out
