"""Fixtures of the node tests: owl nodes made in the test's own process, Python snippets
run in a child process of their own, and a bag's pipeline outputs."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

#: run_snippet(code, argument, environment) -> the JSON object the snippet printed
SnippetRunner = Callable[[str, str, dict[str, str]], dict[str, Any]]
#: pipeline_outputs(bag, options) -> [(Output, engine, camera)] of every processed frame
OutputsOfBag = Callable[[Path, Any], list[tuple[Any, Any, Any]]]


@pytest.fixture
def run_snippet() -> SnippetRunner:
    """Runs a Python snippet in a fresh interpreter (process-wide settings such as the heap
    thresholds or the BLAS threads start from nothing there) with one argument
    (``sys.argv[1]``) and an environment; returns the JSON object it printed on stdout."""

    def run(code: str, argument: str, env: dict[str, str]) -> dict[str, Any]:
        out = subprocess.run(
            [sys.executable, "-c", code, argument],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        result: dict[str, Any] = json.loads(out.stdout)
        return result

    return run


@pytest.fixture
def make_owl(rclpy_context: Any) -> Iterator[Callable[..., Any]]:
    """Makes ``OwlNode``s on the test's own rclpy context (parameter overrides, and
    ``remaps`` as ``-r`` arguments); closes and destroys them after the test."""
    from owl_ros.node import OwlNode

    nodes: list[OwlNode] = []

    def make(*overrides: Any, remaps: Sequence[str] = ()) -> OwlNode:
        cli = ["--ros-args", *(a for r in remaps for a in ("-r", r))] if remaps else None
        node = OwlNode(context=rclpy_context, parameter_overrides=list(overrides), cli_args=cli)
        nodes.append(node)
        return node

    yield make
    for node in nodes:
        node.close()
        node.destroy_node()


@pytest.fixture
def pipeline_outputs() -> OutputsOfBag:
    """Runs a bag's camera, camera_info and IMU messages through a
    :class:`~owl_ros.pipeline.Pipeline` (its clock: the bag's log time) and returns every
    Output with the engine and camera at hand when it came out (what the node hands to its
    dense stage)."""
    from rclpy.serialization import deserialize_message

    from bags.io import BagReader
    from msg_adapters.msgtypes import message_class
    from owl_ros.pipeline import Pipeline
    from owl_ros.roles import Role

    def run(bag: Path, options: Any) -> list[tuple[Any, Any, Any]]:
        now = [0]
        pipeline = Pipeline(options, clock=lambda: now[0])
        outs: list[tuple[Any, Any, Any]] = []
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
                outs += [(out, pipeline.engine, pipeline.camera) for out in got]
        return outs

    return run
