"""Small pieces shared by the project's command-line tools (``owl_*`` executables).

- :class:`OneLineErrorParser`: argparse that reports a bad command line in one line
  (``PROG: error: ...``, exit 2) instead of dumping the usage text.
  A value that starts with a minus sign and reads as a number list
  (``--gyro-bias -0.01,0,0``, ``--camera-to-imu-rotation-xyzw -0.5,0.5,-0.5,0.5``) is
  taken as the option's value, as ``--opt=-0.01,0,0`` is (plain argparse takes it for an
  option and says "expected one argument").
- :class:`StopRequest`: a SIGINT/SIGTERM handler that only sets a flag, for tools whose
  loops check it between short sleeps and then close their files cleanly.
- :func:`topic_name_problem`: why rclpy would refuse a topic name (checked up front, so a
  bad name is one line, not rclpy's InvalidTopicNameException traceback).
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import Any, NoReturn

__all__ = ["OneLineErrorParser", "StopRequest", "topic_name_problem", "user_cache_dir"]


#: A comma-separated list of numbers whose first starts with "-" (e.g. -0.5,0.5,-1e-3).
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
NEGATIVE_NUMBER_LIST = re.compile(rf"-(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?(?:,{_NUMBER})*")


class OneLineErrorParser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage dump), exit status 2, and negative number
    lists accepted as option values (see the module docstring)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: Any = None
    ) -> tuple[Any, list[str]]:
        import sys

        return super().parse_known_args(
            join_negative_values(self, sys.argv[1:] if args is None else args), namespace
        )


def join_negative_values(parser: argparse.ArgumentParser, args: Sequence[str]) -> list[str]:
    """``["--opt", "-0.5,1"]`` -> ``["--opt=-0.5,1"]`` for options of ``parser`` that take
    one value; everything else unchanged (``--`` ends the options)."""
    single = {
        opt
        for action in parser._actions
        if action.nargs is None and action.option_strings
        for opt in action.option_strings
    }
    out: list[str] = []
    items = list(args)
    i = 0
    while i < len(items):
        item = items[i]
        if item == "--":
            out += items[i:]
            break
        if item in single and i + 1 < len(items) and NEGATIVE_NUMBER_LIST.fullmatch(items[i + 1]):
            out.append(f"{item}={items[i + 1]}")
            i += 2
            continue
        out.append(item)
        i += 1
    return out


def topic_name_problem(name: str, full: bool = True) -> str | None:
    """Why rclpy refuses the topic ``name`` (e.g. "topic name must not contain characters
    other than alphanumerics, '_', or '/'"), or None if it is valid: as a fully qualified
    name, or with ``full`` False as a name a node resolves (relative, ``~``, substitutions).
    None too where rclpy is not importable (nothing could subscribe to it then)."""
    try:
        from rclpy.exceptions import InvalidTopicNameException
        from rclpy.validate_full_topic_name import validate_full_topic_name
        from rclpy.validate_topic_name import validate_topic_name
    except ImportError:
        return None
    try:
        (validate_full_topic_name if full else validate_topic_name)(name)
    except InvalidTopicNameException as err:
        first = str(err).splitlines()[0] if str(err) else "invalid topic name"
        return first.removeprefix("Invalid topic name: ").rstrip(":")
    return None


def user_cache_dir(name: str) -> Path:
    """``$XDG_CACHE_HOME/owl_ros/<name>`` (default ``~/.cache/owl_ros/<name>``): where tools
    keep re-creatable files, instead of a directory below wherever they are run."""
    import os

    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "owl_ros" / name


class StopRequest:
    """Signal handler (``signal.signal(SIGINT, stop)``) that sets ``requested``."""

    def __init__(self) -> None:
        self.requested = False

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        self.requested = True
