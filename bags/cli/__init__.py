"""Small pieces shared by the project's command-line tools (``owl_*`` executables).

- :class:`OneLineErrorParser`: argparse that reports a bad command line in one line
  (``PROG: error: ...``, exit 2) instead of dumping the usage text.
- :class:`StopRequest`: a SIGINT/SIGTERM handler that only sets a flag, for tools whose
  loops check it between short sleeps and then close their files cleanly.
"""

from __future__ import annotations

import argparse
from types import FrameType
from typing import NoReturn

__all__ = ["OneLineErrorParser", "StopRequest"]


class OneLineErrorParser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage dump), exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


class StopRequest:
    """Signal handler (``signal.signal(SIGINT, stop)``) that sets ``requested``."""

    def __init__(self) -> None:
        self.requested = False

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        self.requested = True
