"""The tools' error hierarchy: one base class, one subclass per tool.

Every message is one line naming what was wrong and the value; the tools' ``main()``
prints ``str(error)`` and exits non-zero.
"""


class ToolError(Exception):
    """Base class of every error raised by the tools in :mod:`owl_ros.tools`."""


class EvalError(ToolError):
    """owl_eval: the result or truth bag cannot be scored (one line naming it)."""


class BenchError(ToolError):
    """owl_bench: a case or option cannot be run (one line naming it)."""


class SoakError(ToolError):
    """owl_soak: the soak run cannot start or finish (one line naming it)."""


class LatencyError(ToolError):
    """owl_latency: the latency run cannot start or finish (one line naming it)."""


class DemoError(ToolError):
    """A step of the demo failed (one line naming it)."""


class LiveNodeError(ToolError):
    """owl_node in its own process did not come up or did not stop (one line, with its log)."""


class BatchError(ToolError):
    """owl_batch: a bag list or option cannot be run (one line naming it)."""
