"""msg_adapters: ROS 2 messages <-> numpy arrays and owl_core records, table-driven."""
