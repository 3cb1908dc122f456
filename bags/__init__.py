"""bags: synthetic scenarios with ground truth, rosbag2 MCAP reading/writing, replay, record."""
