"""ROS 2 type names ("sensor_msgs/msg/Image") -> rclpy message classes.

rosidl_runtime_py is not available, so the generated module ``<pkg>.msg`` is imported and
the class taken by name. Used by owl_replay / owl_record to publish and subscribe raw CDR.
"""

from __future__ import annotations

import importlib
import re
from functools import cache
from typing import Any

from msg_adapters.errors import AdapterError

_TYPE_NAME = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(?:msg/)?([A-Za-z][A-Za-z0-9_]*)$")


class UnknownMessageTypeError(AdapterError):
    """A type name that is malformed or whose Python message package is not installed."""


@cache
def message_class(msgtype: str) -> Any:
    """The rclpy message class of ``msgtype`` ("pkg/msg/Name" or "pkg/Name").

    Raises:
        UnknownMessageTypeError: malformed name, package not importable or no such class.
    """
    match = _TYPE_NAME.match(msgtype)
    if match is None:
        raise UnknownMessageTypeError(
            f"message type {msgtype!r} is not of the form 'package/msg/Name'"
        )
    package, name = match.groups()
    try:
        module = importlib.import_module(f"{package}.msg")
    except ImportError:
        raise UnknownMessageTypeError(
            f"message type {msgtype!r}: Python package '{package}' is not installed"
        ) from None
    cls = getattr(module, name, None)
    if cls is None or not hasattr(cls, "_TYPE_SUPPORT"):
        raise UnknownMessageTypeError(f"message type {msgtype!r}: '{package}.msg' has no {name}")
    return cls


def header_first(cls: Any) -> bool:
    """True when the message's first field is a std_msgs/Header (its stamp leads the CDR)."""
    fields = cls.get_fields_and_field_types()
    first = next(iter(fields.items()), None)
    return first is not None and first[0] == "header" and first[1] == "std_msgs/Header"
