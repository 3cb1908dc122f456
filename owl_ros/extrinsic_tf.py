"""The camera-IMU rotation from TF, for node ``owl`` (when ``tf2_ros`` is importable).

On a ROS install the rotation between the camera and the IMU is usually published on
``/tf_static`` (robot_state_publisher, a static_transform_publisher). The node looks up
the transform from the image's ``header.frame_id`` to the IMU's ``header.frame_id`` once
both are known, unless ``camera_to_imu_rotation_xyzw`` was given as a parameter (the
parameter overrides TF). The PyPI install has no ``tf2_ros``; the node then says so once.
"""

from __future__ import annotations

from typing import Any

__all__ = ["TfExtrinsic", "tf_available"]


def tf_available() -> bool:
    """Whether ``tf2_ros`` can be imported here."""
    try:
        import tf2_ros  # noqa: F401
    except ImportError:
        return False
    return True


class TfExtrinsic:
    """A TF buffer and listener on ``node``; :meth:`lookup` returns the rotation or None.

    Raises:
        ImportError: tf2_ros is not importable (check :func:`tf_available` first).
    """

    def __init__(self, node: Any) -> None:
        import tf2_ros

        self._buffer = tf2_ros.Buffer()
        self._listener = tf2_ros.TransformListener(self._buffer, node, spin_thread=False)

    def lookup(
        self, camera_frame: str, imu_frame: str
    ) -> tuple[float, float, float, float] | None:
        """camera_to_imu_rotation_xyzw: the rotation of the transform whose parent is the
        IMU frame and child the camera frame (maps camera coordinates to IMU ones), or
        None while TF does not have it."""
        from rclpy.time import Time

        try:
            tf = self._buffer.lookup_transform(
                imu_frame.lstrip("/"), camera_frame.lstrip("/"), Time()
            )
        except Exception:  # tf2 LookupException, ConnectivityException, ExtrapolationException
            return None
        q = tf.transform.rotation
        return (float(q.x), float(q.y), float(q.z), float(q.w))

    def close(self) -> None:
        """Stop listening: ``/tf`` and ``/tf_static`` are no longer received (on a robot
        ``/tf`` runs at hundreds of messages a second, each deserialised on the node's
        executor thread for nothing once the rotation is known)."""
        unregister = getattr(self._listener, "unregister", None)
        if unregister is not None:
            unregister()
