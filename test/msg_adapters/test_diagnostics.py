"""Status records <-> DiagnosticArray."""

from __future__ import annotations

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.serialization import deserialize_message, serialize_message

from msg_adapters.diagnostics import Level, StatusRecord, msg_to_records, records_to_msg
from msg_adapters.errors import FieldError


def test_round_trip():
    records = [
        StatusRecord.build(
            "owl: processing",
            Level.WARN,
            "no points: no translation",
            {"frames": 12, "latency_p95_ms": 23.456789, "reason": "t = 0"},
            hardware_id="cam0",
        ),
        StatusRecord("owl: input", Level.OK, "ok", (("a", "1"), ("a", "2"))),
    ]
    msg = records_to_msg(records, 5_000_000_123)
    wire = deserialize_message(serialize_message(msg), DiagnosticArray)
    assert wire.status[0].level == b"\x01"
    stamp, back = msg_to_records(wire)
    assert stamp == 5_000_000_123
    assert back == records
    assert back[0].value_map() == {"frames": "12", "latency_p95_ms": "23.4568", "reason": "t = 0"}


def test_bad_level():
    with pytest.raises(FieldError, match="7"):
        StatusRecord.build("x", 7, "m")
    msg = records_to_msg([StatusRecord("x", Level.OK, "m")], 0)
    msg.status[0].level = b"\x09"
    with pytest.raises(FieldError, match=r"'x'.*9"):
        msg_to_records(msg)
