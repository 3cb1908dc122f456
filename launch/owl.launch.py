"""Launch node 'owl' with config/owl.yaml and the usual camera/IMU remappings.

    ros2 launch owl_ros owl.launch.py image:=/camera/image_raw camera_info:=/camera/camera_info \\
        imu:=/imu/data use_sim_time:=false params_file:=/path/to/owl.yaml rviz:=true
"""

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def generate_launch_description() -> LaunchDescription:
    """Node 'owl' (owl_node) with remappable inputs, a parameter file and optional RViz."""
    share = Path(get_package_share_directory("owl_ros"))
    args = [
        DeclareLaunchArgument("image", default_value="/camera/image_raw",
                              description="sensor_msgs/Image topic"),
        DeclareLaunchArgument("camera_info", default_value="/camera/camera_info",
                              description="sensor_msgs/CameraInfo topic"),
        DeclareLaunchArgument("imu", default_value="/imu/data",
                              description="sensor_msgs/Imu topic"),
        DeclareLaunchArgument("params_file", default_value=str(share / "config" / "owl.yaml"),
                              description="parameter file of node 'owl'"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="use /clock (e.g. owl_replay --clock)"),
        DeclareLaunchArgument("rviz", default_value="false",
                              description="also start RViz with config/owl.rviz"),
    ]  # fmt: skip
    owl = Node(
        package="owl_ros",
        executable="owl_node",
        name="owl",
        output="screen",
        parameters=[
            LaunchConfiguration("params_file"),
            {"use_sim_time": LaunchConfiguration("use_sim_time")},
        ],
        remappings=[
            ("image", LaunchConfiguration("image")),
            ("image/compressed", [LaunchConfiguration("image"), "/compressed"]),
            ("camera_info", LaunchConfiguration("camera_info")),
            ("imu", LaunchConfiguration("imu")),
        ],
    )
    rviz = Node(
        package="rviz2",
        executable="rviz2",
        name="rviz2",
        arguments=["-d", str(share / "config" / "owl.rviz")],
        parameters=[{"use_sim_time": LaunchConfiguration("use_sim_time")}],
        condition=IfCondition(LaunchConfiguration("rviz")),
    )
    return LaunchDescription([*args, owl, rviz])
