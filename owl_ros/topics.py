"""The result topics of node ``owl``: one table for the node, owl_process, owl_eval, owl_bench
and the demo.

``name`` is what the node publishes (relative, remappable; ``/diagnostics`` is absolute);
``bag`` is the name in a result bag (``owl_process`` writes and ``owl_eval`` reads
``/owl/points`` ...). ``msgtype`` is the ROS 2 type name, ``qos`` the bag QoS name
(:data:`bags.io.QOS`).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ResultTopic:
    """One output topic of the node.

    Attributes:
        name: the node's topic name, e.g. "owl/points".
        msgtype: ROS 2 type name, e.g. "sensor_msgs/msg/PointCloud2".
        qos: bag QoS name ("reliable").
    """

    name: str
    msgtype: str
    qos: str = "reliable"

    @property
    def bag(self) -> str:
        """The topic's name in a result bag (absolute)."""
        return self.name if self.name.startswith("/") else f"/{self.name}"


#: sensor_msgs/PointCloud2, one per processed frame (possibly empty), header = the image's.
POINTS = ResultTopic("owl/points", "sensor_msgs/msg/PointCloud2")
#: geometry_msgs/Vector3Stamped, unit heading (camera optical frame), frames with a heading.
HEADING = ResultTopic("owl/heading", "geometry_msgs/msg/Vector3Stamped")
#: geometry_msgs/TwistWithCovarianceStamped, the heading in ``linear`` with its covariance.
HEADING_COV = ResultTopic(
    "owl/heading_with_covariance", "geometry_msgs/msg/TwistWithCovarianceStamped"
)
#: visualization_msgs/Marker, the heading as an arrow (RViz, Foxglove).
HEADING_MARKER = ResultTopic("owl/heading_marker", "visualization_msgs/msg/Marker")
#: geometry_msgs/Vector3Stamped, gyro-bias estimate (IMU frame, rad/s), every processed frame.
GYRO_BIAS = ResultTopic("owl/gyro_bias", "geometry_msgs/msg/Vector3Stamped")
#: diagnostic_msgs/DiagnosticArray, every ``diagnostics_period_s``.
DIAGNOSTICS = ResultTopic("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")

#: Every result topic, in the order result bags list them.
RESULT_TOPICS = (POINTS, HEADING, HEADING_COV, HEADING_MARKER, GYRO_BIAS, DIAGNOSTICS)
