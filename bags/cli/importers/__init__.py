"""Importers of public dataset folders into the project's standard bag layout (owl_import).

- :mod:`bags.cli.importers.asl`: the ASL folder layout of EuRoC MAV and TUM-VI (``mav0/cam0``,
  ``mav0/imu0``, optional ``state_groundtruth_estimate0`` or ``mocap0``);
- :mod:`bags.cli.importers.kitti`: the KITTI odometry layout (``image_0``, ``calib.txt``,
  ``times.txt``, optional poses and IMU files);
- :mod:`bags.cli.importers.common`: the :class:`~bags.cli.importers.common.Dataset` record both
  readers return, the strict CSV reader, the ground-truth differentiation and the writer;
- :mod:`bags.cli.importers.cli`: the ``owl_import`` command.

The bag has the synthetic bags' topics, frames and QoS (see :mod:`bags.cli.make_bag`), so
``owl_process``, ``owl_replay`` and ``owl_eval`` read it unchanged.
"""
