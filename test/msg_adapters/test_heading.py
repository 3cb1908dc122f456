"""Heading <-> Vector3Stamped."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_msgs.msg import Vector3Stamped
from rclpy.serialization import deserialize_message, serialize_message

from msg_adapters.errors import FieldError
from msg_adapters.heading import heading_to_msg, msg_to_heading
from msg_adapters.stamps import header_to_ns, make_header


def test_round_trip_exact():
    h = np.array([0.1, -0.2, 0.9])
    h /= np.linalg.norm(h)
    msg = heading_to_msg(h, make_header(99, "cam"))
    wire = deserialize_message(serialize_message(msg), Vector3Stamped)
    np.testing.assert_array_equal(msg_to_heading(wire), h)
    assert header_to_ns(wire.header) == 99 and wire.header.frame_id == "cam"


@pytest.mark.parametrize(
    ("value", "match"),
    [([0.0, 0.0, 0.0], "non-zero"), ([np.nan, 0, 1], "nan"), ([1.0, 0.0], r"\(2,\)")],
)
def test_bad_heading(value, match):
    with pytest.raises(FieldError, match=match):
        heading_to_msg(value, make_header(0, "c"))
