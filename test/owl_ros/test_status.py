"""The pure status builder: levels, messages and the published key names from a snapshot."""

from __future__ import annotations

import math
from dataclasses import replace

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


def test_an_engine_slower_than_the_camera_is_named_with_what_helps() -> None:
    # 30 images/s, 20 processed, the engine 45 ms a frame: the drops are not a burst
    counts = Counters(images=60, imu=800, camera_info=60, processed=40, frames_with_points=40)
    slow = _inputs(counts=replace(counts, dropped_queue_full=20), process_s=[0.045, 0.045])
    proc = build_status(slow)[1]
    assert proc.level == Level.WARN
    assert proc.message.endswith(
        "20 frames dropped (queue full, newest wins): the engine takes 45 ms a frame, images "
        "arrive every 33 ms (fewer max_features keep up; the README's 'Cost per frame' says "
        "what each setting costs)"
    )
    # with the dense stage on, its rate cap is the other lever
    dense = build_status(replace(slow, dense_max_rate_hz=0.0))[1].message
    assert "(fewer max_features or a lower dense_max_rate_hz (now none) keep up;" in dense
    capped = build_status(replace(slow, dense_max_rate_hz=10.0))[1].message
    assert "dense_max_rate_hz (now 10 Hz) keep up;" in capped
    # a burst: the same drops with an engine well inside the interval say only the drops
    burst = _inputs(counts=replace(counts, dropped_queue_full=20), process_s=[0.01, 0.012])
    assert build_status(burst)[1].message.endswith("20 frames dropped (queue full, newest wins)")


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


def test_a_camera_that_stopped_is_told_from_one_never_heard() -> None:
    """After a replay ends the window is empty but the node did work: the message says how
    long it has been quiet and what it processed, not that nothing ever came."""
    quiet = Counters()
    stopped = build_status(_inputs(counts=quiet))[1]
    assert stopped.level == Level.WARN
    assert stopped.message == (
        "no frames processed: no images in this period (600 received, 580 processed since start)"
    )
    never = build_status(_inputs(counts=quiet, totals=Counters()))[1]
    assert never.message == "no frames processed: no images received"
    # images that came but were never processed (no IMU or camera_info yet) were heard
    unheard = build_status(_inputs(counts=quiet, totals=Counters(images=5)))[1]
    assert unheard.message.startswith("no frames processed: no images in this period (5 rec")


def test_empty_window_rates_are_nan() -> None:
    inp, _, _ = build_status(_inputs(span_s=math.nan))
    assert math.isnan(float(inp.value_map()["image_rate_hz"]))


def test_missing_images_warn_with_the_fast_dds_hint_only_for_large_images() -> None:
    def input_record(missing: int, image_bytes: int) -> tuple[int, str, dict[str, str]]:
        counts = Counters(images=60, imu=800, camera_info=60, images_missing=missing)
        totals = Counters(images_missing=missing)
        rec = build_status(_inputs(counts=counts, totals=totals, image_bytes=image_bytes))[0]
        return rec.level, rec.message, dict(rec.values)

    # 3 of 63 (4.8 %) is below the 5 % bound; 4 of 64 is above
    level, message, values = input_record(3, 921_600)
    assert level == Level.OK and message == "inputs OK"
    assert values["images_missing_total"] == "3"
    level, message, _ = input_record(4, 307_200)  # VGA mono8 fits the default segment
    assert level == Level.WARN
    assert message == (
        "4 of 64 images missing between the received stamps (lost before the node: "
        "camera driver or transport)"
    )
    level, message, _ = input_record(40, 921_600)  # 720p mono8 does not
    assert level == Level.WARN
    assert message.startswith("40 of 100 images missing")
    assert "images of 900 KiB exceed Fast DDS's default 512 KiB" in message
    assert "fastdds_large_images.xml" in message


def test_backlog_drops_warn_and_are_counted() -> None:
    """IMU/camera_info messages lost from the node's full input backlog (a stalled worker)
    are a WARN of "owl: input" in the window they happen, and a total."""
    counts = Counters(images=60, imu=800, camera_info=60, backlog_dropped=120)
    rec = build_status(_inputs(counts=counts, totals=Counters(backlog_dropped=120)))[0]
    assert rec.level == Level.WARN
    assert rec.message.startswith("120 IMU/camera_info/speed messages dropped")
    assert dict(rec.values)["backlog_dropped_total"] == "120"
    quiet = Counters(images=60, imu=800, camera_info=60)
    rec = build_status(_inputs(counts=quiet, totals=Counters(backlog_dropped=120)))[0]
    assert rec.level == Level.OK and dict(rec.values)["backlog_dropped_total"] == "120"
