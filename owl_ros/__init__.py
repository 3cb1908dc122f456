"""owl_ros: the rclpy node `owl` and the command-line tools."""
