"""What node ``owl`` says about itself: start-up line, parameter checks, silent-input warnings.

Kept apart from :mod:`owl_ros.node` so that the node stays a thin wiring of ROS objects:

- :func:`coerce_overrides`: ``-p pixel_noise_px:=1`` (an integer for a double) and
  ``-p "camera_to_imu_rotation_xyzw:=[0,0,0,1]"`` (an integer array for a double array)
  are converted to the declared type before the parameter is declared (rclpy would refuse
  them: ROS 2 parameter types are strict). The parameters stay statically typed.
- :func:`unknown_parameters`: overrides that name no parameter of the node; one close to a
  real name (``max_feature``) is an error naming the close match, others a warning.
- :func:`check_params_file_args`: a ``--params-file`` that cannot be read gives one line
  (rclpy would end in an ``RCLError`` traceback).
- :func:`startup_line`: the resolved topics (after remaps), the extrinsic and its source,
  the speed source; :func:`extrinsic_warning` when the identity is used by default.
- :class:`SilenceWatch`: throttled WARN lines naming the input topic that is silent and
  the reason frames are empty (the same facts /diagnostics carries, in the log).
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from owl_ros.params import PARAMS

__all__ = [
    "EXTRINSIC_HOWTO",
    "SilenceWatch",
    "check_params_file_args",
    "coerce_overrides",
    "empty_reason",
    "extrinsic_warning",
    "name_inputs",
    "startup_line",
    "unknown_parameters",
]

_BY_NAME = {p.name: p for p in PARAMS}
#: parameters every rclpy node has or accepts without declaring them.
_ROS_OWN = ("use_sim_time", "start_type_description_service")
#: how to give the camera-IMU rotation (printed where the identity is used by default).
EXTRINSIC_HOWTO = (
    "set it with -p camera_to_imu_rotation_xyzw:=[x,y,z,w] (owl_process: "
    "--camera-to-imu-rotation-xyzw X,Y,Z,W) or publish the IMU -> camera transform on TF"
)
#: said when the rotation parameter is set to the identity where TF could give it (an old
#: copy of config/owl.yaml listed it): a parameter always wins over TF.
IDENTITY_BLOCKS_TF = (
    "the identity, set: TF is not looked up; leave the parameter unset (remove it from the "
    "parameter file or the -p arguments) to take the rotation from TF"
)
#: seconds between two WARN lines about the same problem.
WARN_PERIOD_S = 10.0


def coerce_overrides(overrides: dict[str, Any]) -> list[str]:
    """Convert integer overrides of double / double-array parameters to doubles, in place.

    Args:
        overrides: rclpy ``Node._parameter_overrides`` (name -> rclpy Parameter).

    Returns:
        The names converted.
    """
    from rclpy.parameter import Parameter

    converted = []
    for name, param in list(overrides.items()):
        spec = _BY_NAME.get(name)
        if spec is None:
            continue
        kind, value = param.type_, param.value
        if spec.kind == "double" and kind == Parameter.Type.INTEGER:
            overrides[name] = Parameter(name, Parameter.Type.DOUBLE, float(value))
            converted.append(name)
        elif spec.kind == "double_array" and kind == Parameter.Type.INTEGER_ARRAY:
            floats = [float(v) for v in value]
            overrides[name] = Parameter(name, Parameter.Type.DOUBLE_ARRAY, floats)
            converted.append(name)
    return converted


def unknown_parameters(names: Iterable[str]) -> tuple[list[str], list[str]]:
    """(errors, warnings) for parameter names the node does not have.

    A name close to a real one (a typo: ``max_feature``) is an error naming the match;
    any other unknown name is a warning (a parameter file for several nodes may hold it).
    """
    errors, warnings = [], []
    known = list(_BY_NAME)
    for name in sorted(set(names)):
        if name in _BY_NAME or name in _ROS_OWN or name.startswith("qos_overrides."):
            continue
        close = difflib.get_close_matches(name, known, n=1, cutoff=0.75)
        if close:
            errors.append(f"parameter {name}: unknown parameter (did you mean {close[0]}?)")
        else:
            warnings.append(f"parameter {name}: unknown parameter, ignored")
    return errors, warnings


def check_params_file_args(args: Sequence[str]) -> str | None:
    """One line for a ``--params-file`` of the ROS arguments that cannot be read, else None."""
    for i, arg in enumerate(args):
        if arg == "--params-file" and i + 1 < len(args):
            path = args[i + 1]
            if not os.path.isfile(path):
                return f"--params-file {path}: no such file"
            if not os.access(path, os.R_OK):
                return f"--params-file {path}: not readable"
    return None


def _quat(q: Sequence[float]) -> str:
    return "[" + ", ".join(f"{float(v):g}" for v in q) + "]"


def startup_line(
    topics: Mapping[str, str],
    publications: Sequence[str],
    rotation_xyzw: Sequence[float],
    extrinsic_source: str,
    speed_source: str,
) -> str:
    """The node's INFO line at start.

    Args:
        topics: role ("image", "camera_info", "imu", "speed") -> resolved topic name.
        publications: resolved names of the published topics.
        rotation_xyzw: the camera-to-IMU rotation in use.
        extrinsic_source: "parameter", "TF ..." or "default (identity)".
        speed_source: "none", "odometry" or "twist".
    """
    subs = ", ".join(f"{role} {name}" for role, name in topics.items())
    return (
        f"listening on {subs}; publishing {', '.join(publications)}; "
        f"camera_to_imu_rotation_xyzw {_quat(rotation_xyzw)} from {extrinsic_source}; "
        f"speed from {speed_source if speed_source != 'none' else 'none (cloud in seconds)'}"
    )


def extrinsic_warning(tf_available: bool) -> str:
    """The WARN line when no extrinsic was given (the identity is used)."""
    tf = "" if tf_available else " (tf2_ros is not importable here: TF is not looked up)"
    return f"camera_to_imu_rotation_xyzw not given: using the identity{tf}; {EXTRINSIC_HOWTO}"


@dataclass
class SilenceWatch:
    """Throttled WARN lines from the node's input counters.

    Call :meth:`check` at each diagnostics period with the totals; it returns the lines
    to log now: an input topic that delivered nothing for ``after_s`` seconds since start
    or since its last message, and the reason frames came out empty. The same text is
    repeated at most every ``period_s`` seconds.

    Attributes:
        topics: role -> resolved topic name ("image", "camera_info", "imu"[, "speed"]).
        after_s: silence that is reported, s.
        period_s: least time between two identical lines, s.
    """

    topics: Mapping[str, str]
    after_s: float = 3.0
    period_s: float = WARN_PERIOD_S
    _last_total: dict[str, int] = field(default_factory=dict)
    _last_change_s: dict[str, float] = field(default_factory=dict)
    _said: dict[str, float] = field(default_factory=dict)

    def check(self, now_s: float, totals: Mapping[str, int], empty_reason: str) -> list[str]:
        """Lines to log now.

        Args:
            now_s: monotonic time, s.
            totals: role -> messages received so far.
            empty_reason: why the last frames had no points ("" when they had points).
        """
        lines = []
        for role, topic in self.topics.items():
            total = int(totals.get(role, 0))
            if role not in self._last_change_s or total != self._last_total.get(role):
                self._last_total[role] = total
                self._last_change_s[role] = now_s
                continue
            silent = now_s - self._last_change_s[role]
            if silent >= self.after_s:
                what = "nothing received" if total == 0 else f"nothing since message {total}"
                lines.append(
                    f"{role} topic {topic}: {what} for {silent:.0f} s "
                    f"(check the topic name / remap and the publisher's QoS)"
                )
        if empty_reason and "no frames processed: no images" not in empty_reason:  # per topic
            lines.append(f"frames without points: {empty_reason}")
        # forget what was said a period ago (it may be said again): the lines carry
        # changing values, so keeping every key would grow without bound
        self._said = {k: t for k, t in self._said.items() if now_s - t < self.period_s}
        out = []
        for line in lines:
            key = line.split(" for ")[0] if " for " in line else line
            if now_s - self._said.get(key, -1e300) >= self.period_s:
                self._said[key] = now_s
                out.append(line)
        return out


def name_inputs(records: Sequence[Any], topics: Mapping[str, str], node_name: str) -> list[Any]:
    """The node's status records with ``hardware_id`` (the node's full name) and the input
    record naming the topics listened on (``<role>_topic`` keys, appended)."""
    from dataclasses import replace

    out = []
    for rec in records:
        values = rec.values
        if rec.name.endswith(": input"):
            values = values + tuple((f"{role}_topic", name) for role, name in topics.items())
        out.append(replace(rec, hardware_id=node_name, values=values))
    return out


def empty_reason(records: Sequence[Any]) -> str:
    """Why frames had no points in the last diagnostics window ("" when they had)."""
    for rec in records:
        if rec.name.endswith(": processing") and int(rec.level) >= 1:
            first = rec.message.split("; ")[0]
            if first.startswith(("no points", "no frames processed")):
                return first
    return ""
