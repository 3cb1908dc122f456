"""Status records <-> diagnostic_msgs/DiagnosticArray.

A ``StatusRecord`` is the node's view of one DiagnosticStatus: name, level, message,
hardware id and ordered key/value pairs (values already formatted as strings; use
``StatusRecord.build`` to format numbers consistently).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from msg_adapters.errors import FieldError
from msg_adapters.stamps import header_to_ns, make_header


class Level(enum.IntEnum):
    """diagnostic_msgs/DiagnosticStatus levels."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


def format_value(value: object) -> str:
    """One key/value value as text: floats with 6 significant digits, others via str()."""
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


@dataclass(frozen=True)
class StatusRecord:
    """One DiagnosticStatus.

    Attributes:
        name: status name, e.g. "owl: processing".
        level: Level.
        message: one human-readable line.
        values: ordered (key, value) string pairs.
        hardware_id: optional hardware id.
    """

    name: str
    level: Level
    message: str
    values: tuple[tuple[str, str], ...] = ()
    hardware_id: str = ""

    @classmethod
    def build(
        cls,
        name: str,
        level: Level | int,
        message: str,
        values: Mapping[str, object] | None = None,
        hardware_id: str = "",
    ) -> StatusRecord:
        """Record from a mapping of any values (formatted with ``format_value``)."""
        try:
            lvl = Level(int(level))
        except ValueError:
            raise FieldError(f"diagnostic level must be 0..3, got {level}") from None
        pairs = tuple((str(k), format_value(v)) for k, v in (values or {}).items())
        return cls(name, lvl, message, pairs, hardware_id)

    def value_map(self) -> dict[str, str]:
        """The key/value pairs as a dict."""
        return dict(self.values)


def records_to_msg(records: Sequence[StatusRecord], stamp_ns: int) -> Any:
    """Status records -> DiagnosticArray stamped ``stamp_ns`` (header frame_id empty)."""
    msg = DiagnosticArray(header=make_header(stamp_ns, ""))
    for rec in records:
        status = DiagnosticStatus(
            name=rec.name,
            message=rec.message,
            hardware_id=rec.hardware_id,
            values=[KeyValue(key=k, value=v) for k, v in rec.values],
        )
        status.level = bytes([int(rec.level)])
        msg.status.append(status)
    return msg


def msg_to_records(msg: Any) -> tuple[int, list[StatusRecord]]:
    """DiagnosticArray -> (stamp_ns, status records)."""
    out = []
    for status in msg.status:
        raw = status.level
        level = raw[0] if isinstance(raw, (bytes, bytearray)) else int(raw)
        try:
            lvl = Level(int(level))
        except ValueError:
            raise FieldError(
                f"diagnostic_status[{status.name!r}].level must be 0..3, got {level}"
            ) from None
        pairs = tuple((str(kv.key), str(kv.value)) for kv in status.values)
        out.append(StatusRecord(status.name, lvl, status.message, pairs, status.hardware_id))
    return header_to_ns(msg.header), out
