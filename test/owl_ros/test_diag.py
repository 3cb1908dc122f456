"""owl_diag: /diagnostics of a running owl_node as a table, over real DDS (one node)."""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest

from msg_adapters.diagnostics import Level, StatusRecord
from owl_ros.tools import diag

pytestmark = [pytest.mark.dds]


def test_table_layout() -> None:
    recs = [
        StatusRecord("owl: input", Level.WARN, "no images", (("image_topic", "/cam"),), "/owl"),
        StatusRecord("owl: gyro", Level.OK, "bias", (), "/owl"),
    ]
    lines = diag.table(2_500_000_000, recs, values=True)
    assert lines[0] == "--- 2.500 s, 2 statuses"
    assert lines[1].split() == ["LEVEL", "NAME", "HARDWARE_ID", "MESSAGE"]
    assert lines[2].split() == ["WARN", "owl:", "input", "/owl", "no", "images"]
    assert lines[3].split() == ["image_topic", "/cam"]
    assert lines[4].split()[0] == "OK" and len(lines) == 5


def test_owl_diag_prints_a_running_node_and_times_out_alone(ros_domain_env) -> None:
    cmd = [sys.executable, "-m", "owl_ros.tools.diag", "--timeout", "2"]
    alone = subprocess.run(cmd, env=ros_domain_env, capture_output=True, text=True, timeout=60)
    assert alone.returncode == 1 and alone.stdout == ""
    assert alone.stderr.strip().splitlines() == [
        "owl_diag: error: nothing on /diagnostics within 2 s "
        "(is the node running, on this ROS_DOMAIN_ID?)"
    ]
    node = subprocess.Popen(
        [sys.executable, "-m", "owl_ros.node", "--ros-args", "-r", "image:=/cam/img",
         "-p", "diagnostics_period_s:=0.5"],
        env=ros_domain_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        run = subprocess.run(
            [*cmd[:3], "--once", "--values", "--timeout", "30", "--name", "owl:"],
            env=ros_domain_env, capture_output=True, text=True, timeout=90,
        )  # fmt: skip
    finally:
        node.send_signal(signal.SIGINT)
        node.wait(timeout=30)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[0].startswith("--- ") and lines[0].endswith(" 3 statuses"), lines
    name_at, hw_at = lines[1].index("NAME"), lines[1].index("HARDWARE_ID")
    rows = {ln[name_at:hw_at].strip(): ln for ln in lines[2:] if not ln.startswith("    ")}
    assert set(rows) == {"owl: input", "owl: processing", "owl: gyro"}, lines
    assert rows["owl: input"].split()[0] in ("WARN", "ERROR")
    assert all(" /owl " in row for row in rows.values())  # hardware_id: the node
    keys = dict([*ln.split(maxsplit=1), ""][:2] for ln in lines if ln.startswith("    "))
    assert keys["image_topic"] == "/cam/img" and keys["imu_topic"] == "/imu"
    assert keys["camera_info_topic"] == "/camera_info"
