"""Shared fixtures: repository paths and a per-module ROS domain for DDS tests."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository root (where package.xml lives)."""
    return REPO


@pytest.fixture
def ros_domain_env(monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """Environment for child ROS processes on a private DDS domain.

    Each test gets its own ROS_DOMAIN_ID (derived from the pid and a counter) so
    that tests running next to each other never see each other's topics.
    """
    ros_domain_env.counter = getattr(ros_domain_env, "counter", 0) + 1  # type: ignore[attr-defined]
    domain = 100 + (os.getpid() * 7 + ros_domain_env.counter) % 100  # type: ignore[attr-defined]
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    monkeypatch.setenv("PYTHONUNBUFFERED", "1")
    return dict(os.environ)


@pytest.fixture
def rclpy_context(ros_domain_env: dict[str, str]) -> Iterator[Any]:
    """An rclpy context of the test's own on its private domain, for nodes made in the
    test's process; shut down after the test."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_domain_env["ROS_DOMAIN_ID"]))
    yield ctx
    rclpy.try_shutdown(context=ctx)
