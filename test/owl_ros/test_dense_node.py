"""The node's dense publishers over real DDS (in-process rclpy): built only while subscribed."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest
from rclpy.serialization import deserialize_message

from bags.cli import make_bag
from bags.io import BagReader
from msg_adapters.image import image_to_array
from msg_adapters.msgtypes import message_class
from owl_ros.dense_outputs import DensePublishers
from owl_ros.params import build_options
from owl_ros.pipeline import Output, Pipeline
from owl_ros.roles import Role

pytestmark = [pytest.mark.dds]


def _outputs(bag: Path, options: Any) -> list[tuple[Output, Any, Any]]:
    now = [0]  # the pipeline's clock: the bag's log time
    pipeline = Pipeline(options, clock=lambda: now[0])
    outs: list[tuple[Output, Any, Any]] = []
    roles = {
        "/camera/image_raw": Role.IMAGE,
        "/camera/camera_info": Role.CAMERA_INFO,
        "/imu/data": Role.IMU,
    }
    with BagReader(bag) as reader:
        types = {t: i.msgtype for t, i in reader.topics.items()}
        for raw in reader.messages(list(roles)):
            msg = deserialize_message(raw.data, message_class(types[raw.topic]))
            now[0] = raw.log_time_ns
            got = pipeline.add(roles[raw.topic], msg, raw.log_time_ns) + pipeline.poll()
            for out in got:
                outs.append((out, pipeline.engine, pipeline.camera))
    return outs


def test_dense_outputs_built_only_while_subscribed(
    tmp_path: Path, ros_domain_env: dict[str, str]
) -> None:
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    bag = tmp_path / "street"
    args = ["street", str(bag), "--seconds", "0.5", "--width", "160", "--height", "120"]
    assert make_bag.main([*args, "--quiet"]) == 0
    options = build_options({"dense": True, "dense_width": 80, "dense_height": 60})
    outs = _outputs(bag, options)
    assert len(outs) >= 10
    context = Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("owl", context=context)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        pubs = DensePublishers(node, options, qos)
        half = len(outs) // 2
        for out, engine, camera in outs[:half]:
            pubs.publish(out, engine, camera)
        assert pubs.stage.last is None  # nobody listened: the dense stage never ran
        got: list[Any] = []
        listener = rclpy.create_node("listener", context=context)
        listener.create_subscription(Image, "owl/range_over_speed", got.append, qos)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(listener)
        deadline = time.monotonic() + 10.0
        ros_pub = next(p for p in pubs.publishers if p.topic_name == "/owl/range_over_speed")
        while ros_pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert ros_pub.get_subscription_count() == 1
        for out, engine, camera in outs[half:]:
            pubs.publish(out, engine, camera)
        assert pubs.wait_idle(10.0)
        # the first frame after subscribing keeps its image only; the dense thread measured
        # every later one or dropped it for a newer one (newest wins), never the last
        handed = len(outs) - half - 1
        status = pubs.stage.status().value_map()
        measured = int(status["dense_frames_total"])
        assert measured + int(status["dropped_for_newer_total"]) == handed
        while len(got) < measured and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert len(got) == measured >= 1
        last = outs[-1][0].header.stamp
        assert (got[-1].header.stamp.sec, got[-1].header.stamp.nanosec) == (last.sec, last.nanosec)
        assert pubs.stage.last is not None
        assert image_to_array(got[-1]).shape == (60, 80)
        assert got[-1].encoding == "32FC1"
        pubs.close()
        listener.destroy_node()
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_dense_status_says_why_a_frame_gave_nothing_and_shows_no_old_figures(
    tmp_path: Path,
) -> None:
    """``owl: dense`` after a failed frame WARNs with the reason instead of showing the
    last good frame's time to contact as current; a good frame clears it; a reset (nobody
    listens) forgets the result."""
    from owl_ros.dense_outputs import DenseStage

    bag = tmp_path / "street"
    args = ["street", str(bag), "--seconds", "0.5", "--width", "160", "--height", "120"]
    assert make_bag.main([*args, "--quiet"]) == 0
    options = build_options({"dense": True, "dense_width": 80, "dense_height": 60})
    outs = _outputs(bag, options)
    stage = DenseStage(options)

    def feed(items: list[tuple[Output, Any, Any]], image: Any = None) -> int:
        done = 0
        for out, engine, camera in items:
            job = stage.begin(engine, camera, out.image if image is None else image, out.result)
            done += job is not None and stage.finish(job) is not None
        return done

    assert feed(outs[:4]) == 3
    good = stage.status()
    assert good.level.name == "OK" and "ttc_s" in good.value_map()
    assert feed(outs[4:5], image=outs[4][0].image[:, :100]) == 0  # a cropped image
    bad = stage.status()
    assert bad.level.name == "WARN" and "dense image must be a (120, 160)" in bad.message
    values = bad.value_map()
    assert "ttc_s" not in values and "confident_fraction" not in values
    assert int(values["dense_errors_total"]) == 1
    # the bad image dropped the kept ones: the second good frame after it measures again
    assert feed(outs[5:7]) == 1
    again = stage.status()
    assert again.level.name == "OK" and "ttc_s" in again.value_map()
    assert int(again.value_map()["dense_errors_total"]) == 1
    stage.reset()
    gone = stage.status()
    assert gone.level.name == "OK" and gone.message.startswith("no dense result yet")
    assert "ttc_s" not in gone.value_map()
