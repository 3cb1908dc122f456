"""The scenario simulator: camera, scene and IMU models that render synthetic runs with
exact ground truth (``render``, ``scenarios``, ``sensors``). Used in memory by tests, the
benchmark and the demo, and written to bags by ``bags.cli.make_bag``."""
