"""The parameters of node ``owl`` (and the options of ``owl_process``), in one table.

``PARAMS`` lists every parameter once: name, type, default, unit/meaning, valid range and
whether a change needs a restart (``read_only``). Everything else follows from it:

- the node declares each with a ``ParameterDescriptor`` (:func:`descriptor`: ranges as
  ``FloatingPointRange`` / ``IntegerRange``, ``read_only``, choices in
  ``additional_constraints``);
- :func:`validate` checks a set of values and returns one line per bad value, naming the
  parameter and the value (negative counts, NaN, a wrong array length...);
- :func:`build_options` turns valid values into one frozen :class:`NodeOptions` holding the
  engine's :class:`~owl_core.engine.EngineOptions` and the node's own settings;
- ``owl_process`` accepts the same names (``-p NAME:=VALUE``, ``--params-file``).

Engine parameters may change at runtime (the engine is rebuilt, its tracks reset); the
read-only ones shape subscriptions and queues and are fixed at start.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

from bags.cli import topic_name_problem
from owl_core.engine import EngineOptions
from owl_core.errors import OwlError
from owl_core.tracker import TrackerOptions

__all__ = [
    "PARAMS",
    "NodeOptions",
    "Param",
    "ParameterError",
    "build_options",
    "defaults",
    "descriptor",
    "parse_value",
    "validate",
]

#: Parameter kinds (ROS parameter types) used in the table.
KINDS = ("bool", "int", "double", "string", "double_array")


class ParameterError(ValueError):
    """One or more parameter values are invalid; ``lines`` holds one line per problem."""

    def __init__(self, lines: Iterable[str]) -> None:
        self.lines = tuple(lines)
        super().__init__("; ".join(self.lines))


@dataclass(frozen=True)
class Param:
    """One row of the parameter table.

    Attributes:
        name: ROS parameter name (also the ``owl_process -p`` name).
        kind: one of KINDS.
        default: default value (a tuple for double_array).
        description: meaning and unit, one sentence.
        low, high: inclusive valid range for int/double (None = unbounded on that side).
        read_only: True when a change needs a restart (refused at runtime).
        choices: allowed values of a string parameter.
        topic: a string parameter that names a topic (checked like ``create_subscription``
            does, so that a bad name is one parameter error, not a traceback at start).
        length: required length of a double_array.
        engine: the EngineOptions field it sets ("tracker.<field>" for TrackerOptions), or
            None for node settings (NodeOptions field of the same name).
    """

    name: str
    kind: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    read_only: bool = False
    choices: tuple[str, ...] = ()
    topic: bool = False
    length: int | None = None
    engine: str | None = None

    def constraint_text(self) -> str:
        """The valid range as text (used in descriptors, the YAML file and errors)."""
        if self.choices:
            return "one of " + ", ".join(self.choices)
        if self.length is not None:
            return f"{self.length} finite numbers"
        if self.kind in ("int", "double"):
            lo = "-inf" if self.low is None else f"{self.low:g}"
            hi = "inf" if self.high is None else f"{self.high:g}"
            return f"[{lo}, {hi}]"
        return ""


_E = EngineOptions()
_T = TrackerOptions()

#: Every parameter of node ``owl``, in declaration order.
PARAMS: tuple[Param, ...] = (
    # ---- inputs and scheduling (node settings) ---------------------------------------------
    Param(
        "image_transport",
        "string",
        "raw",
        "subscribe to 'image' (sensor_msgs/Image, raw) or 'image/compressed' "
        "(sensor_msgs/CompressedImage, compressed)",
        read_only=True,
        choices=("raw", "compressed"),
    ),
    Param(
        "queue_size",
        "int",
        2,
        "images waiting for processing, count; when full the oldest is dropped (newest "
        "wins), and the node processes the newest frame the IMU already covers; more than "
        "1 lets a frame wait for an IMU that arrives after the next image",
        low=1,
        high=100,
        read_only=True,
    ),
    Param(
        "imu_wait_s",
        "double",
        0.1,
        "longest wait for IMU samples covering a frame's interval before it is processed "
        "with what exists (and flagged), s",
        low=0.0,
        high=5.0,
    ),
    Param(
        "imu_max_gap_s",
        "double",
        0.05,
        "a longer gap between IMU samples is not interpolated across: frames whose interval "
        "spans it are processed as not covered by the IMU (flagged or skipped), s",
        low=1e-3,
        high=1.0,
    ),
    Param(
        "significant_bits",
        "int",
        16,
        "significant bits of mono16 images (e.g. 12 for a 12-bit sensor), scaled to 8 bits",
        low=1,
        high=16,
    ),
    Param(
        "speed_source",
        "string",
        "none",
        "metric scale: 'none' (x y z in seconds), 'odometry' (nav_msgs/Odometry) or 'twist' "
        "(geometry_msgs/TwistStamped) on speed_topic (x y z in metres)",
        read_only=True,
        choices=("none", "odometry", "twist"),
    ),
    Param(
        "speed_topic",
        "string",
        "odom",
        "topic of the speed source (relative names are remappable)",
        read_only=True,
        topic=True,
    ),
    Param(
        "speed_max_age_s",
        "double",
        0.2,
        "a speed message farther than this from the image stamp is not used, s",
        low=0.0,
        high=10.0,
    ),
    Param(
        "min_speed",
        "double",
        0.05,
        "below this speed the cloud stays in seconds (scale unobservable), m/s",
        low=0.0,
        high=1000.0,
    ),
    Param(
        "rectified",
        "bool",
        False,
        "the image topic is rectified (image_rect): the projection P of camera_info is "
        "used and its distortion D ignored; false: a raw image, K and D are used (connect "
        "image_raw)",
        read_only=True,
    ),
    Param(
        "publish_debug_image",
        "bool",
        True,
        "offer owl/debug_image (tracks and heading mark; built only while subscribed)",
        read_only=True,
    ),
    Param(
        "diagnostics_period_s",
        "double",
        1.0,
        "period of /diagnostics, s",
        low=0.05,
        high=60.0,
    ),
    # ---- camera-IMU extrinsic and timing (contract) ----------------------------------------
    Param(
        "camera_to_imu_rotation_xyzw",
        "double_array",
        tuple(float(v) for v in _E.camera_to_imu_rotation_xyzw),
        "rotation taking camera-optical-frame vectors into the IMU frame (TF rotation "
        "IMU -> camera optical frame), quaternion x y z w",
        length=4,
        engine="camera_to_imu_rotation_xyzw",
    ),
    Param(
        "imu_time_offset",
        "double",
        _E.imu_time_offset_s,
        "IMU stamp minus camera stamp for simultaneous events, s",
        low=-1.0,
        high=1.0,
        engine="imu_time_offset_s",
    ),
    Param(
        "rolling_shutter_readout_s",
        "double",
        _E.rolling_shutter_readout_s,
        "rolling-shutter readout time, s: row 0 to the row after the last (image height x "
        "line time); the row at pixel v is seen at stamp + (v / height) x this, and the "
        "engine gives each feature its row's time (gyro rotation, track fit; outputs refer "
        "to the stamp); a frame waits for IMU up to stamp + this; 0 = global shutter",
        low=0.0,
        high=0.5,
        engine="rolling_shutter_readout_s",
    ),
    Param(
        "estimate_imu_time_offset",
        "bool",
        _E.estimate_time_offset,
        "estimate a residual camera-IMU time offset online from the leftover rotation of "
        "each frame (a time offset looks like a gyro bias proportional to the angular "
        "acceleration) and use it, with the bias estimated jointly, once its 1-sigma is "
        "below 5 ms; starts from imu_time_offset; 'owl: gyro' shows it",
        engine="estimate_time_offset",
    ),
    Param(
        "calibration_check",
        "bool",
        True,
        "compare the rotation seen in the images with the gyro over the last 2 s every 30 "
        "frames and WARN in 'owl: gyro' when the camera-IMU rotation or time offset "
        "disagree (owl_core.calib_check); false: off (saves about 5 ms per frame)",
    ),
    Param(
        "require_gyro",
        "bool",
        _E.require_gyro,
        "true: frames without IMU coverage give no points; false: processed without "
        "derotation, every point flagged NO_GYRO (16)",
        engine="require_gyro",
    ),
    # ---- engine ----------------------------------------------------------------------------
    Param(
        "max_features",
        "int",
        _E.max_features,
        "features tracked, count",
        low=1,
        high=20000,
        engine="max_features",
    ),
    Param(
        "fit_frames",
        "int",
        _E.fit_frames,
        "frames per track in the bearing-vs-time fit, count",
        low=2,
        high=30,
        engine="fit_frames",
    ),
    Param(
        "fit_order",
        "int",
        _E.fit_order,
        "order of that fit: 1 straight line, 2 quadratic",
        low=1,
        high=2,
        engine="fit_order",
    ),
    Param(
        "min_track_frames",
        "int",
        _E.min_track_frames,
        "tracks seen in fewer frames give no point, count (<= fit_frames)",
        low=2,
        high=30,
        engine="min_track_frames",
    ),
    Param(
        "pixel_noise_px",
        "double",
        _E.pixel_noise_px,
        "1-sigma tracking noise per image axis, px",
        low=1e-4,
        high=100.0,
        engine="pixel_noise_px",
    ),
    Param(
        "neighbours",
        "int",
        _E.neighbours,
        "image neighbours of the local looming rule, count",
        low=3,
        high=200,
        engine="neighbours",
    ),
    Param(
        "min_neighbours",
        "int",
        _E.min_neighbours,
        "fewer usable neighbours -> no L from the local rule, count (<= neighbours)",
        low=3,
        high=200,
        engine="min_neighbours",
    ),
    Param(
        "neighbour_radius_px",
        "double",
        _E.neighbour_radius_px,
        "neighbours farther than this are not used, px",
        low=1.0,
        high=10000.0,
        engine="neighbour_radius_px",
    ),
    Param(
        "min_quality",
        "double",
        _E.min_quality,
        "points below this quality are flagged LOW_QUALITY (8), 0..1",
        low=0.0,
        high=1.0,
        engine="min_quality",
    ),
    Param(
        "moving_sigma",
        "double",
        _E.moving_sigma,
        "a point disagreeing with the heading by more than this many sigmas is flagged MOVING (4)",
        low=0.1,
        high=100.0,
        engine="moving_sigma",
    ),
    Param(
        "estimate_bias",
        "bool",
        _E.estimate_bias,
        "estimate the gyro bias from the flow, jointly with the heading",
        engine="estimate_bias",
    ),
    Param(
        "initial_bias_imu",
        "double_array",
        tuple(float(v) for v in _E.initial_bias_imu),
        "initial gyro bias, IMU frame, rad/s (x y z)",
        length=3,
        engine="initial_bias_imu",
    ),
    Param(
        "bias_initial_sigma",
        "double",
        _E.bias_initial_sigma,
        "1-sigma of the initial bias per axis, rad/s",
        low=1e-9,
        high=10.0,
        engine="bias_initial_sigma",
    ),
    Param(
        "bias_random_walk",
        "double",
        _E.bias_random_walk,
        "gyro bias random walk, rad/s/sqrt(s)",
        low=0.0,
        high=10.0,
        engine="bias_random_walk",
    ),
    Param(
        "bias_scatter_window",
        "int",
        _E.bias_scatter_window,
        "frames over which the bias filter measures how far the frames' leftover rotations "
        "scatter beyond their claimed noise (real sensors' model errors) and widens its "
        "measurements by it; 0 trusts the claims",
        low=0,
        high=10000,
        engine="bias_scatter_window",
    ),
    Param(
        "gyro_noise_density",
        "double",
        _E.gyro_noise_density,
        "gyro white-noise density, rad/s/sqrt(Hz)",
        low=1e-9,
        high=10.0,
        engine="gyro_noise_density",
    ),
    Param(
        "max_frame_gap_s",
        "double",
        _E.max_frame_gap_s,
        "a longer gap between frames resets the tracks, s",
        low=1e-3,
        high=60.0,
        engine="max_frame_gap_s",
    ),
    Param(
        "seed",
        "int",
        _E.seed,
        "seed of the RANSAC random generator (results are deterministic)",
        low=0,
        high=2**31 - 1,
        engine="seed",
    ),
    # ---- tracker ---------------------------------------------------------------------------
    Param(
        "tracker_min_distance_px",
        "double",
        _T.min_distance_px,
        "minimum distance between a new corner and any feature, px",
        low=0.0,
        high=1000.0,
        engine="tracker.min_distance_px",
    ),
    Param(
        "tracker_detect_level",
        "int",
        _T.detect_level,
        "pyramid level the corner search runs on (0: the image; 1: half size, a quarter of "
        "the detection CPU; docs/performance.md says what it costs)",
        low=0,
        high=3,
        engine="tracker.detect_level",
    ),
    Param(
        "tracker_fb_threshold_px",
        "double",
        _T.fb_threshold_px,
        "largest forward-backward tracking round-trip error, px",
        low=1e-3,
        high=100.0,
        engine="tracker.fb_threshold_px",
    ),
    Param(
        "tracker_lk_window_px",
        "int",
        _T.lk_window_px,
        "Lucas-Kanade window side, px (odd)",
        low=5,
        high=101,
        engine="tracker.lk_window_px",
    ),
    Param(
        "tracker_lk_levels",
        "int",
        _T.lk_levels,
        "pyramid levels above the full image",
        low=0,
        high=8,
        engine="tracker.lk_levels",
    ),
    Param(
        "tracker_lk_backward_levels",
        "int",
        _T.lk_backward_levels,
        "pyramid levels of the forward-backward check pass (capped at tracker_lk_levels)",
        low=0,
        high=8,
        engine="tracker.lk_backward_levels",
    ),
    Param(
        "tracker_lk_backward_window_px",
        "int",
        _T.lk_backward_window_px,
        "window side of the forward-backward check pass, px (odd; 0: tracker_lk_window_px)",
        low=0,
        high=101,
        engine="tracker.lk_backward_window_px",
    ),
    Param(
        "tracker_lk_predicted_levels",
        "int",
        _T.lk_predicted_levels,
        "pyramid levels of the first forward pass of points predicted by the gyro and their "
        "last displacement; points it does not serve are tracked again with "
        "tracker_lk_levels (>= tracker_lk_levels: one full pass)",
        low=0,
        high=8,
        engine="tracker.lk_predicted_levels",
    ),
    Param(
        "tracker_lk_predict_velocity",
        "bool",
        _T.lk_predict_velocity,
        "start Lucas-Kanade at the gyro prediction plus each track's last translational "
        "displacement (a new track: its neighbours'), so that the shallow first pass "
        "converges (false: every point from the gyro prediction alone)",
        engine="tracker.lk_predict_velocity",
    ),
    Param(
        "tracker_lk_deformation_correction",
        "bool",
        _T.lk_deformation_correction,
        "remove from each tracked position the first-order error translation-only "
        "Lucas-Kanade makes on a window whose content deforms (its flow gradient fitted to "
        "the neighbouring tracks' flows): tracks stay on their scene points as surfaces loom",
        engine="tracker.lk_deformation_correction",
    ),
    # ---- dense stage (owl_core.dense; node settings) ---------------------------------------
    Param(
        "dense",
        "bool",
        False,
        "run the dense stage and offer owl/looming, owl/range_over_speed, owl/depth/image "
        "(+ camera_info), owl/dense_points and owl/time_to_contact (each built only while "
        "subscribed; owl_process writes all of them)",
        read_only=True,
    ),
    Param(
        "dense_process",
        "bool",
        True,
        "the dense stage runs in a child process of its own (owl-dense), so it does not "
        "take turns with the sparse engine at Python's GIL (owl_process: it measures one "
        "frame while the engine runs the next); false: in a thread of the node (in "
        "owl_process's own thread)",
        read_only=True,
    ),
    Param(
        "dense_width",
        "int",
        320,
        "working width of the dense stage, px (the image is resized to it)",
        low=16,
        high=4096,
    ),
    Param("dense_height", "int", 240, "working height of the dense stage, px", low=16, high=4096),
    Param(
        "dense_preset",
        "string",
        "balanced",
        "DIS dense-flow preset: OpenCV's ultrafast, fast, medium, or balanced (medium with "
        "fewer iterations: as accurate, about 25 % less flow time; ultrafast is about 7x "
        "faster than medium, less accurate)",
        choices=("ultrafast", "fast", "balanced", "medium"),
    ),
    Param(
        "dense_baseline_frames",
        "int",
        3,
        "dense flow between the current image and the one this many frames earlier, count",
        low=1,
        high=10,
    ),
    Param(
        "dense_min_confidence",
        "double",
        0.5,
        "confidence (0..1: texture, forward-backward flow, fit residual, precision, route "
        "agreement) at or above which a pixel is published",
        low=0.0,
        high=1.0,
    ),
    Param(
        "dense_cloud_stride",
        "int",
        4,
        "owl/dense_points holds every n-th working pixel in each direction, count",
        low=1,
        high=64,
    ),
    Param(
        "dense_max_rate_hz",
        "double",
        0.0,
        "the dense stage measures at most this many frames per second (its images are kept "
        "every frame, so the flow baseline stays dense_baseline_frames); leaves CPU to the "
        "sparse engine on small computers, Hz (0 = every frame it can)",
        low=0.0,
        high=1000.0,
    ),
    Param(
        "ttc_cone_deg",
        "double",
        10.0,
        "half-angle of the path cone about the heading for the time to contact, degrees",
        low=0.1,
        high=89.0,
    ),
    Param(
        "ttc_warn_s",
        "double",
        1.0,
        "'owl: dense' in /diagnostics WARNs while the shortest time to contact in the path "
        "cone is below this, s (0 = never)",
        low=0.0,
        high=1000.0,
    ),
)

_BY_NAME: dict[str, Param] = {p.name: p for p in PARAMS}


@dataclass(frozen=True)
class NodeOptions:
    """Everything node ``owl`` and ``owl_process`` need, read once from the parameters.

    Attributes:
        engine: the engine's options (extrinsic, time offset, require_gyro, tracking...).
        image_transport: "raw" or "compressed".
        queue_size: frames waiting for processing, count (newest wins when full).
        imu_wait_s: bounded wait for IMU coverage of a frame, s.
        imu_max_gap_s: longest IMU sample gap interpolated across, s.
        significant_bits: significant bits of mono16 images.
        speed_source: "none", "odometry" or "twist".
        speed_topic: topic of the speed source.
        speed_max_age_s: largest |speed stamp - image stamp| used, s.
        min_speed: below this the cloud stays in seconds, m/s.
        publish_debug_image: offer owl/debug_image.
        rectified: the image is rectified: camera_info's P is used, D ignored.
        diagnostics_period_s: period of /diagnostics, s.
        calibration_check: run the live camera-IMU calibration check.
        dense: run the dense stage (owl_ros.dense_outputs) and offer its topics.
        dense_process: the dense stage runs in a child process (else in a thread).
        dense_width, dense_height: its working size, px.
        dense_preset: DIS preset name.
        dense_baseline_frames: flow baseline, frames.
        dense_min_confidence: published pixels' least confidence, 0..1.
        dense_cloud_stride: owl/dense_points stride, working px.
        dense_max_rate_hz: most frames per second the dense stage measures, Hz (0: all).
        ttc_cone_deg: path-cone half-angle, degrees.
        ttc_warn_s: WARN below this time to contact, s (0 = never).
    """

    engine: EngineOptions = field(default_factory=EngineOptions)
    image_transport: str = "raw"
    queue_size: int = 2
    imu_wait_s: float = 0.1
    imu_max_gap_s: float = 0.05
    significant_bits: int = 16
    speed_source: str = "none"
    speed_topic: str = "odom"
    speed_max_age_s: float = 0.2
    min_speed: float = 0.05
    publish_debug_image: bool = True
    diagnostics_period_s: float = 1.0
    calibration_check: bool = True
    dense: bool = False
    dense_process: bool = True
    dense_width: int = 320
    dense_height: int = 240
    dense_preset: str = "balanced"
    dense_baseline_frames: int = 3
    dense_min_confidence: float = 0.5
    dense_cloud_stride: int = 4
    dense_max_rate_hz: float = 0.0
    ttc_cone_deg: float = 10.0
    ttc_warn_s: float = 1.0
    rectified: bool = False

    def with_values(self, values: Mapping[str, Any]) -> NodeOptions:
        """These options with some parameters changed (validated; ParameterError)."""
        return build_options({**to_values(self), **values})


def defaults() -> dict[str, Any]:
    """Parameter name -> default value."""
    return {p.name: p.default for p in PARAMS}


def _check(p: Param, value: Any) -> str | None:
    """One line describing why ``value`` is invalid for ``p``, or None."""
    if p.kind == "bool":
        return None if isinstance(value, bool) else f"must be true or false, got {value!r}"
    if p.kind == "string":
        if not isinstance(value, str):
            return f"must be a string, got {value!r}"
        if p.choices and value not in p.choices:
            return f"must be one of {', '.join(p.choices)}, got {value!r}"
        if not p.choices and not value.strip():
            return "must not be empty"
        return _topic_name_error(value) if p.topic else None
    if p.kind == "double_array":
        if isinstance(value, str | bytes) or not isinstance(value, Iterable):
            return f"must be a list of {p.length} numbers, got {value!r}"
        items = list(value)
        if p.length is not None and len(items) != p.length:
            return f"must have {p.length} elements, got {len(items)}: {items!r}"
        if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in items):
            return f"must hold numbers, got {items!r}"
        if not all(math.isfinite(v) for v in items):
            return f"must hold finite numbers, got {items!r}"
        return None
    if p.kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            return f"must be an integer, got {value!r}"
    elif isinstance(value, bool) or not isinstance(value, int | float):
        return f"must be a number, got {value!r}"
    elif not math.isfinite(value):
        return f"must be finite, got {value!r}"
    if (p.low is not None and value < p.low) or (p.high is not None and value > p.high):
        return f"must be in {p.constraint_text()}, got {value!r}"
    return None


def _topic_name_error(name: str) -> str | None:
    """Why ``name`` is not a topic name a node can resolve (rcl's own rules), or None."""
    why = topic_name_problem(name, full=False)
    return None if why is None else f"must be a valid topic name ({why}), got {name!r}"


def validate(values: Mapping[str, Any], *, unknown_ok: bool = False) -> list[str]:
    """Check parameter values (each alone, then together).

    Args:
        values: parameter name -> value (missing names take their default).
        unknown_ok: ignore names that are not in the table (e.g. ``use_sim_time``).

    Returns:
        One line per problem: ``"parameter NAME: must ..., got VALUE"``; empty when valid.
    """
    lines = []
    for name, value in values.items():
        p = _BY_NAME.get(name)
        if p is None:
            if not unknown_ok:
                lines.append(f"parameter {name}: unknown parameter")
            continue
        why = _check(p, value)
        if why is not None:
            lines.append(f"parameter {name}: {why}")
    quat = values.get("camera_to_imu_rotation_xyzw")
    if quat is not None and not lines:
        norm = math.sqrt(sum(float(v) ** 2 for v in quat))
        if abs(norm - 1.0) > 1e-2:
            lines.append(
                f"parameter camera_to_imu_rotation_xyzw: must be a unit quaternion, got "
                f"{list(quat)!r} (norm {norm:.6g})"
            )
    if lines:
        return lines
    try:
        _build({**defaults(), **{k: v for k, v in values.items() if k in _BY_NAME}})
    except (OwlError, ValueError) as err:
        lines.append(_relate(str(err)))
    return lines


def _relate(message: str) -> str:
    """Name the parameter in an EngineOptions/TrackerOptions error message."""
    found = [
        (message.find(p.engine.split(".")[-1]), p.name)
        for p in PARAMS
        if p.engine is not None and p.engine.split(".")[-1] in message
    ]
    if found:
        return f"parameter {min(found)[1]}: {message}"
    return f"parameters: {message}"


def _engine_options(values: Mapping[str, Any]) -> EngineOptions:
    engine: dict[str, Any] = {}
    tracker: dict[str, Any] = {}
    for p in PARAMS:
        if p.engine is None:
            continue
        value = values[p.name]
        if p.kind == "double_array":
            value = tuple(float(v) for v in value)
        elif p.kind == "double":
            value = float(value)
        if p.engine.startswith("tracker."):
            tracker[p.engine.split(".", 1)[1]] = value
        else:
            engine[p.engine] = value
    return EngineOptions(**engine, tracker=replace(TrackerOptions(), **tracker))


def _build(values: Mapping[str, Any]) -> NodeOptions:
    node_fields = {f.name for f in fields(NodeOptions)} - {"engine"}
    node: dict[str, Any] = {}
    for name in node_fields:
        value = values[name]
        node[name] = float(value) if _BY_NAME[name].kind == "double" else value
    return NodeOptions(engine=_engine_options(values), **node)


def build_options(values: Mapping[str, Any] | None = None) -> NodeOptions:
    """Validated values -> NodeOptions (missing names take their default).

    Raises:
        ParameterError: with one line per bad value (see :func:`validate`).
    """
    given = dict(values or {})
    lines = validate(given, unknown_ok=True)
    if lines:
        raise ParameterError(lines)
    return _build({**defaults(), **{k: v for k, v in given.items() if k in _BY_NAME}})


def to_values(options: NodeOptions) -> dict[str, Any]:
    """NodeOptions -> parameter name -> value (inverse of :func:`build_options`)."""
    out: dict[str, Any] = {}
    for p in PARAMS:
        if p.engine is None:
            out[p.name] = getattr(options, p.name)
        elif p.engine.startswith("tracker."):
            out[p.name] = getattr(options.engine.tracker, p.engine.split(".", 1)[1])
        else:
            value = getattr(options.engine, p.engine)
            out[p.name] = tuple(value) if p.kind == "double_array" else value
    return out


def parse_value(name: str, text: str) -> Any:
    """A command-line value (``owl_process -p NAME:=TEXT``) as the parameter's type.

    YAML syntax as ``ros2 param set`` uses it: ``true``, ``5``, ``0.5``, ``[0, 0, 0, 1]``;
    ints are accepted for doubles. Raises ParameterError naming the parameter and text.
    """
    import yaml

    p = _BY_NAME.get(name)
    if p is None:
        import difflib

        close = difflib.get_close_matches(name, list(_BY_NAME), n=1, cutoff=0.75)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise ParameterError([f"parameter {name}: unknown parameter{hint}"])
    if p.kind == "string":
        return text
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        raise ParameterError([f"parameter {name}: cannot parse {text!r}"]) from None
    if p.kind == "double" and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if p.kind == "double" and isinstance(value, str) and value.lower() in ("nan", ".nan"):
        value = math.nan
    if p.kind == "double_array" and isinstance(value, list):
        value = [float(v) if isinstance(v, int) and not isinstance(v, bool) else v for v in value]
    return value


def parse_assignment(item: str) -> tuple[str, Any]:
    """One ``-p NAME:=VALUE`` item of a tool's command line (``NAME=VALUE`` too) -> (name,
    value of the parameter's type); ParameterError naming the item or the value."""
    name, sep, text = item.partition(":=")
    if not sep:
        name, sep, text = item.partition("=")
    name = name.strip()
    if not sep or not name:
        raise ParameterError([f"-p expects NAME:=VALUE, got {item!r}"])
    return name, parse_value(name, text)


def find(name: str) -> Param | None:
    """The table's row of parameter ``name`` (None for an unknown name)."""
    return _BY_NAME.get(name)


def descriptor(p: Param) -> Any:
    """rcl_interfaces/ParameterDescriptor of ``p`` (ranges, read_only, constraints text)."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

    desc = ParameterDescriptor(
        name=p.name,
        description=p.description,
        read_only=p.read_only,
        additional_constraints=p.constraint_text(),
    )
    if p.kind == "int" and (p.low is not None or p.high is not None):
        desc.integer_range = [
            IntegerRange(
                from_value=int(p.low if p.low is not None else -(2**63)),
                to_value=int(p.high if p.high is not None else 2**63 - 1),
                step=1,
            )
        ]
    elif p.kind == "double" and (p.low is not None or p.high is not None):
        desc.floating_point_range = [
            FloatingPointRange(
                from_value=float(p.low if p.low is not None else -1e300),
                to_value=float(p.high if p.high is not None else 1e300),
                step=0.0,
            )
        ]
    return desc


#: parameters that config/owl.yaml lists commented out, and why: setting one there would
#: change what the node does when it is not set.
UNSET_IN_FILE = {
    "camera_to_imu_rotation_xyzw": (
        "Not set here: unset, the node takes it from TF (the IMU -> camera optical frame "
        "transform, once both frame_ids are known) and owl_process from the bag's /tf_static, "
        "else the identity; set, it overrides TF."
    ),
}


def config_yaml() -> str:
    """The text of ``config/owl.yaml``: every parameter with its default, meaning, range
    and read-only flag, as a ROS 2 parameter file for node ``owl``."""
    import textwrap

    out = [
        "# Parameters of node 'owl' (executable owl_node) and of owl_process",
        "# (-p / --params-file). Load with:",
        "#   ros2 run owl_ros owl_node --ros-args --params-file config/owl.yaml",
        "# Every parameter is listed with its default; 'read-only' ones need a restart, the",
        "# others may be changed at runtime (ros2 param set /owl NAME VALUE; the engine then",
        "# restarts its tracks). Doubles need a decimal point (1.0, not 1): ROS 2 parameter",
        "# types are strict. Generated from owl_ros/params.py by params.config_yaml().",
        "# '/**' applies it to the node in any namespace and under any name (-r __ns:=/robot1,",
        "# ros2 launch ... namespace:=robot1); a key 'owl' would match /owl only.",
        "/**:",
        "  ros__parameters:",
    ]

    def fmt(p: Param) -> str:
        v = p.default
        if p.kind == "bool":
            return "true" if v else "false"
        if p.kind == "string":
            return f'"{v}"'
        if p.kind == "double":
            return repr(float(v))
        if p.kind == "double_array":
            return "[" + ", ".join(repr(float(x)) for x in v) + "]"
        return str(v)

    for p in PARAMS:
        out += textwrap.wrap(
            f"{p.description}.", 92, initial_indent="    # ", subsequent_indent="    #   "
        )
        extra = []
        if p.constraint_text():
            extra.append(f"valid: {p.constraint_text()}")
        if p.read_only:
            extra.append("read-only")
        if extra:
            out.append(f"    # ({'; '.join(extra)})")
        if p.name in UNSET_IN_FILE:
            out += textwrap.wrap(
                UNSET_IN_FILE[p.name], 92, initial_indent="    # ", subsequent_indent="    # "
            )
            out.append(f"    # {p.name}: {fmt(p)}")
            continue
        out.append(f"    {p.name}: {fmt(p)}")
    return "\n".join(out) + "\n"
