"""Named synthetic scenarios with exact ground truth, usable in memory or as bags.

In-memory use (tests, benchmarks, engine end-to-end runs; no bag needed)::

    from bags.sim import scenarios
    scenarios.names()                       # ["cube", "scaled", ...]
    scenarios.DESCRIPTIONS["street"]        # one line
    sim = scenarios.get("street").simulate(SimOptions(seconds=1.0, width=320, height=240))
    sim.camera                              # owl_core.camera.CameraModel
    sim.gyro_samples()                      # owl_core.types.GyroSamples (IMU frame, IMU clock)
    sim.imu                                 # sensors.ImuData (gyro, accel, true rate, bias)
    sim.camera_to_imu_xyzw, sim.imu_time_offset_ns
    for f in sim.frames():                  # Frame: stamp_ns, image, range_m, mask, twist...
        ...
    sim.relative_rotation(t0_ns, t1_ns)     # exact R_{1<-0} between two camera stamps

Ground truth conventions: ``Frame.velocity`` is the camera velocity relative to the static
scene and ``Frame.omega`` its angular velocity, both in the camera optical frame at the
image stamp; ``range_m`` is the distance from the camera centre along each pixel-centre ray
(metres, +inf = sky); ``mask`` is True on independently moving objects.

Rolling shutter (``SimOptions.rolling_shutter_readout_s`` = T > 0): image row r is rendered
at ``t_frame + (r / height) T`` (its own pose, the movers where they are then), so the
stamp is the time of row 0 (:mod:`owl_core.rolling_shutter` states the same convention).
The twist, ``R_wc`` and ``c_w`` stay those of the stamp. ``range_m`` is then the distance
from the camera centre *at the stamp* to the scene point each pixel sees (at its row's
time): the range of that point in the snapshot at the stamp, which is what the engine's
outputs refer to (for a moving object, where it was at its row's time). Scene and
trajectories live in a world frame with x forward, y left, z up (see bags.sim.sensors).

Every scenario takes ``scale`` (:class:`SimOptions`): the whole scene, its textures and
the camera path are multiplied by it (speeds too; rotations unchanged), so images, L,
omega and RoT are identical for every scale while ranges and speeds scale. ``scaled`` is
the scenario meant for that comparison (default scale 3; compare with ``scale=1``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from bags import layout
from bags.errors import ScenarioError
from bags.sim.render import Rect, RenderedFrame, Renderer, box, exposure_blur
from bags.sim.sensors import (
    ImuData,
    ImuOptions,
    Trajectory,
    bump_yaw,
    car_trajectory,
    heading_following_angles,
    polynomial_path,
    scaled_path,
    sine_angles,
    synthesize_imu,
)
from owl_core.camera import CameraModel
from owl_core.types import GyroSamples

F64 = npt.NDArray[np.float64]

#: Camera stamp of scenario time 0 (2023-11-14T22:13:20Z), ns.
DEFAULT_START_NS = 1_700_000_000_000_000_000
CAMERA_FRAME = layout.CAMERA_FRAME
IMU_FRAME = layout.IMU_FRAME
CAMERA_HEIGHT = 1.5


@dataclass(frozen=True)
class MovingObject:
    """An object whose rectangles depend on time (scenario seconds)."""

    object_id: int
    rects_at: Callable[[float], list[Rect]]


@dataclass(frozen=True)
class SimOptions:
    """How to sample a scenario.

    Attributes:
        seconds: duration, s (> 0). rate_hz: camera frame rate, Hz (> 0).
        width, height: image size, pixels (> 0).
        hfov_deg: horizontal field of view of the pinhole part, degrees (0 < hfov < 170).
        distortion: () for none, or plumb_bob (k1, k2, p1, p2, k3).
        encoding: "mono8" or "rgb8".
        seed: seed of image noise and IMU noise.
        noise_sigma: image noise standard deviation, grey levels.
        supersample: sub-pixel rays per axis at object edges (1..4).
        scale: geometric scale of scene and path (> 0; see module doc). None = the
            scenario's default (3 for ``scaled``, 1 otherwise).
        start_ns: camera stamp of the first frame, ns.
        imu: the IMU model (its seed is replaced by ``seed``).
        rolling_shutter_readout_s: readout time of a rolling shutter, s (row 0 to the row
            after the last; 0 = global shutter; see the module doc).
    """

    seconds: float = 3.0
    rate_hz: float = 30.0
    width: int = 640
    height: int = 480
    hfov_deg: float = 70.0
    distortion: tuple[float, ...] = ()
    encoding: str = "mono8"
    seed: int = 0
    noise_sigma: float = 2.0
    supersample: int = 2
    scale: float | None = None
    start_ns: int = DEFAULT_START_NS
    imu: ImuOptions = field(default_factory=ImuOptions)
    rolling_shutter_readout_s: float = 0.0

    def __post_init__(self) -> None:
        checks = [
            (self.seconds, "seconds", lambda x: x > 0),
            (self.rate_hz, "rate", lambda x: x > 0),
            (self.hfov_deg, "hfov_deg", lambda x: 0 < x < 170),
        ]
        for value, name, ok in checks:
            if not (isinstance(value, int | float) and math.isfinite(value) and ok(value)):
                msg = f"{name} out of range: {value!r}"
                raise ScenarioError(msg)
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                msg = f"{name} must be a positive integer number of pixels, got {value!r}"
                raise ScenarioError(msg)
        if isinstance(self.supersample, bool) or self.supersample not in (1, 2, 3, 4):
            msg = f"supersample must be an integer in 1..4, got {self.supersample!r}"
            raise ScenarioError(msg)
        if not (math.isfinite(self.noise_sigma) and self.noise_sigma >= 0):
            msg = f"image noise sigma must be finite and >= 0, got {self.noise_sigma!r}"
            raise ScenarioError(msg)
        if self.scale is not None and not (math.isfinite(self.scale) and self.scale > 0):
            msg = f"scale must be a positive number, got {self.scale!r}"
            raise ScenarioError(msg)
        if len(self.distortion) not in (0, 5):
            msg = f"distortion must be empty or 5 plumb_bob numbers, got {self.distortion!r}"
            raise ScenarioError(msg)
        if self.encoding not in ("mono8", "rgb8"):
            msg = f"encoding must be mono8 or rgb8, got {self.encoding!r}"
            raise ScenarioError(msg)
        if self.start_ns < 0:
            msg = f"start_ns must be >= 0, got {self.start_ns}"
            raise ScenarioError(msg)
        readout = self.rolling_shutter_readout_s
        if not (isinstance(readout, int | float) and math.isfinite(readout) and 0 <= readout < 1):
            msg = f"rolling-shutter readout must be in [0, 1) s, got {readout!r}"
            raise ScenarioError(msg)

    def camera(self) -> CameraModel:
        """The camera model: square pixels, principal point at the image centre."""
        fx = 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2)
        k = np.array([[fx, 0, (self.width - 1) / 2], [0, fx, (self.height - 1) / 2], [0, 0, 1]])
        if self.distortion:
            return CameraModel(self.width, self.height, k, np.array(self.distortion), "plumb_bob")
        return CameraModel(self.width, self.height, k, np.zeros(0), "none")

    @property
    def num_frames(self) -> int:
        """Frames at t = k / rate for t <= seconds (at least 2)."""
        return max(2, math.floor(self.seconds * self.rate_hz + 1e-9) + 1)


@dataclass(frozen=True)
class Frame:
    """One rendered camera frame with ground truth.

    Attributes:
        index: frame number. stamp_ns: camera stamp, ns. t: scenario time, s.
        image: (H, W) uint8 mono8 or (H, W, 3) uint8 rgb8.
        range_m: (H, W) float32 metres along each pixel-centre ray (+inf sky, NaN invalid).
        object_id: (H, W) uint16 object hit by each pixel-centre ray (0 = sky).
        mask: (H, W) bool, True on independently moving objects (all False if none).
        velocity: (3,) camera velocity relative to the static scene, camera frame, m/s.
        omega: (3,) camera angular velocity, camera frame, rad/s.
        R_wc: (3, 3) camera-to-world rotation. c_w: (3,) camera centre, world, m.
    """

    index: int
    stamp_ns: int
    t: float
    image: npt.NDArray[np.uint8]
    range_m: npt.NDArray[np.float32]
    object_id: npt.NDArray[np.uint16]
    mask: npt.NDArray[np.bool_]
    velocity: F64
    omega: F64
    R_wc: F64
    c_w: F64


@dataclass(frozen=True)
class Scenario:
    """A scene (static rectangles + moving objects) and a body trajectory.

    Geometry is stored at scale 1; :meth:`simulate` applies ``SimOptions.scale``.
    """

    name: str
    description: str
    static: tuple[Rect, ...]
    trajectory: Trajectory
    movers: tuple[MovingObject, ...] = ()
    default_scale: float = 1.0

    @property
    def moving_ids(self) -> frozenset[int]:
        """Object ids of the independently moving objects."""
        return frozenset(m.object_id for m in self.movers)

    def simulate(self, options: SimOptions | None = None) -> Simulation:
        """The sampled scenario (renderer, IMU) for ``options``."""
        return Simulation(self, options or SimOptions())

    def render_frames(self, options: SimOptions | None = None) -> Iterator[Frame]:
        """Shortcut for ``simulate(options).frames()`` (use simulate() for the IMU too)."""
        return self.simulate(options).frames()


def _scale_rect(r: Rect, k: float) -> Rect:
    return replace(
        r,
        origin=tuple(k * np.asarray(r.origin)),
        half_u=r.half_u * k,
        half_v=r.half_v * k,
        texel_m=r.texel_m * k,
    )


class Simulation:
    """A scenario sampled with given options: frames, IMU and exact ground truth."""

    def __init__(self, scenario: Scenario, options: SimOptions) -> None:
        self.scenario = scenario
        self.options = options
        self.scale = scenario.default_scale if options.scale is None else float(options.scale)
        k = self.scale
        traj = scenario.trajectory
        self.trajectory = Trajectory(scaled_path(traj.position_fn, k), traj.angles_fn)
        self.imu_options = replace(options.imu, seed=options.seed)
        self.R_bc = self.imu_options.R_bc
        self.camera = options.camera()
        w, h = self.camera.width, self.camera.height
        border = np.array(
            [(u, v) for u in (0, w - 1) for v in range(h)]
            + [(u, v) for v in (0, h - 1) for u in range(w)],
            dtype=np.float64,
        )
        bad = ~np.all(np.isfinite(self.camera.pixel_to_bearing(border)), axis=-1)
        if bad.any():
            msg = (
                f"distortion {list(options.distortion)} leaves {int(bad.sum())} border pixels "
                "without a valid ray (the lens model folds over inside the image)"
            )
            raise ScenarioError(msg)
        self._static = [_scale_rect(r, k) for r in scenario.static]
        self._renderer: Renderer | None = None
        self._rays: F64 | None = None
        t_end = (options.num_frames - 1) / options.rate_hz + options.rolling_shutter_readout_s
        self.imu: ImuData = synthesize_imu(
            self.trajectory, self.imu_options, options.start_ns, -0.1, t_end + 0.1
        )

    # -- timing and truth -----------------------------------------------------------------

    @property
    def camera_to_imu_xyzw(self) -> tuple[float, float, float, float]:
        """Rotation camera -> IMU frame, quaternion (x, y, z, w)."""
        return self.imu_options.camera_to_imu_xyzw

    @property
    def imu_time_offset_ns(self) -> int:
        """IMU stamp - camera stamp for simultaneous events, ns."""
        return self.imu_options.time_offset_ns

    @property
    def frame_stamps_ns(self) -> npt.NDArray[np.int64]:
        """(F,) int64 camera stamps of the frames."""
        k = np.arange(self.options.num_frames)
        return self.options.start_ns + np.round(k * 1e9 / self.options.rate_hz).astype(np.int64)

    def time_of(self, stamp_ns: int) -> float:
        """Scenario time (s) of a camera stamp."""
        return (int(stamp_ns) - self.options.start_ns) * 1e-9

    def pose(self, t: float) -> tuple[F64, F64]:
        """(R_wc (3, 3), c_w (3,)) of the camera at scenario time t (s)."""
        st = self.trajectory.state(t)
        return st.R_wb[0] @ self.R_bc, st.position[0]

    def twist(self, t: float) -> tuple[F64, F64]:
        """(velocity, omega) of the camera, camera frame, at scenario time t (s)."""
        st = self.trajectory.state(t)
        r_wc = st.R_wb[0] @ self.R_bc
        return r_wc.T @ st.velocity[0], self.R_bc.T @ st.omega_b[0]

    def relative_rotation(self, t0_ns: int, t1_ns: int) -> F64:
        """Exact R_{1<-0}: camera-frame bearing of a world direction at t0 -> at t1."""
        r0, _ = self.pose(self.time_of(t0_ns))
        r1, _ = self.pose(self.time_of(t1_ns))
        out: F64 = r1.T @ r0
        return out

    def scene_at(self, t: float) -> list[Rect]:
        """All rectangles (world frame, scaled) at scenario time t (s)."""
        rects = list(self._static)
        for m in self.scenario.movers:
            rects += [_scale_rect(r, self.scale) for r in m.rects_at(t)]
        return rects

    def gyro_samples(self) -> GyroSamples:
        """The measured gyro as owl_core GyroSamples (IMU frame, IMU clock)."""
        return GyroSamples(self.imu.stamp_ns.copy(), self.imu.angular_velocity.copy())

    # -- rendering ----------------------------------------------------------------------

    @property
    def renderer(self) -> Renderer:
        """The renderer (built on first use: ray grids for the camera)."""
        if self._renderer is None:
            o = self.options
            self._renderer = Renderer(
                self.camera,
                supersample=o.supersample,
                noise_sigma=o.noise_sigma,
                seed=o.seed,
                encoding=o.encoding,
            )
        return self._renderer

    def frame(self, index: int) -> Frame:
        """Render frame ``index`` (0 <= index < num_frames)."""
        if not 0 <= index < self.options.num_frames:
            msg = f"frame index {index} outside 0..{self.options.num_frames - 1}"
            raise ScenarioError(msg)
        stamp = int(self.frame_stamps_ns[index])
        t = self.time_of(stamp)
        r_wc, c_w = self.pose(t)
        out = self._render(t, index)
        moving = np.array(sorted(self.scenario.moving_ids), dtype=np.uint16)
        mask = np.isin(out.object_id, moving)
        vel, omega = self.twist(t)
        return Frame(
            index, stamp, t, out.image, out.range_m, out.object_id, mask, vel, omega, r_wc, c_w
        )

    def frame_at(self, t: float, index: int, exposure_s: float = 0.0, samples: int = 3) -> Frame:
        """Render the camera at scenario time ``t`` (s; any time, e.g. uneven intervals).

        ``exposure_s`` > 0: motion blur, the mean of ``samples`` renders spread evenly over
        the exposure centred on ``t`` (:func:`bags.sim.render.exposure_blur`); range, object
        ids, mask and twist are those at ``t``. ``index`` selects the noise stream.
        """
        if not (math.isfinite(exposure_s) and exposure_s >= 0) or samples < 1:
            msg = f"exposure must be >= 0 s with >= 1 sample, got {exposure_s!r}, {samples!r}"
            raise ScenarioError(msg)
        stamp = self.options.start_ns + round(t * 1e9)
        r_wc, c_w = self.pose(t)
        out = self._render(t, index)
        image = out.image
        if exposure_s > 0 and samples > 1:
            subs = []
            for j, dt in enumerate(np.linspace(-exposure_s / 2, exposure_s / 2, samples)):
                sub = self._render(t + float(dt), index * samples + j + 1_000_000)
                subs.append(sub.image)
            image = exposure_blur(subs)
        moving = np.array(sorted(self.scenario.moving_ids), dtype=np.uint16)
        mask = np.isin(out.object_id, moving)
        vel, omega = self.twist(t)
        return Frame(
            index, stamp, t, image, out.range_m, out.object_id, mask, vel, omega, r_wc, c_w
        )

    def _render(self, t: float, index: int) -> RenderedFrame:
        """The image of scenario time ``t`` (s): one pose, or with a rolling shutter each
        row at its own time (``range_m`` then from the camera centre at ``t``, module doc)."""
        readout = self.options.rolling_shutter_readout_s
        if readout == 0:
            r_wc, c_w = self.pose(t)
            return self.renderer.render(self.scene_at(t), r_wc, c_w, index)
        h = self.camera.height
        times = t + np.arange(h) / h * readout
        st = self.trajectory.state(times)
        r_rows = st.R_wb @ self.R_bc
        c_rows = st.position
        if self.scenario.movers:
            scenes = [self.scene_at(float(x)) for x in times]
        else:
            scenes = [self.scene_at(t)] * h
        out = self.renderer.render_rows(scenes, r_rows, c_rows, index)
        rays = self._pixel_rays()  # (h, w, 3) camera frame
        seen = c_rows[:, None, :] + out.range_m[..., None] * np.einsum(
            "rij,rcj->rci", r_rows, rays
        )
        hit = np.isfinite(out.range_m)
        at_stamp = np.linalg.norm(seen - c_rows[0], axis=-1)
        range_m = np.where(hit, at_stamp, out.range_m).astype(np.float32)
        return RenderedFrame(out.image, range_m, out.object_id)

    def _pixel_rays(self) -> F64:
        """(H, W, 3) unit ray of every pixel centre, camera frame (cached)."""
        if self._rays is None:
            w, h = self.camera.width, self.camera.height
            uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
            self._rays = self.camera.pixel_to_bearing(np.stack([uu, vv], axis=-1))
        return self._rays

    def frames(self) -> Iterator[Frame]:
        """Render every frame in order."""
        for k in range(self.options.num_frames):
            yield self.frame(k)


# --- scenes ----------------------------------------------------------------------------

GROUND_ID = 1


def _ground(texel: float = 0.01) -> Rect:
    return Rect((0, 0, 0), (1, 0, 0), (0, 1, 0), math.inf, math.inf, GROUND_ID, 101, texel, 0.85)


def _wall(x0: float, x1: float, y: float, height: float, oid: int, seed: int) -> Rect:
    """A wall along x at lateral position y, facing the street (y = 0)."""
    sign = 1.0 if y > 0 else -1.0
    # u along x, v up; normal = u x v = (0, -1, 0): flip u for the right-hand wall
    u = (1.0 * sign, 0.0, 0.0)
    return Rect(
        ((x0 + x1) / 2, y, height / 2),
        u,
        (0.0, 0.0, 1.0),
        (x1 - x0) / 2,
        height / 2,
        oid,
        seed,
        0.02,
        0.9,
        (1.0, 0.9, 0.8),
    )


def _street_scene(x_min: float = -30.0, x_max: float = 170.0) -> list[Rect]:
    rects = [
        _ground(),
        _wall(x_min, x_max, 7.0, 10.0, 2, 102),
        _wall(x_min, x_max, -7.0, 9.0, 3, 103),
    ]
    # far end wall facing -x
    rects.append(
        Rect((x_max, 0, 6), (0, -1, 0), (0, 0, 1), 8, 6, 4, 104, 0.05, 0.8, (0.8, 0.9, 1.0))
    )
    tints = [(1.0, 0.6, 0.5), (0.5, 0.7, 1.0), (0.7, 1.0, 0.6), (1.0, 1.0, 0.5)]
    specs = [  # x, y, size (x, y, z)
        (9.0, 3.5, (3.0, 1.8, 1.5)),
        (15.0, -4.0, (2.0, 2.0, 2.5)),
        (22.0, 4.5, (4.0, 2.0, 1.6)),
        (30.0, -3.0, (1.5, 1.5, 1.0)),
        (38.0, 2.5, (2.5, 1.5, 3.0)),
        (48.0, -4.5, (4.5, 2.0, 2.0)),
        (60.0, 4.0, (3.0, 2.5, 4.0)),
        (75.0, -3.5, (3.0, 2.0, 1.8)),
        (95.0, 3.0, (5.0, 3.0, 3.0)),
        (120.0, -2.5, (4.0, 3.0, 5.0)),
        (-12.0, 3.5, (3.0, 1.8, 1.5)),
        (-20.0, -4.0, (2.0, 2.0, 2.5)),
    ]
    for i, (x, y, size) in enumerate(specs):
        rects += box(
            (x, y, size[2] / 2),
            size,
            10 + i,
            texture_seed=200 + 10 * i,
            texel_m=0.008,
            brightness=0.9,
            tint=tints[i % len(tints)],
        )
    return rects


def _cube_scene() -> list[Rect]:
    rects = [_ground(0.008)]
    rects += box((7.0, 0.8, 1.0), (1.2, 1.2, 1.2), 10, texture_seed=300, texel_m=0.004)
    return rects


def _scaled_scene() -> list[Rect]:
    rects = _cube_scene()
    rects += box((12.0, -1.5, 0.75), (1.5, 1.5, 1.5), 11, texture_seed=310, texel_m=0.005)
    rects += box((20.0, 2.5, 1.5), (3.0, 2.0, 3.0), 12, texture_seed=320, texel_m=0.008)
    rects.append(Rect((40, 0, 5), (0, -1, 0), (0, 0, 1), 20, 5, 4, 104, 0.05, 0.8))
    return rects


def _plaza_scene() -> list[Rect]:
    rects = [_ground()]
    for i, (x, y) in enumerate([(10, -3), (12, 6), (18, 2), (24, 11), (16, 14), (28, 4), (6, -4)]):
        rects += box(
            (x, y, 1.0), (2.0, 2.0, 2.0), 10 + i, texture_seed=400 + 10 * i, texel_m=0.006
        )
    walls = [((60, 0, 5), (0, -1, 0)), ((0, 60, 5), (1, 0, 0)), ((0, -60, 5), (-1, 0, 0))]
    for j, (o, u) in enumerate(walls):
        rects.append(Rect(o, u, (0, 0, 1), 60, 5, 2 + j, 500 + j, 0.05, 0.8))
    return rects


def _crossing_car(t: float) -> list[Rect]:
    # crosses the street from left to right 20 m ahead at 1.5 m/s
    return box(
        (20.0, 5.0 - 1.5 * t, 0.8),
        (4.0, 1.8, 1.6),
        50,
        texture_seed=600,
        texel_m=0.006,
        tint=(1.0, 0.4, 0.4),
    )


_H = (0.0, 0.0, CAMERA_HEIGHT)
_NO_ROT = sine_angles()


def _street_rotation(yaw: float, pitch: float) -> Callable[..., tuple[F64, F64]]:
    return sine_angles(
        amplitude=(yaw, pitch, 0.02), freq_hz=(0.4, 0.7, 0.3), phase=(0.0, 0.5, 1.0)
    )


def _turn_trajectory() -> Trajectory:
    path = polynomial_path(_H, (3.0, 0.0, 0.0), (0.0, 1.2, 0.0))
    return Trajectory(path, heading_following_angles(path, gain=0.6))


def _avenue_scene() -> list[Rect]:
    """The street widened (walls at +-11 m, boxes 1.7 x farther out), for paths that
    weave across it."""
    rects = [
        _ground(),
        _wall(-30.0, 200.0, 11.0, 10.0, 2, 102),
        _wall(-30.0, 200.0, -11.0, 9.0, 3, 103),
        Rect((200, 0, 6), (0, -1, 0), (0, 0, 1), 12, 6, 4, 104, 0.05, 0.8, (0.8, 0.9, 1.0)),
    ]
    tints = [(1.0, 0.6, 0.5), (0.5, 0.7, 1.0), (0.7, 1.0, 0.6), (1.0, 1.0, 0.5)]
    for i in range(16):
        x = -10.0 + 9.0 * i
        y = (6.0 + (i % 3)) * (1 if i % 2 else -1)
        size = (2.0 + (i % 4), 1.6 + 0.3 * (i % 3), 1.2 + 0.6 * (i % 5))
        rects += box(
            (x, y, size[2] / 2),
            size,
            10 + i,
            texture_seed=200 + 10 * i,
            texel_m=0.008,
            brightness=0.9,
            tint=tints[i % len(tints)],
        )
    return rects


def _car_speed(t: F64) -> tuple[F64, F64]:
    # 1 m/s at t = 0, 8 m/s at t = 4 s, 1 m/s again at 8 s
    w = 2 * np.pi / 8.0
    return 4.5 - 3.5 * np.cos(w * t), 3.5 * w * np.sin(w * t)


def _car_yaw(t: F64) -> tuple[F64, F64, F64]:
    # yaw rate 0.6 sin(2 pi t / 4): left and right turns at up to 0.6 rad/s
    w = 2 * np.pi / 4.0
    return -0.6 / w * np.cos(w * t), 0.6 * np.sin(w * t), 0.6 * w * np.cos(w * t)


def _brisk(street: tuple[Rect, ...]) -> Scenario:
    """Walking while turning at up to 1 rad/s: the rolling-shutter case."""
    return Scenario(
        "brisk",
        "street, camera walking forward at 1.5 m/s while turning briskly (yaw +-0.28 rad "
        "at 0.5 Hz, pitch +-0.09 rad at 0.8 Hz, roll +-0.04 rad at 0.6 Hz: up to 1 rad/s): "
        "the rolling-shutter case",
        street,
        Trajectory(
            polynomial_path(_H, (1.5, 0.0, 0.0)),
            sine_angles(amplitude=(0.28, 0.09, 0.04), freq_hz=(0.5, 0.8, 0.6), phase=(0, 0.5, 1)),
        ),
    )


def _motion_scenarios(street: tuple[Rect, ...]) -> list[Scenario]:
    """The scenarios of the paper's kinds of motion (translation, turns, movers)."""
    return [
        Scenario(
            "cube",
            "the paper's first experiment: a textured cube (and ground) seen by a camera in "
            "rectilinear translation",
            tuple(_cube_scene()),
            Trajectory(polynomial_path(_H, (1.0, 0.15, 0.0)), _NO_ROT),
        ),
        Scenario(
            "scaled",
            "three boxes, translation with a slow yaw; scene and path x --scale (default 3): "
            "same images and OWL values as --scale 1, ranges and speeds x scale",
            tuple(_scaled_scene()),
            Trajectory(
                polynomial_path(_H, (1.2, -0.2, 0.05)),
                sine_angles(amplitude=(0.05, 0, 0), freq_hz=(0.3, 0, 0)),
            ),
            default_scale=3.0,
        ),
        Scenario(
            "accel",
            "street, camera accelerating forward at 2 m/s^2 from 1 m/s, no rotation",
            street,
            Trajectory(polynomial_path(_H, (1.0, 0.0, 0.0), (2.0, 0.0, 0.0)), _NO_ROT),
        ),
        Scenario(
            "turn",
            "plaza of boxes, camera path curving left (lateral 1.2 m/s^2 at 3 m/s), camera "
            "yaw following 60% of the path direction",
            tuple(_plaza_scene()),
            _turn_trajectory(),
        ),
        Scenario(
            "street",
            "street with walls, ground and boxes; camera at 4 m/s while yawing (+-0.15 rad) "
            "and pitching (+-0.06 rad)",
            street,
            Trajectory(polynomial_path(_H, (4.0, 0.0, 0.0)), _street_rotation(0.15, 0.06)),
        ),
        Scenario(
            "mover",
            "street with a car crossing 20 m ahead at 1.5 m/s (moving-object mask); camera at "
            "3 m/s, gentle yaw and pitch",
            street,
            Trajectory(polynomial_path(_H, (3.0, 0.0, 0.0)), _street_rotation(0.08, 0.03)),
            movers=(MovingObject(50, _crossing_car),),
        ),
        Scenario(
            "rotation_only",
            "street, camera standing still and rotating (yaw +-0.3 rad, pitch +-0.1 rad): no "
            "translation, no OWL points expected",
            street,
            Trajectory(polynomial_path(_H, (0, 0, 0)), _street_rotation(0.3, 0.1)),
        ),
    ]


def _special_scenarios(street: tuple[Rect, ...]) -> list[Scenario]:
    """Calibration recordings, a still camera, and the realistic bench motions."""
    return [
        Scenario(
            "pan_only",
            "street, camera standing still and panning (yaw +-0.3 rad) about one axis only: "
            "owl_calibrate must refuse it",
            street,
            Trajectory(
                polynomial_path(_H, (0, 0, 0)),
                sine_angles(amplitude=(0.3, 0, 0), freq_hz=(0.4, 0, 0)),
            ),
        ),
        Scenario(
            "handheld",
            "street, camera walking forward at 1.2 m/s while turning about all three axes "
            "(yaw +-0.25, pitch +-0.12, roll +-0.08 rad): a recording for owl_calibrate",
            street,
            Trajectory(
                polynomial_path(_H, (1.2, 0.0, 0.0)),
                sine_angles(
                    amplitude=(0.25, 0.12, 0.08), freq_hz=(0.45, 0.7, 0.55), phase=(0, 0.5, 1)
                ),
            ),
        ),
        Scenario(
            "still",
            "street, camera not moving at all: no points, no heading expected",
            street,
            Trajectory(polynomial_path(_H, (0, 0, 0)), _NO_ROT),
        ),
        Scenario(
            "car",
            "a car weaving down a wide street (speed 1 to 8 m/s, yaw rate up to 0.6 rad/s), "
            "camera and IMU 1.5 m ahead of the rear axle: the heading swings up to 20 deg off "
            "the optical axis in turns (meant for 10 Hz)",
            tuple(_avenue_scene()),
            car_trajectory(_car_speed, _car_yaw, 1.5, (0.0, 0.0, CAMERA_HEIGHT)),
        ),
        Scenario(
            "sideways",
            "street, camera moving sideways (to its right) at 0.4 m/s; its yaw rate is zero, "
            "rises to 0.4 rad/s and falls back to zero between 1 and 2 s (a slider whose "
            "rotation starts and stops)",
            street,
            Trajectory(
                polynomial_path((5.0, 2.0, CAMERA_HEIGHT), (0.0, -0.4, 0.0)),
                bump_yaw(1.0, 1.0, 0.4),
            ),
        ),
        Scenario(
            "slow_start",
            "street, camera starting at 0.3 m/s and accelerating forward at 1 m/s^2, gentle "
            "yaw and pitch",
            street,
            Trajectory(
                polynomial_path(_H, (0.3, 0.0, 0.0), (1.0, 0.0, 0.0)), _street_rotation(0.05, 0.02)
            ),
        ),
        Scenario(
            "receding",
            "street, camera moving backwards at 3 m/s while looking forward (L < 0)",
            street,
            Trajectory(polynomial_path((40.0, 0.0, CAMERA_HEIGHT), (-3.0, 0.0, 0.0)), _NO_ROT),
        ),
    ]


def _build() -> dict[str, Scenario]:
    street = tuple(_street_scene())
    scenes = _motion_scenarios(street) + _special_scenarios(street) + [_brisk(street)]
    return {s.name: s for s in scenes}


_SCENARIOS = _build()
#: name -> one-line description, in listing order.
DESCRIPTIONS: dict[str, str] = {name: s.description for name, s in _SCENARIOS.items()}


def names() -> list[str]:
    """Scenario names in listing order."""
    return list(_SCENARIOS)


def get(name: str) -> Scenario:
    """The scenario called ``name``.

    Raises:
        ScenarioError: unknown name (the message lists the known ones).
    """
    try:
        return _SCENARIOS[name]
    except KeyError:
        msg = f"unknown scenario {name!r} (choose from: {', '.join(_SCENARIOS)})"
        raise ScenarioError(msg) from None
