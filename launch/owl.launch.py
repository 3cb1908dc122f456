"""Launch node 'owl' with config/owl.yaml and the usual camera/IMU remappings.

    ros2 launch owl_ros owl.launch.py image:=/camera/image_raw camera_info:=/camera/camera_info \\
        imu:=/imu/data camera_to_imu_rotation_xyzw:=-0.5,0.5,-0.5,0.5 imu_time_offset:=0.0 \\
        namespace:=robot1 use_sim_time:=false params_file:=/path/to/owl.yaml rviz:=true \\
        frame:=camera_optical_frame

``camera_to_imu_rotation_xyzw`` and ``imu_time_offset`` override the parameter file when
given (empty: the file's value; for the rotation, TF when the file does not set it, as the
shipped config/owl.yaml does not).
``frame`` is RViz's fixed frame: the frame_id of your camera's images.
"""

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription
from owl_ros.launch_args import node_parameters


def _nodes(context, share: Path) -> list:
    """Node 'owl' (and RViz) with the arguments' values."""
    value = lambda name: LaunchConfiguration(name).perform(context)  # noqa: E731
    overrides = node_parameters(value("camera_to_imu_rotation_xyzw"), value("imu_time_offset"))
    owl = Node(
        package="owl_ros",
        executable="owl_node",
        name="owl",
        namespace=value("namespace"),
        output="screen",
        parameters=[
            value("params_file"),
            {"use_sim_time": value("use_sim_time").lower() == "true", **overrides},
        ],
        remappings=[
            ("image", value("image")),
            ("image/compressed", value("image") + "/compressed"),
            ("camera_info", value("camera_info")),
            ("imu", value("imu")),
        ],
    )
    rviz = Node(
        package="rviz2",
        executable="rviz2",
        name="rviz2",
        namespace=value("namespace"),  # its relative topics (owl/points) then match
        arguments=["-d", str(share / "config" / "owl.rviz"), "-f", value("frame")],
        parameters=[{"use_sim_time": value("use_sim_time").lower() == "true"}],
        condition=IfCondition(LaunchConfiguration("rviz")),
    )
    return [owl, rviz]


def generate_launch_description() -> LaunchDescription:
    """Node 'owl' (owl_node) with remappable inputs, a parameter file and optional RViz."""
    share = Path(get_package_share_directory("owl_ros"))
    args = [
        DeclareLaunchArgument("image", default_value="/camera/image_raw",
                              description="sensor_msgs/Image topic (raw, not rectified: "
                              "or set rectified: true in the parameter file)"),
        DeclareLaunchArgument("camera_info", default_value="/camera/camera_info",
                              description="sensor_msgs/CameraInfo topic"),
        DeclareLaunchArgument("imu", default_value="/imu/data",
                              description="sensor_msgs/Imu topic"),
        DeclareLaunchArgument("camera_to_imu_rotation_xyzw", default_value="",
                              description="camera-to-IMU rotation x,y,z,w (empty: the "
                              "parameter file's, else TF)"),
        DeclareLaunchArgument("imu_time_offset", default_value="",
                              description="IMU stamp - camera stamp, s (empty: the file's)"),
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of the node (and of RViz)"),
        DeclareLaunchArgument("params_file", default_value=str(share / "config" / "owl.yaml"),
                              description="parameter file of node 'owl'"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="use /clock (e.g. owl_replay --clock)"),
        DeclareLaunchArgument("rviz", default_value="false",
                              description="also start RViz with config/owl.rviz"),
        DeclareLaunchArgument("frame", default_value="camera_optical_frame",
                              description="RViz fixed frame: your images' frame_id"),
    ]  # fmt: skip
    return LaunchDescription([*args, OpaqueFunction(function=_nodes, args=[share])])
