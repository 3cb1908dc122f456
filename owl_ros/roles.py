"""The roles of the messages node ``owl`` and ``owl_process`` take in: one enum for both.

A :class:`Role` names what an input topic is for; its value is the name used in
parameters, log lines and the ``<role>_topic`` diagnostic keys ("image", "camera_info",
"imu", "speed"), so a role can stand wherever that text did.
"""

from __future__ import annotations

from enum import StrEnum

__all__ = ["Role"]


class Role(StrEnum):
    """What an input message is for."""

    IMAGE = "image"  # sensor_msgs/Image or CompressedImage
    CAMERA_INFO = "camera_info"  # sensor_msgs/CameraInfo
    IMU = "imu"  # sensor_msgs/Imu
    SPEED = "speed"  # nav_msgs/Odometry or geometry_msgs/TwistStamped
