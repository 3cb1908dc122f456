"""ROS 2 type names -> rclpy classes, and the header-first check used for CDR stamps."""

from __future__ import annotations

import pytest
from geometry_msgs.msg import TwistStamped
from sensor_msgs.msg import Image

from msg_adapters.errors import AdapterError
from msg_adapters.msgtypes import UnknownMessageTypeError, header_first, message_class


def test_known_types_both_spellings():
    assert message_class("sensor_msgs/msg/Image") is Image
    assert message_class("geometry_msgs/TwistStamped") is TwistStamped


@pytest.mark.parametrize(
    ("name", "match"),
    [
        ("tf2_msgs/msg/TFMessage", "'tf2_msgs' is not installed"),
        ("sensor_msgs/msg/Nope", "has no Nope"),
        ("sensor_msgs/msg/", "not of the form"),
        ("Image", "not of the form"),
    ],
)
def test_unknown_types_name_the_value(name, match):
    with pytest.raises(UnknownMessageTypeError, match=match) as info:
        message_class(name)
    assert isinstance(info.value, AdapterError)


def test_header_first():
    assert header_first(Image)
    assert header_first(message_class("sensor_msgs/msg/Imu"))
    assert not header_first(message_class("std_msgs/msg/String"))
    assert not header_first(message_class("rosgraph_msgs/msg/Clock"))
