"""The bags error hierarchy: one base class, a few specific subclasses.

Every message is one line and names the path, topic or value that was wrong, e.g.
``NotABagError("not a bag: /tmp/x is a directory without metadata.yaml")``. CLIs print
``str(error)`` and exit non-zero; no traceback is needed to understand it.
"""


class BagError(Exception):
    """Base class of every error raised by the bags package."""


class BagNotFoundError(BagError, FileNotFoundError):
    """The bag path does not exist."""


class NotABagError(BagError, ValueError):
    """The path exists but is not a rosbag2 directory or an MCAP file."""


class CorruptBagError(BagError, ValueError):
    """The bag is truncated or damaged (missing footer, bad record, bad metadata)."""


class BagExistsError(BagError, FileExistsError):
    """The output path exists and overwriting was not requested (or is unsafe)."""


class OutputOverlapError(BagExistsError):
    """The output path is an input, lies inside one or contains one (refused even with
    overwrite: replacing it would delete the input)."""


class BagTopicError(BagError, KeyError):
    """A topic or message type is unknown, duplicated or not registered."""

    def __str__(self) -> str:
        # KeyError's str() quotes its argument; keep the message a plain line.
        return str(self.args[0]) if self.args else ""


class ScenarioError(BagError, ValueError):
    """A scenario name or a rendering/sensor option is invalid."""
