"""The node's dense publishers over real DDS (in-process rclpy): built only while subscribed."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from bags.cli import make_bag
from msg_adapters.image import image_to_array
from owl_ros.dense_outputs import DensePublishers
from owl_ros.params import build_options
from owl_ros.pipeline import Output

pytestmark = [pytest.mark.dds]


def _listen(context: Any, pubs: DensePublishers, qos: Any) -> tuple[list[Any], Any, Any]:
    """A listener node on ``owl/range_over_speed`` that the dense publisher has matched:
    (the list its images go to, the node, an executor spinning nothing else)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image

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
    return got, listener, executor


def _street_outputs(
    tmp_path: Path, seconds: float, options: Any, pipeline_outputs: Any
) -> list[tuple[Output, Any, Any]]:
    """The pipeline's outputs over a rendered 160x120 street bag of ``seconds``."""
    bag = tmp_path / "street"
    args = ["street", str(bag), "--seconds", str(seconds), "--width", "160", "--height", "120"]
    assert make_bag.main([*args, "--quiet"]) == 0
    outs: list[tuple[Output, Any, Any]] = pipeline_outputs(bag, options)
    return outs


@contextmanager
def _dense_node(options: Any) -> Iterator[tuple[Any, Any, DensePublishers, Any]]:
    """In a context of its own: (the context, node ``owl``, its dense publishers, their
    QoS); rclpy shut down on the way out."""
    import rclpy
    from rclpy.context import Context
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    context = Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("owl", context=context)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        yield context, node, DensePublishers(node, options, qos), qos
    finally:
        rclpy.shutdown(context=context)


@pytest.mark.parametrize("in_process", [True, False], ids=["process", "thread"])
def test_dense_outputs_built_only_while_subscribed(
    tmp_path: Path, ros_domain_env: dict[str, str], pipeline_outputs: Any, in_process: bool
) -> None:
    values = {"dense": True, "dense_width": 80, "dense_height": 60}
    options = build_options({**values, "dense_process": in_process})
    outs = _street_outputs(tmp_path, 0.5, options, pipeline_outputs)
    assert len(outs) >= 10
    with _dense_node(options) as (context, node, pubs, qos):
        assert (pubs.process is not None) == in_process
        half = len(outs) // 2
        for out, engine, camera in outs[:half]:
            pubs.publish(out, engine, camera)
        assert pubs.stage.last is None  # nobody listened: the dense stage never ran
        got, listener, executor = _listen(context, pubs, qos)
        deadline = time.monotonic() + 10.0
        for out, engine, camera in outs[half:]:
            pubs.publish(out, engine, camera)
        assert pubs.wait_idle(10.0)
        # the first frame after subscribing keeps its image only; the dense thread measured
        # every later one or dropped it for a newer one (newest wins), never the last
        handed = len(outs) - half - 1
        status = pubs.stage.status().value_map()
        measured = int(status["dense_frames_total"])
        assert measured + int(status["dropped_for_newer_total"]) == handed, status
        while len(got) < measured and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert len(got) == measured >= 1
        last = outs[-1][0].header.stamp
        assert (got[-1].header.stamp.sec, got[-1].header.stamp.nanosec) == (last.sec, last.nanosec)
        assert pubs.stage.last is not None
        assert image_to_array(got[-1]).shape == (60, 80)
        assert got[-1].encoding == "32FC1"
        pubs.close()
        assert pubs.process is None or pubs.process.pid is None  # the child has exited
        listener.destroy_node()
        node.destroy_node()


def test_a_dead_dense_process_is_said_and_started_again(
    tmp_path: Path, ros_domain_env: dict[str, str], pipeline_outputs: Any
) -> None:
    """The dense process killed between frames: ``owl: dense`` WARNs that it exited (with
    its exit code), the node goes on, and the next frame starts a new one that publishes."""
    import os
    import signal

    options = build_options({"dense": True, "dense_width": 80, "dense_height": 60})
    outs = _street_outputs(tmp_path, 0.4, options, pipeline_outputs)
    with _dense_node(options) as (context, node, pubs, qos):
        got, listener, executor = _listen(context, pubs, qos)
        deadline = time.monotonic() + 10.0

        def feed(items: list[Any]) -> None:
            for out, engine, camera in items:
                pubs.publish(out, engine, camera)
                assert pubs.wait_idle(30.0)  # one frame at a time: none dropped

        feed(outs[:3])
        assert pubs.process is not None and pubs.process.starts == 1
        first = pubs.process.pid
        assert first is not None
        assert Path(f"/proc/{first}/comm").read_text().strip() == "owl-dense"
        os.kill(first, signal.SIGKILL)
        feed(outs[3:4])
        dead = pubs.stage.status()
        assert dead.level.name == "WARN"
        assert "the dense process exited (code -9)" in dead.message, dead.message
        assert int(dead.value_map()["dense_errors_total"]) == 1
        feed(outs[4:6])
        again = pubs.stage.status()
        assert again.level.name == "OK", again.message
        assert pubs.process.starts == 2 and pubs.process.pid not in (None, first)
        assert int(again.value_map()["dense_frames_total"]) == 4  # 2 before, 2 after
        while len(got) < 4 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert len(got) == 4
        pubs.close()
        listener.destroy_node()
        node.destroy_node()


def test_dense_status_says_why_a_frame_gave_nothing_and_shows_no_old_figures(
    tmp_path: Path, pipeline_outputs: Any
) -> None:
    """``owl: dense`` after a failed frame WARNs with the reason instead of showing the
    last good frame's time to contact as current; a good frame clears it; a reset (nobody
    listens) forgets the result."""
    from owl_ros.dense_outputs import DenseStage

    options = build_options({"dense": True, "dense_width": 80, "dense_height": 60})
    outs = _street_outputs(tmp_path, 0.5, options, pipeline_outputs)
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
