"""Fixtures of the node tests: owl nodes made in the test's own process, and Python
snippets run in a child process of their own."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import pytest

#: run_snippet(code, argument, environment) -> the JSON object the snippet printed
SnippetRunner = Callable[[str, str, dict[str, str]], dict[str, Any]]


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
