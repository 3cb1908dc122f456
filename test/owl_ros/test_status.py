"""The pure status builder: levels, messages and the published key names from a snapshot."""

from __future__ import annotations

import math

import numpy as np

from msg_adapters.diagnostics import Level
from owl_ros.counters import Counters
from owl_ros.status import StatusInputs, build_status


def _inputs(**kw: object) -> StatusInputs:
    base: dict[str, object] = {
        "span_s": 2.0,
        "counts": Counters(
            images=60, imu=800, camera_info=60, processed=58, frames_with_points=50
        ),
        "totals": Counters(images=600, processed=580, frames_with_points=500),
        "points": [100, 300],
        "process_s": [0.01, 0.03],
        "camera_known": True,
    }
    base.update(kw)
    return StatusInputs(**base)  # type: ignore[arg-type]


def test_healthy_window() -> None:
    inp, proc, gyro = build_status(_inputs(gyro_bias=np.array([0.001, 0.0, -0.002])))
    assert [r.name for r in (inp, proc, gyro)] == ["owl: input", "owl: processing", "owl: gyro"]
    assert (inp.level, inp.message) == (Level.OK, "inputs OK")
    assert (proc.level, proc.message) == (Level.OK, "29.0 frames/s, 200 points/frame")
    values = proc.value_map()
    assert values["frames_processed_total"] == "580"
    assert float(values["processing_ms_mean"]) == 20.0
    assert float(values["processing_ms_max"]) == 30.0
    assert math.isnan(float(values["latency_ms_p50"]))  # no latency recorded
    assert inp.value_map()["image_rate_hz"] == "30"
    assert gyro.level == Level.OK and gyro.message == "bias [0.001, 0, -0.002] rad/s"
    assert gyro.value_map()["bias_z_rad_s"] == "-0.002"


def test_problems_raise_the_level_and_are_named() -> None:
    counts = Counters(images=10, imu=0, processed=0, dropped_queue_full=3)
    inp, proc, gyro = build_status(
        _inputs(
            counts=counts,
            camera_known=False,
            wrong_type=["/imu: std_msgs/msg/String"],
            last_empty_reason="IMU gap",
        )
    )
    assert inp.level == Level.ERROR
    assert inp.message == (
        "no camera_info received; wrong message type: /imu: std_msgs/msg/String; no IMU"
    )
    assert proc.level == Level.WARN
    assert proc.message == (
        "no frames processed: IMU gap; 3 frames dropped (queue full, newest wins)"
    )
    assert gyro.level == Level.WARN  # images without IMU


def test_empty_window_rates_are_nan() -> None:
    inp, _, _ = build_status(_inputs(span_s=math.nan))
    assert math.isnan(float(inp.value_map()["image_rate_hz"]))
