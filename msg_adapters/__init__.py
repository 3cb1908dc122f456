"""msg_adapters: ROS 2 messages <-> numpy arrays and owl_core records, table-driven.

Modules (import the one you need; nothing is re-exported so importing the package stays
cheap):

- ``errors``: AdapterError(ValueError) and its subclasses.
- ``stamps``: builtin_interfaces/Time <-> int nanoseconds, headers.
- ``image``: Image / CompressedImage <-> arrays, ``to_mono8``, ``image_to_frame``.
- ``camera_info``: CameraInfo <-> owl_core.camera.CameraModel.
- ``imu``: Imu (REP 145) <-> owl_core.types.GyroSamples.
- ``pointcloud``: FrameResult -> owl/points PointCloud2, any PointCloud2 -> structured array.
- ``heading``: heading (3,) <-> Vector3Stamped.
- ``diagnostics``: StatusRecord <-> DiagnosticArray.
"""
