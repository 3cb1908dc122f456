"""owl_ros: the rclpy node `owl`, its pipeline and parameters, and owl_process (the product);
the evaluation, benchmark, soak, latency and demo tools live apart in ``owl_ros.tools``."""
