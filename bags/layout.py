"""The standard bag layout: the topics of the synthetic bags (``owl_make_bag``) and of the
imported ones (``owl_import``), which ``owl_process``, ``owl_replay``, ``owl_eval`` and
``owl_bench --bag`` read. One table, so that writers and readers cannot drift apart.

Each role maps to ``(topic, ROS 2 type name, bag QoS name)`` (:data:`bags.io.QOS`).
"""

from __future__ import annotations

#: ``header.frame_id`` of the camera messages (optical frame, REP 103) and of the IMU's.
CAMERA_FRAME = "camera_optical_frame"
IMU_FRAME = "imu_link"

TOPICS: dict[str, tuple[str, str, str]] = {
    "image": ("/camera/image_raw", "sensor_msgs/msg/Image", "sensor"),
    "info": ("/camera/camera_info", "sensor_msgs/msg/CameraInfo", "sensor"),
    "imu": ("/imu/data", "sensor_msgs/msg/Imu", "sensor"),
    "tf": ("/tf_static", "tf2_msgs/msg/TFMessage", "latched"),
    "twist": ("/ground_truth/twist", "geometry_msgs/msg/TwistStamped", "reliable"),
    "range": ("/ground_truth/range", "sensor_msgs/msg/Image", "reliable"),
    "mask": ("/ground_truth/moving_mask", "sensor_msgs/msg/Image", "reliable"),
    "bias": ("/ground_truth/gyro_bias", "geometry_msgs/msg/Vector3Stamped", "reliable"),
}


def subset(*roles: str) -> dict[str, tuple[str, str, str]]:
    """The rows of :data:`TOPICS` for ``roles``, in that order (a writer's topic order)."""
    return {role: TOPICS[role] for role in roles}
