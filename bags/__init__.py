"""bags: rosbag2 MCAP reading/writing (``bags.io``, ``bags.errors``), the scenario simulator
with exact ground truth (``bags.sim``) and the command-line tools make_bag, replay and record
(``bags.cli``). The library and the simulator never import ``bags.cli``."""
