"""Fixtures of the node tests: owl nodes made in the test's own process."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import pytest


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
