"""Dense OWL outputs of node ``owl`` and ``owl_process`` (parameter ``dense: true``).

The glue between :class:`~owl_ros.pipeline.Pipeline` outputs and
:class:`owl_core.dense.DenseOwl`: after each processed frame, :meth:`DenseStage.run` hands
the grey image, the gyro rotation since the dense stage's previous image (bias removed,
from the engine's gyro buffer) and the engine's heading to the dense stage, and
:func:`build_messages` turns its result into messages (only the ones asked for):

| topic | type | content |
|---|---|---|
| ``owl/looming`` | sensor_msgs/Image 32FC1 | L, 1/s, NaN where not confident |
| ``owl/range_over_speed`` | sensor_msgs/Image 32FC1 | r/|t|, s, NaN where not confident |
| ``owl/depth/image`` | sensor_msgs/Image 32FC1 | z/|t| (s), z (m) with a known speed |
| ``owl/depth/camera_info`` | sensor_msgs/CameraInfo | the working grid's calibration |
| ``owl/dense_points`` | sensor_msgs/PointCloud2 | confident pixels at a stride |
| ``owl/time_to_contact`` | geometry_msgs/PointStamped | bearing x shortest TTC (s) |

Images are on the working grid (``dense_width`` x ``dense_height``) of the input image,
with the input image's header. ``owl/time_to_contact``: ``point`` is the unit bearing of
the pixel with the shortest time to contact inside the path cone multiplied by that time
in seconds, so ``|point|`` is the time to contact and ``point/|point|`` where it is (the
same direction in the camera optical frame); NaN x y z when nothing confident approaches
inside the cone. A PointStamped was chosen because it is the smallest stamped message that
carries both what a planner acts on and where it lies (sensor_msgs/Range has no
direction: its cone is the frame's x axis), and RViz draws it as is.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters.camera_info import camera_model_to_info
from msg_adapters.diagnostics import Level, StatusRecord
from msg_adapters.image import array_to_image
from msg_adapters.pointcloud import array_to_cloud
from owl_core.camera import CameraModel
from owl_core.dense import DenseOptions, DenseOwl, DenseResult
from owl_core.engine import OwlEngine
from owl_core.errors import OwlError
from owl_ros.params import NodeOptions

__all__ = [
    "TOPICS",
    "DenseStage",
    "build_messages",
    "dense_options",
    "working_camera",
]

#: topic (relative name) -> ROS message type name, in publication order.
TOPICS: dict[str, str] = {
    "owl/looming": "sensor_msgs/msg/Image",
    "owl/range_over_speed": "sensor_msgs/msg/Image",
    "owl/depth/image": "sensor_msgs/msg/Image",
    "owl/depth/camera_info": "sensor_msgs/msg/CameraInfo",
    "owl/dense_points": "sensor_msgs/msg/PointCloud2",
    "owl/time_to_contact": "geometry_msgs/msg/PointStamped",
}

_CLOUD_DTYPE = np.dtype(
    [
        ("x", np.float32),
        ("y", np.float32),
        ("z", np.float32),
        ("u", np.float32),
        ("v", np.float32),
        ("L", np.float32),
        ("range_over_speed", np.float32),
        ("confidence", np.float32),
    ]
)


def dense_options(options: NodeOptions) -> DenseOptions:
    """The dense stage's settings from the node options."""
    return DenseOptions(
        width=options.dense_width,
        height=options.dense_height,
        preset=options.dense_preset,
        baseline_frames=options.dense_baseline_frames,
        min_confidence=options.dense_min_confidence,
        ttc_cone_deg=options.ttc_cone_deg,
    )


def working_camera(camera: CameraModel, width: int, height: int) -> CameraModel:
    """The camera model of the working grid: K scaled about pixel centres, same lens."""
    sx, sy = width / camera.width, height / camera.height
    k = np.array(camera.K, dtype=np.float64)
    k[0, 0] *= sx
    k[0, 1] *= sx
    k[0, 2] = (k[0, 2] + 0.5) * sx - 0.5
    k[1, 1] *= sy
    k[1, 2] = (k[1, 2] + 0.5) * sy - 0.5
    return CameraModel(width, height, k, np.array(camera.D), camera.distortion_model)


@dataclass
class _Last:
    result: DenseResult | None = None
    error: str = ""
    frames: int = 0
    warned: int = 0
    gyro_missing: int = 0
    # shortest time to contact since the last status: (seconds, pixel (u, v) or None)
    window_min: tuple[float, Any] | None = None


class DenseStage:
    """Runs :class:`~owl_core.dense.DenseOwl` after the sparse engine, frame by frame.

    Args:
        options: node options (the ``dense_*`` and ``ttc_*`` parameters).
    """

    def __init__(self, options: NodeOptions) -> None:
        self.options = options
        self._dense: DenseOwl | None = None
        self._work: CameraModel | None = None
        self._last = _Last()

    @property
    def last(self) -> DenseResult | None:
        """The latest dense result (None before the second frame)."""
        return self._last.result

    @property
    def camera_info_model(self) -> CameraModel | None:
        """The working grid's camera model (None before the first frame)."""
        return self._work

    def reset(self) -> None:
        """Forget the kept images (call when nobody listens for a while)."""
        if self._dense is not None:
            self._dense.reset()

    def run(
        self, engine: OwlEngine | None, camera: CameraModel | None, image: Any, result: Any
    ) -> DenseResult | None:
        """One frame: ``image`` (H, W) uint8 grey, ``result`` the engine's FrameResult."""
        if engine is None or camera is None:
            return None
        opts = dense_options(self.options)
        if self._dense is None or self._dense.camera != camera or self._dense.options != opts:
            self._dense = DenseOwl(camera, opts)
            self._work = working_camera(camera, opts.width, opts.height)
        dense = self._dense
        stamp = int(result.stamp_ns)
        prev = dense.previous_stamp_ns
        rotation = None
        if prev is not None and prev < stamp:
            if engine.gyro.covers(prev, stamp):
                rotation = engine.gyro.relative_rotation(prev, stamp, engine.gyro_bias)
            else:
                self._last.gyro_missing += 1
        try:
            out = dense.process(image, stamp, rotation, result.heading, result.heading_sigma_rad)
        except OwlError as err:
            self._last.error = f"dense: {err}"
            dense.reset()
            return None
        self._last.frames += 1
        self._last.result = out
        ttc = out.ttc if out is not None else None
        if ttc is not None and math.isfinite(ttc.seconds):
            best = self._last.window_min
            if best is None or ttc.seconds < best[0]:
                self._last.window_min = (ttc.seconds, ttc.pixel)
            if self._warning(ttc.seconds, ttc.pixel) is not None:
                self._last.warned += 1
        return out

    def _warning(self, seconds: float, pixel: Any) -> str | None:
        """The WARN line when a time to contact is below ``ttc_warn_s``."""
        limit = self.options.ttc_warn_s
        if not limit > 0 or not math.isfinite(seconds) or seconds >= limit:
            return None
        where = "" if pixel is None else f" at pixel ({pixel[0]:.0f}, {pixel[1]:.0f})"
        return f"time to contact {seconds:.2f} s < ttc_warn_s {limit:g} s{where}"

    def status(self) -> StatusRecord:
        """The ``owl: dense`` diagnostic status since the last call: WARN when the shortest
        time to contact in the path cone went below ``ttc_warn_s`` meanwhile."""
        last = self._last
        res = last.result
        window_min, last.window_min = last.window_min, None
        values: dict[str, object] = {
            "dense_frames_total": last.frames,
            "ttc_warnings_total": last.warned,
            "frames_without_gyro_total": last.gyro_missing,
        }
        if res is None:
            msg = last.error or "no dense result yet (needs two frames while subscribed)"
            return StatusRecord.build("owl: dense", Level.OK, msg, values)
        ttc = res.ttc
        shortest = window_min[0] if window_min is not None else math.nan
        values.update(
            {
                "confident_fraction": res.confident_fraction,
                "dense_ms": 1e3 * res.timings.get("total", math.nan),
                "ttc_s": ttc.seconds if ttc is not None else math.nan,
                "ttc_min_period_s": shortest,
                "ttc_cone_pixels": ttc.pixels_in_cone if ttc is not None else 0,
            }
        )
        if window_min is not None:
            warning = self._warning(*window_min)
            if warning is not None:
                return StatusRecord.build("owl: dense", Level.WARN, warning, values)
        text = "; ".join(res.reasons) or (
            "no approaching confident pixel in the path cone"
            if not math.isfinite(shortest)
            else f"shortest time to contact {shortest:.2f} s"
        )
        return StatusRecord.build("owl: dense", Level.OK, text, values)


def _image(array: Any, header: Any) -> Any:
    return array_to_image(np.ascontiguousarray(array, dtype=np.float32), "32FC1", header=header)


def build_messages(
    result: DenseResult,
    work_camera: CameraModel,
    header: Any,
    speed: float | None,
    stride: int,
    wanted: Callable[[str], bool],
) -> dict[str, Any]:
    """Messages of one dense result for the topics where ``wanted(topic)`` is true.

    ``speed`` (m/s) makes the depth image and the cloud metric; None keeps seconds.
    """
    from geometry_msgs.msg import PointStamped

    out: dict[str, Any] = {}
    conf = result.confident
    nan = np.float32(np.nan)
    scale = np.float32(speed) if speed is not None else np.float32(1.0)
    if wanted("owl/looming"):
        out["owl/looming"] = _image(np.where(conf, result.looming, nan), header)
    if wanted("owl/range_over_speed"):
        out["owl/range_over_speed"] = _image(np.where(conf, result.range_over_speed, nan), header)
    if wanted("owl/depth/image"):
        out["owl/depth/image"] = _image(
            np.where(conf, result.depth_over_speed * scale, nan), header
        )
    if wanted("owl/depth/camera_info"):
        out["owl/depth/camera_info"] = camera_model_to_info(work_camera, header)
    if wanted("owl/dense_points"):
        sub = (slice(None, None, stride), slice(None, None, stride))
        keep = conf[sub]
        pts = result.points[sub][keep] * scale
        v, u = np.nonzero(keep)
        cloud = np.zeros(pts.shape[0], dtype=_CLOUD_DTYPE)
        cloud["x"], cloud["y"], cloud["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
        cloud["u"] = (u * stride).astype(np.float32)
        cloud["v"] = (v * stride).astype(np.float32)
        cloud["L"] = result.looming[sub][keep]
        cloud["range_over_speed"] = result.range_over_speed[sub][keep]
        cloud["confidence"] = result.confidence[sub][keep]
        out["owl/dense_points"] = array_to_cloud(cloud, header)
    if wanted("owl/time_to_contact"):
        msg = PointStamped(header=header)
        ttc = result.ttc
        if ttc is not None and ttc.bearing is not None and math.isfinite(ttc.seconds):
            p = ttc.bearing * ttc.seconds
            msg.point.x, msg.point.y, msg.point.z = float(p[0]), float(p[1]), float(p[2])
        else:
            msg.point.x = msg.point.y = msg.point.z = math.nan
        out["owl/time_to_contact"] = msg
    return out


class DensePublishers:
    """The node's dense publishers; builds each message only while it has a subscriber.

    Args:
        node: the rclpy node (publishers are created on it, reliable QoS ``qos``).
        options: node options.
        qos: QoS profile of the publications.
    """

    def __init__(self, node: Any, options: NodeOptions, qos: Any) -> None:
        from geometry_msgs.msg import PointStamped
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2

        kinds = {
            "sensor_msgs/msg/Image": Image,
            "sensor_msgs/msg/CameraInfo": CameraInfo,
            "sensor_msgs/msg/PointCloud2": PointCloud2,
            "geometry_msgs/msg/PointStamped": PointStamped,
        }
        self.stage = DenseStage(options)
        self._pubs = {t: node.create_publisher(kinds[k], t, qos) for t, k in TOPICS.items()}
        self._idle = True

    def publish(self, out: Any, engine: OwlEngine | None, camera: CameraModel | None) -> None:
        """Run the dense stage on one pipeline Output and publish what is subscribed."""
        listening = {t for t, p in self._pubs.items() if p.get_subscription_count() > 0}
        if not listening:
            if not self._idle:
                self.stage.reset()  # the kept images would be stale when someone returns
            self._idle = True
            return
        self._idle = False
        result = self.stage.run(engine, camera, out.image, out.result)
        work = self.stage.camera_info_model
        if result is None or work is None:
            return
        stride = self.stage.options.dense_cloud_stride
        msgs = build_messages(result, work, out.header, out.speed, stride, listening.__contains__)
        for topic, msg in msgs.items():
            self._pubs[topic].publish(msg)

    @property
    def publishers(self) -> list[Any]:
        """The publishers (for the shutdown flush)."""
        return list(self._pubs.values())


class DenseWriter:
    """``owl_process``'s dense topics: every message of every frame, into a bag writer.

    Args:
        options: node options.
        writer: a ``bags.io.BagWriter`` (topics are added here, ``/`` + the relative name).
        encode: ``(msg, msgtype) -> CDR bytes`` (owl_process's canonical encoder).
    """

    def __init__(self, options: NodeOptions, writer: Any, encode: Callable[[Any, str], bytes]):
        self.stage = DenseStage(options)
        self._writer = writer
        self._encode = encode
        for topic, kind in TOPICS.items():
            writer.add_topic("/" + topic, kind, "reliable")

    def write(self, out: Any, engine: OwlEngine | None, camera: CameraModel | None) -> None:
        """Run the dense stage on one pipeline Output and write all its messages."""
        from msg_adapters.stamps import header_to_ns

        result = self.stage.run(engine, camera, out.image, out.result)
        work = self.stage.camera_info_model
        if result is None or work is None:
            return
        stride = self.stage.options.dense_cloud_stride
        stamp = max(header_to_ns(out.header), 0)
        msgs = build_messages(result, work, out.header, out.speed, stride, lambda _: True)
        for topic, msg in msgs.items():
            self._writer.write_raw("/" + topic, stamp, self._encode(msg, TOPICS[topic]))
