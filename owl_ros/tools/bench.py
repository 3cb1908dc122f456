"""owl_bench: OWL against the classical two-view baseline, side by side, in one process.

For each standard case (a named scenario from :mod:`bags.sim.scenarios`, with or without a
constant gyro bias) the frames are rendered in memory (no bags, no DDS) or loaded from the
cache (``~/.cache/owl_ros/frames``, see ``--cache-dir``; the images do not depend on the
IMU, so the biased and unbiased rows share them). Then one pass over the frames:

1. the OWL engine (:class:`owl_core.engine.OwlEngine`) processes the image and the gyro;
2. on exactly the engine's tracks of that frame, the baseline runs at each frame gap of
   :data:`GAPS` (1, 2 and 4: the current frame paired with the one that many frames
   earlier; a camera faster than 30 Hz also at the gap spanning 4 frames' time at 30 Hz,
   :func:`case_gaps`) in two variants (:mod:`owl_core.baseline`): OpenCV's 5-point essential matrix
   + recoverPose + triangulation ("cv-5pt@G"), and the gyro-aided translation-only variant
   ("cv-gyro@G", derotated with the same gyro, less the true bias where the case knows it,
   else the bias OWL has estimated by then); each of them also through OWL's own heading
   filter at each measurement sigma of :data:`FILTER_SIGMAS_DEG` ("cv-gyro@G+kfS",
   :class:`owl_core.baseline.FilteredBaseline`, predicting with that gyro and bias too), so
   that OWL is not credited with its temporal filter or its bias estimate;
3. all are scored by the same :mod:`owl_ros.tools.evaluate` functions against the truth. Per case
   the best baseline (lowest heading median, then p90) is named, and OWL is checked
   against the lowest median and p90 any baseline reaches at any gap, filtered or not.

``--bag BAG`` (repeatable) runs the same on a recorded or imported bag in the standard
layout (``/camera/image_raw``, ``/camera/camera_info``, ``/imu/data``, ``/tf_static``,
``/ground_truth/twist``; ``/ground_truth/range`` and ``moving_mask`` when present), see
:func:`bag_source`.

Timing: per-stage times from the engine (track = LK + detection, integrate, heading,
looming) and the baseline's estimation time; frames/s = frames / (tracking + estimation)
for each method (they share tracking); ``estimation_speedup`` = baseline estimation time /
OWL estimation time (tracking excluded). One thread (OpenCV and BLAS). Peak memory is the
process's maximum resident set size (it includes rendering).

``owl_bench`` (full, ``make bench``): 640x480, 1000 features, 3 s at 30 Hz per case, plus
the :data:`REALISTIC` cases (other rates, the car, IMU models, camera effects; labels
``NAME[@RATEhz][+IMU][+EFFECT]...[+bias]``, :func:`parse_case`). A rolling-shutter effect
(``brisk+rs30``: a 30 ms readout) runs OWL compensating it ("owl") and ignoring it
(:data:`UNCOMPENSATED`); the same scenario without the effect is the global shutter.
``owl_bench --quick``: 320x240, 300 features, 1 s, five cases (one realistic).
``--json`` prints one object (keys in :func:`run_bench`'s docstring).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import resource
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from bags import layout
from bags.cli import OneLineErrorParser, user_cache_dir
from bags.errors import BagError
from bags.io import BagReader, RawMessage
from bags.sim import scenarios
from bags.sim.render import apply_gain, sensor_noise
from bags.sim.scenarios import SimOptions, Simulation
from bags.sim.sensors import IMU_MODELS, ImuOptions
from owl_core.baseline import BaselineFrame, BaselineOptions, FilteredBaseline, TwoViewBaseline
from owl_core.camera import CameraModel
from owl_core.engine import EngineOptions, OwlEngine
from owl_core.errors import OwlError
from owl_core.rolling_shutter import ReadoutRotations, readout_rotations
from owl_core.types import FrameResult, GyroSamples, ImageFrame
from owl_ros import params
from owl_ros.heap import keep_freed_memory
from owl_ros.threads import one_thread
from owl_ros.tools.errors import BenchError, EvalError, ToolError
from owl_ros.tools.evaluate import (
    Estimate,
    FrameScore,
    Truth,
    paired_range_errors,
    score_frame,
    summarize,
)

PROG = "owl_bench"
#: Frame gaps at which both baselines run (the current frame paired with the one this many
#: frames earlier): 1 is the strongest two-view estimate on straight motion, 4 has more
#: parallax but lags on curving paths.
GAPS = (1, 2, 4)
#: The frame rate at which :data:`GAPS` were chosen, Hz. A faster camera's case also runs
#: the gap that spans what 4 frames span here (60 Hz: 8 frames), as far as the tracks'
#: history reaches (:func:`case_gaps`), so that a fast camera does not leave the baselines
#: only short gaps.
GAPS_RATE_HZ = 30.0
BASELINES = ("cv-5pt", "cv-gyro")
#: The measurement 1-sigmas (deg) at which each baseline's heading also runs through OWL's
#: own heading filter (:class:`owl_core.baseline.FilteredBaseline`; "cv-5pt@1+kf0.2", ...):
#: the grid spans what suits a 10 Hz car (0.05) to a 30 Hz walk (0.5), and each case is
#: judged against the best of them, as it is against the best gap.
FILTER_SIGMAS_DEG = (0.05, 0.2, 0.5)


def _methods(gaps: Sequence[int]) -> tuple[tuple[str, ...], tuple[tuple[str, str, float], ...]]:
    """Every scored method at ``gaps`` (OWL, each baseline at each gap "cv-5pt@1", ..., and
    each of those filtered "cv-5pt@1+kf0.2", ...) and the filtered settings (name, the
    two-view method it filters, sigma in deg)."""
    two_view = tuple(f"{b}@{g}" for b in BASELINES for g in gaps)
    filtered = tuple((f"{m}+kf{s:g}", m, s) for m in two_view for s in FILTER_SIGMAS_DEG)
    return ("owl", *two_view, *(f[0] for f in filtered)), filtered


#: Every scored method of a camera at :data:`GAPS_RATE_HZ` or slower (:func:`_methods`).
METHODS = _methods(GAPS)[0]
#: Bias magnitude of the biased rows, rad/s, along (1, 1, 1)/sqrt(3) in the IMU frame.
BIAS = 0.01
#: Scenarios without independently moving objects and with translation (pooled accuracy).
STATIC = ("cube", "scaled", "accel", "turn", "street", "receding")


#: Image effects of real cameras a case can add (:func:`effect_frames`).
EFFECTS = ("blur", "noise", "gain", "jpeg", "jitter", "drop", "rs30")
#: Rolling-shutter readout of an effect, s: the images are rendered with it, OWL runs with
#: ``rolling_shutter_readout_s`` set to it ("owl") and once more ignoring it
#: (:data:`UNCOMPENSATED`).
READOUTS = {"rs30": 0.030}
#: The extra method of a rolling-shutter case: OWL with ``rolling_shutter_readout_s`` 0.
UNCOMPENSATED = "owl-uncomp"


@dataclass(frozen=True)
class Case:
    """One benchmark row: a scenario and a gyro-bias magnitude (rad/s), or a bag
    (``bag``: path of a bag in the standard layout; ``scenario`` is then "bag").

    Attributes:
        scenario: scenario name. bias: constant gyro bias magnitude, rad/s.
        bag: path of a bag ("" = synthetic).
        rate_hz: camera rate, Hz (0 = the profile's).
        seconds: duration, s (0 = the profile's).
        imu: IMU model name of :data:`bags.sim.sensors.IMU_MODELS` ("" = the default IMU).
        effects: image effects of :data:`EFFECTS`.
    """

    scenario: str
    bias: float = 0.0
    bag: str = ""
    rate_hz: float = 0.0
    seconds: float = 0.0
    imu: str = ""
    effects: tuple[str, ...] = ()

    @property
    def readout_s(self) -> float:
        """Rolling-shutter readout of the case's images, s (0: global shutter)."""
        return sum(READOUTS.get(x, 0.0) for x in self.effects)

    @property
    def label(self) -> str:
        """e.g. "street", "street+bias", "car@10hz+mems200+blur" or "bag:NAME"."""
        if self.bag:
            return "bag:" + Path(self.bag).name
        out = self.scenario + (f"@{self.rate_hz:g}hz" if self.rate_hz else "")
        out += "".join(f"+{x}" for x in (self.imu, *self.effects) if x)
        return out + ("+bias" if self.bias else "")


@dataclass(frozen=True)
class Profile:
    """Sizes of a benchmark run."""

    name: str
    width: int
    height: int
    seconds: float
    features: int
    cases: tuple[Case, ...]
    rate_hz: float = 30.0
    #: "cpu": stage times are the process's CPU time (time.process_time: what the work
    #: costs, independent of other load on the machine; every thread counts, so a
    #: library's worker thread cannot hide work); "wall": time.perf_counter
    clock: str = "cpu"
    #: render seeds (image and IMU noise) each synthetic case runs with; its figures are
    #: over the frames of all of them
    seeds: tuple[int, ...] = (0,)
    #: node parameters of the engine (``owl_bench -p NAME:=VALUE``) that OWL runs with
    #: instead of their defaults; the tracks, and so the baselines, follow them too
    engine_params: tuple[tuple[str, Any], ...] = ()


#: node parameters the bench sets itself: from --features, or from each case's sensors
BENCH_SETS = {
    "max_features": "give it as --features",
    "camera_to_imu_rotation_xyzw": "each case has its own",
    "imu_time_offset": "each case has its own",
    "rolling_shutter_readout_s": "each case has its own",
}


def parse_engine_params(items: Sequence[str]) -> tuple[tuple[str, Any], ...]:
    """``NAME:=VALUE`` items (node parameters that set an engine option) -> (name, value)
    pairs, validated as the node validates them; BenchError naming the item otherwise."""
    out: dict[str, Any] = {}
    for item in items:
        try:
            name, value = params.parse_assignment(item)
            params.build_options({name: value})
        except params.ParameterError as err:
            raise BenchError("; ".join(err.lines)) from None
        if name in BENCH_SETS:
            raise BenchError(f"-p {item}: the bench sets {name} ({BENCH_SETS[name]})")
        row = params.find(name)
        if row is None or row.engine is None:
            raise BenchError(f"-p {item}: {name} is a node setting, not one of the engine")
        out[name] = value
    return tuple(out.items())


#: Duration of the ``car`` cases, s (its speed and yaw profile repeats every 8 s).
CAR_SECONDS = 8.0
#: Cases of real cameras and IMUs: rates of 10 to 60 Hz, a car at 10 Hz, a slider whose
#: rotation starts and stops, a slow start, IMU models of real parts, image effects.
REALISTIC = (
    Case("street", rate_hz=10.0),
    Case("street", rate_hz=20.0),
    Case("street", rate_hz=60.0),
    Case("car", rate_hz=10.0, seconds=CAR_SECONDS),
    Case("car", 0.0, "", 10.0, CAR_SECONDS, "mems200", ("blur", "noise", "gain", "jpeg")),
    Case("sideways", rate_hz=26.0, imu="adis16448"),
    Case("slow_start"),
    Case("street", imu="adis16448", effects=("jitter", "drop")),
    Case("street", imu="mems400", effects=("blur", "noise", "gain", "jpeg")),
    Case("turn", imu="mems100"),
    Case("brisk"),
    Case("brisk", effects=("rs30",)),
)
FULL = Profile(
    "full",
    640,
    480,
    3.0,
    1000,
    tuple(Case(s) for s in (*STATIC, "mover", "rotation_only"))
    + tuple(Case(s, BIAS) for s in ("street", "turn", "cube", "mover"))
    + REALISTIC,
)
QUICK = Profile(
    "quick",
    320,
    240,
    1.0,
    300,
    (
        Case("street"),
        Case("street", BIAS),
        Case("cube"),
        Case("mover"),
        Case("car", 0.0, "", 10.0, CAR_SECONDS, "mems200", ("noise", "jpeg")),
    ),
)


# ------------------------------------------------------------------------ frames


@dataclass(frozen=True)
class Frames:
    """Rendered frames of one scenario with their truth (arrays stacked over F frames)."""

    stamps_ns: npt.NDArray[np.int64]
    images: npt.NDArray[np.uint8]  # (F, H, W)
    range_m: npt.NDArray[np.float32]  # (F, H, W)
    mask: npt.NDArray[np.bool_] | None  # (F, H, W)
    velocity: npt.NDArray[np.float64]  # (F, 3)

    def truth(self, k: int) -> Truth:
        """Truth record of frame k."""
        mask = None if self.mask is None else self.mask[k]
        return Truth(int(self.stamps_ns[k]), self.velocity[k], self.range_m[k], mask)


def _sim(case: Case, profile: Profile, seed: int = 0) -> Simulation:
    """The simulation of a synthetic case; ``seed`` draws its image and IMU noise."""
    b = case.bias / math.sqrt(3.0)
    imu = IMU_MODELS[case.imu] if case.imu else ImuOptions()
    opts = SimOptions(
        seconds=case.seconds or profile.seconds,
        rate_hz=case.rate_hz or profile.rate_hz,
        width=profile.width,
        height=profile.height,
        imu=replace(imu, gyro_bias=(b, b, b)),
        rolling_shutter_readout_s=case.readout_s,
        seed=seed,
    )
    return scenarios.get(case.scenario).simulate(opts)


def effect_times(case: Case, sim: Simulation) -> npt.NDArray[np.float64]:
    """Scenario times (s) of the frames a case's camera delivers: the regular grid, moved
    by up to +-25 % of the period ("jitter": uneven intervals), with 10 % of the frames
    (and never the first three) left out ("drop"). Seeded: the same every run."""
    n = sim.options.num_frames
    period = 1.0 / sim.options.rate_hz
    t = np.arange(n) * period
    rng = np.random.default_rng(1414)
    if "jitter" in case.effects:
        t[1:] += rng.uniform(-0.25, 0.25, n - 1) * period
    if "drop" in case.effects:
        keep = rng.random(n) >= 0.1
        keep[:3] = True
        t = t[keep]
    return t


#: Exposure time of the "blur" effect, s (a daylight exposure of a machine-vision camera).
EXPOSURE_S = 0.008


def effect_frames(
    case: Case, sim: Simulation, log: Callable[[str], None] = lambda s: None
) -> Frames:
    """Frames of a case with image effects (:data:`EFFECTS`), rendered in memory.

    blur: each image the mean of 3 renders over an exposure of :data:`EXPOSURE_S`
    (:meth:`bags.sim.scenarios.Simulation.frame_at`); noise: read + shot sensor noise
    (:func:`bags.sim.render.sensor_noise`); gain: a seeded auto-gain walk (x0.75 to x1.3,
    steps up to 6 % per frame, :func:`bags.sim.render.apply_gain`); jpeg: each image
    through a sensor_msgs/CompressedImage at JPEG quality 80 (the message adapters'
    encoder and decoder); jitter / drop: :func:`effect_times`; rs30: a rolling shutter with
    a 30 ms readout (the simulation's ``rolling_shutter_readout_s``, set by :func:`_sim`:
    each row at its own time). Truth at each frame's time.
    """
    from msg_adapters.image import array_to_compressed, compressed_to_frame

    times = effect_times(case, sim)
    n = times.size
    w, h = sim.options.width, sim.options.height
    images = np.zeros((n, h, w), dtype=np.uint8)
    ranges = np.zeros((n, h, w), dtype=np.float32)
    masks = np.zeros((n, h, w), dtype=bool)
    vel = np.zeros((n, 3))
    stamps = np.zeros(n, dtype=np.int64)
    rng = np.random.default_rng(2828)
    gain = 1.0
    exposure = EXPOSURE_S if "blur" in case.effects else 0.0
    t0 = time.monotonic()
    for k, t in enumerate(times):
        f = sim.frame_at(float(t), k, exposure)
        img = f.image if f.image.ndim == 2 else f.image.mean(axis=2).astype(np.uint8)
        if "gain" in case.effects:
            gain = float(np.clip(gain * math.exp(rng.uniform(-0.06, 0.06)), 0.75, 1.3))
            img = apply_gain(img, gain)
        if "noise" in case.effects:
            img = sensor_noise(img, rng)
        if "jpeg" in case.effects:
            img = compressed_to_frame(array_to_compressed(img, "mono8", "jpeg", None, 80)).image
        images[k], ranges[k], masks[k], vel[k], stamps[k] = (
            img,
            f.range_m,
            f.mask,
            f.velocity,
            f.stamp_ns,
        )
        if (k + 1) % max(1, n // 4) == 0:
            log(f"  rendered {k + 1}/{n} frames of {case.label} ({time.monotonic() - t0:.0f} s)")
    has_mask = bool(sim.scenario.movers)
    return Frames(stamps, images, ranges, masks if has_mask else None, vel)


def _cache_key(sim: Simulation, effects: tuple[str, ...] = ()) -> str:
    o = sim.options
    src = Path(scenarios.__file__).parent
    digest = hashlib.sha1()
    for name in ("render.py", "scenarios.py", "sensors.py"):
        digest.update((src / name).read_bytes())
    parts = [
        sim.scenario.name,
        f"{o.width}x{o.height}",
        f"{o.seconds:g}s",
        f"{o.rate_hz:g}hz",
        f"seed{o.seed}",
        f"fov{o.hfov_deg:g}",
        f"n{o.noise_sigma:g}",
        f"ss{o.supersample}",
        f"sc{sim.scale:g}",
        digest.hexdigest()[:10],
        *effects,
    ]
    return "_".join(parts)


def sim_engine(sim: Simulation, **options: Any) -> OwlEngine:
    """An engine for a rendered simulation: its camera, extrinsic, IMU time offset and
    rolling-shutter readout (``options``: any further :class:`EngineOptions`), with the
    simulation's gyro added."""
    options.setdefault("rolling_shutter_readout_s", sim.options.rolling_shutter_readout_s)
    engine = OwlEngine(
        sim.options.camera(),
        EngineOptions(
            camera_to_imu_rotation_xyzw=sim.camera_to_imu_xyzw,
            imu_time_offset_s=sim.imu_time_offset_ns * 1e-9,
            **options,
        ),
    )
    engine.add_gyro(sim.gyro_samples())
    return engine


def load_frames(
    sim: Simulation,
    cache_dir: Path | None,
    log: Callable[[str], None] = lambda s: None,
    case: Case | None = None,
) -> Frames:
    """The simulation's frames, from ``cache_dir`` when cached there (else rendered, stored);
    with the image effects of ``case`` when it has any (:func:`effect_frames`)."""
    effects = case.effects if case is not None else ()
    path = cache_dir / f"{_cache_key(sim, effects)}.npz" if cache_dir is not None else None
    if path is not None and path.is_file():
        try:
            with np.load(path) as z:
                mask = z["mask"] if z["has_mask"] else None
                return Frames(
                    z["stamps"], z["images"], z["range"].astype(np.float32), mask, z["velocity"]
                )
        except (OSError, ValueError, KeyError):
            log(f"cache {path} unreadable: rendering again")
    if case is not None and case.effects:
        frames = effect_frames(case, sim, log)
        if path is not None:
            _store(path, frames)
        return frames
    n = sim.options.num_frames
    w, h = sim.options.width, sim.options.height
    images = np.zeros((n, h, w), dtype=np.uint8)
    ranges = np.zeros((n, h, w), dtype=np.float32)
    masks = np.zeros((n, h, w), dtype=bool)
    vel = np.zeros((n, 3))
    t0 = time.monotonic()
    for k, f in enumerate(sim.frames()):
        images[k], ranges[k], masks[k], vel[k] = f.image, f.range_m, f.mask, f.velocity
        if (k + 1) % max(1, n // 4) == 0:
            log(
                f"  rendered {k + 1}/{n} frames of {sim.scenario.name} "
                f"({time.monotonic() - t0:.0f} s)"
            )
    has_mask = bool(sim.scenario.movers)
    frames = Frames(sim.frame_stamps_ns.copy(), images, ranges, masks if has_mask else None, vel)
    if path is not None:
        _store(path, frames)
    return frames


def _store(path: Path, frames: Frames) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    # a name of this process's own: two processes rendering the same case (two benches, a
    # Ray batch) each write their file and the last rename wins, with identical contents
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.{threading.get_ident()}.tmp.npz")
    n, h, w = frames.images.shape
    np.savez(
        tmp,
        stamps=frames.stamps_ns,
        images=frames.images,
        range=frames.range_m.astype(np.float16),  # 5e-4 relative: far below the errors scored
        mask=frames.mask if frames.mask is not None else np.zeros((n, h, w), dtype=bool),
        has_mask=frames.mask is not None,
        velocity=frames.velocity,
    )
    tmp.replace(path)


# ------------------------------------------------------------------------ one case


def owl_estimate(res: FrameResult) -> Estimate:
    """What owl_eval scores of an engine FrameResult."""
    return Estimate(
        res.stamp_ns, res.heading, res.pixels, res.range_over_speed, res.flags, res.gyro_bias
    )


def baseline_estimate(res: BaselineFrame) -> Estimate:
    """What owl_eval scores of a baseline frame (no bias estimate)."""
    return Estimate(res.stamp_ns, res.heading, res.pixels, res.range_over_speed, res.flags)


@dataclass(frozen=True)
class Source:
    """What one case feeds the estimators: camera, extrinsic, gyro and frames with truth.

    Attributes:
        camera: the camera model.
        camera_to_imu_xyzw: rotation camera -> IMU frame, quaternion (x, y, z, w).
        imu_time_offset_s: IMU stamp minus camera stamp, s.
        gyro: every gyro sample (IMU frame, IMU clock).
        truth_bias: (3,) true gyro bias, IMU frame, rad/s, or None (unknown).
        has_mask: the truth has a moving-object mask.
        frames: callable returning an iterator of (stamp_ns, (H, W) uint8 image, Truth).
        num_frames: frames the iterator yields.
        readout_s: rolling-shutter readout of the images, s (0: global shutter).
    """

    camera: CameraModel
    camera_to_imu_xyzw: tuple[float, float, float, float]
    imu_time_offset_s: float
    gyro: GyroSamples
    truth_bias: npt.NDArray[np.float64] | None
    has_mask: bool
    frames: Callable[[], Iterator[tuple[int, npt.NDArray[np.uint8], Truth]]]
    num_frames: int
    readout_s: float = 0.0


def sim_source(case: Case, frames: Frames, sim: Simulation) -> Source:
    """A synthetic case's :class:`Source` (rendered frames, the simulation's IMU)."""
    b = case.bias / math.sqrt(3.0)

    def it() -> Iterator[tuple[int, npt.NDArray[np.uint8], Truth]]:
        for k in range(frames.stamps_ns.size):
            yield int(frames.stamps_ns[k]), frames.images[k], frames.truth(k)

    return Source(
        sim.camera,
        sim.camera_to_imu_xyzw,
        sim.imu_time_offset_ns * 1e-9,
        sim.gyro_samples(),
        np.array([b, b, b]),
        frames.mask is not None,
        it,
        int(frames.stamps_ns.size),
        sim.options.rolling_shutter_readout_s,
    )


@dataclass
class CaseRun:
    """Everything measured on one case."""

    case: Case
    frames: int
    scores: dict[str, list[FrameScore]] = field(default_factory=dict)
    owl_stage_s: dict[str, float] = field(default_factory=dict)
    estimate_s: dict[str, float] = field(default_factory=dict)
    track_s: float = 0.0
    tracks_per_frame: float = 0.0
    owl_results: list[FrameResult] = field(default_factory=list)
    baseline_results: dict[str, list[BaselineFrame]] = field(default_factory=dict)
    has_mask: bool = False
    #: per baseline: (OWL's, the baseline's) relative r/|t| errors on the tracks both
    #: gave a range for (:func:`owl_ros.tools.evaluate.paired_range_errors`)
    paired: dict[str, tuple[list[npt.NDArray[np.float64]], list[npt.NDArray[np.float64]]]] = field(
        default_factory=dict
    )
    #: per baseline: (OWL's, the baseline's) heading errors, deg, on the frames where both
    #: gave a heading (a common set of frames for the two medians)
    heading_pairs: dict[str, tuple[list[float], list[float]]] = field(default_factory=dict)


def case_gaps(rate_hz: float, history: int) -> tuple[int, ...]:
    """The frame gaps the baselines run at for a camera at ``rate_hz``: :data:`GAPS`, and
    for a camera faster than :data:`GAPS_RATE_HZ` also the gap spanning the time of the
    longest one there, capped at ``history - 1`` (the oldest position a track keeps)."""
    longest = min(round(max(GAPS) * rate_hz / GAPS_RATE_HZ), history - 1)
    return tuple(sorted({*GAPS, longest})) if rate_hz > GAPS_RATE_HZ else GAPS


def run_case(
    case: Case,
    profile: Profile,
    frames: Frames,
    sim: Simulation,
    keep_results: bool = False,
) -> CaseRun:
    """Run OWL and every baseline (each gap) over a synthetic case's frames, same tracks."""
    return run_source(case, profile, sim_source(case, frames, sim), keep_results)


def _source_engine(src: Source, profile: Profile, readout_s: float) -> OwlEngine:
    """OWL for a source: its extrinsic, offset and gyro, the profile's features."""
    engine = OwlEngine(
        src.camera,
        replace(
            params.build_options(dict(profile.engine_params)).engine,  # the node's defaults
            camera_to_imu_rotation_xyzw=src.camera_to_imu_xyzw,
            imu_time_offset_s=src.imu_time_offset_s,
            max_features=profile.features,
            rolling_shutter_readout_s=readout_s,
        ),
    )
    engine.add_gyro(src.gyro)
    return engine


def run_source(case: Case, profile: Profile, src: Source, keep_results: bool = False) -> CaseRun:
    """Run OWL and both baselines at every gap of :func:`case_gaps` over ``src``, on the
    same tracks, and score them with the same owl_eval functions. Rolling-shutter images:
    OWL compensates the readout ("owl"), and runs once more ignoring it
    (:data:`UNCOMPENSATED`, on its own tracks)."""
    engine = _source_engine(src, profile, src.readout_s)
    clock = time.process_time if profile.clock == "cpu" else time.perf_counter
    engine.clock = clock
    uncompensated = _source_engine(src, profile, 0.0) if src.readout_s else None
    if uncompensated is not None:
        uncompensated.clock = clock
    gyro = engine.gyro

    known_bias = src.truth_bias

    def bias() -> npt.NDArray[np.float64]:
        return known_bias if known_bias is not None else engine.gyro_bias

    def rotation(t0: int, t1: int) -> npt.NDArray[np.float64] | None:
        # The gyro-aided baselines derotate, and every filtered one predicts, with the
        # true bias where the case knows it (a gyro calibrated exactly: the strongest
        # baseline; the raw gyro of a "+bias" case handicapped them, a filter turning a
        # constant rotation error into lag), else with the bias OWL has estimated by then.
        if not gyro.covers(t0, t1):
            return None
        return gyro.relative_rotation(t0, t1, bias())

    readout_ns = round(src.readout_s * 1e9)

    def row_rotations(frames: npt.NDArray[np.int64], stamp: int) -> ReadoutRotations | None:
        # A rolling shutter: the gyro-aided baselines derotate every point from its own
        # row's time, as OWL does (a rotation per frame left them degrees off on brisk+rs30).
        if not gyro.covers(int(frames.min()), max(int(frames.max()), stamp) + readout_ns):
            return None
        return readout_rotations(gyro, frames, stamp, readout_ns, bias())

    history = max(engine.options.tracker.history_len, engine.options.fit_frames)  # as OWL's
    gaps = case_gaps(case.rate_hz or profile.rate_hz, history)
    names, filtered_settings = _methods(gaps)
    baselines: dict[str, TwoViewBaseline] = {}
    for g in gaps:
        baselines[f"cv-5pt@{g}"] = TwoViewBaseline(
            src.camera, BaselineOptions(method="essential", gap_frames=g)
        )
        baselines[f"cv-gyro@{g}"] = TwoViewBaseline(
            src.camera,
            BaselineOptions(method="gyro", gap_frames=g),
            rotation,
            row_rotations if readout_ns > 0 else None,
        )
    filtered = {
        name: (raw, FilteredBaseline(math.radians(sigma), rotation))
        for name, raw, sigma in filtered_settings
    }
    for _, flt in filtered.values():
        flt.clock = clock
    methods = (*names, UNCOMPENSATED) if uncompensated is not None else names
    run = CaseRun(case, src.num_frames, {m: [] for m in methods})
    run.has_mask = src.has_mask
    run.estimate_s = dict.fromkeys(methods, 0.0)
    run.baseline_results = {m: [] for m in (*baselines, *filtered)}
    for base in baselines.values():
        base.clock = clock
    n_tracks = 0
    count = 0
    for stamp, image, truth in src.frames():
        count += 1
        res = engine.process(ImageFrame(stamp, image))
        for key, value in res.timings.items():
            run.owl_stage_s[key] = run.owl_stage_s.get(key, 0.0) + value
        track_s = res.timings.get("track", 0.0)
        run.track_s += track_s
        run.estimate_s["owl"] += res.timings.get("total", 0.0) - track_s
        owl_score = score_frame(owl_estimate(res), truth, src.truth_bias)
        run.scores["owl"].append(owl_score)
        if uncompensated is not None:
            plain = uncompensated.process(ImageFrame(stamp, image))
            run.estimate_s[UNCOMPENSATED] += plain.timings.get("total", 0.0)
            run.scores[UNCOMPENSATED].append(
                score_frame(owl_estimate(plain), truth, src.truth_bias)
            )
        tracks = engine.last_tracks  # the very tracks OWL used for this frame
        if tracks is not None:
            n_tracks += tracks.num_tracks
        outs: dict[str, BaselineFrame] = {}
        for name, base in baselines.items():
            if tracks is None:
                continue
            out = outs[name] = base.process(tracks)
            run.estimate_s[name] += out.timings["estimate"]
            run.scores[name].append(score_frame(baseline_estimate(out), truth))
            _pair_heading(run, name, owl_score, run.scores[name][-1])
            if truth.range_m is not None and truth.range_m.size:
                pair = paired_range_errors(
                    res.ids, res.pixels, res.range_over_speed, out.ids, out.range_over_speed, truth
                )
                mine, theirs = run.paired.setdefault(name, ([], []))
                mine.append(pair[0])
                theirs.append(pair[1])
            if keep_results:
                run.baseline_results[name].append(out)
        for name, (raw, flt) in filtered.items():
            if raw not in outs:
                continue
            fout = flt.step(outs[raw])  # the same points and ranges: not paired again
            run.estimate_s[name] += fout.timings["estimate"]
            run.scores[name].append(score_frame(baseline_estimate(fout), truth))
            _pair_heading(run, name, owl_score, run.scores[name][-1])
            if keep_results:
                run.baseline_results[name].append(fout)
        if keep_results:
            run.owl_results.append(res)
    run.frames = count
    run.tracks_per_frame = n_tracks / max(run.frames, 1)
    return run


def _pair_heading(run: CaseRun, method: str, owl: FrameScore, other: FrameScore) -> None:
    """Keep OWL's and ``method``'s heading errors of one frame when both have one."""
    if math.isfinite(owl.heading_deg) and math.isfinite(other.heading_deg):
        mine, theirs = run.heading_pairs.setdefault(method, ([], []))
        mine.append(owl.heading_deg)
        theirs.append(other.heading_deg)


def merge_runs(runs: Sequence[CaseRun]) -> CaseRun:
    """One case's runs over several render seeds as one run: its frame scores, r/|t| pairs
    and times over the frames of all of them (one seed: the run itself)."""
    if len(runs) == 1:
        return runs[0]
    first = runs[0]
    out = CaseRun(first.case, sum(r.frames for r in runs), {m: [] for m in first.scores})
    out.has_mask = first.has_mask
    out.estimate_s = dict.fromkeys(first.estimate_s, 0.0)
    for r in runs:
        for m, scores in r.scores.items():
            out.scores[m].extend(scores)
        for k, v in r.owl_stage_s.items():
            out.owl_stage_s[k] = out.owl_stage_s.get(k, 0.0) + v
        for m, v in r.estimate_s.items():
            out.estimate_s[m] += v
        out.track_s += r.track_s
        for m, (mine, theirs) in r.paired.items():
            both = out.paired.setdefault(m, ([], []))
            both[0].extend(mine)
            both[1].extend(theirs)
        for m, (h_mine, h_theirs) in r.heading_pairs.items():
            h_both = out.heading_pairs.setdefault(m, ([], []))
            h_both[0].extend(h_mine)
            h_both[1].extend(h_theirs)
    out.tracks_per_frame = sum(r.tracks_per_frame * r.frames for r in runs) / max(out.frames, 1)
    return out


def _seed_row(run: CaseRun) -> dict[str, Any]:
    """OWL's and the best baseline's heading and r/|t| figures of one seed's run."""
    rep = case_report(run)
    keys = ("heading_deg_median", "heading_deg_p90", "range_rel_median", "range_rel_p90")
    best = rep["best"]["heading"]
    return {
        "owl": {k: rep["methods"]["owl"].get(k) for k in keys},
        "best_baseline": best,
        best: {k: rep["methods"][best].get(k) for k in keys},
        "owl_heading_ok": rep["best"]["owl_heading_ok"],
    }


# ------------------------------------------------------------------------ reporting


def _paired_row(run: CaseRun, method: str) -> dict[str, Any] | None:
    """r/|t| of OWL and of baseline ``method`` on the tracks both gave a range for:
    {"points", "owl_median", "owl_p90", "median", "p90"} (relative errors), or None."""
    if method not in run.paired:
        return None
    mine = np.concatenate(run.paired[method][0]) if run.paired[method][0] else np.zeros(0)
    theirs = np.concatenate(run.paired[method][1]) if run.paired[method][1] else np.zeros(0)
    return _paired_stats("points", mine, theirs)


def _paired_stats(count: str, mine: npt.ArrayLike, theirs: npt.ArrayLike) -> dict[str, Any] | None:
    """Median and p90 of OWL's and a baseline's paired errors, with their number under
    ``count``; None when there are none."""
    a, b = np.asarray(mine, dtype=np.float64), np.asarray(theirs, dtype=np.float64)
    if a.size == 0:
        return None
    return {
        count: int(a.size),
        "owl_median": float(np.median(a)),
        "owl_p90": float(np.percentile(a, 90)),
        "median": float(np.median(b)),
        "p90": float(np.percentile(b, 90)),
    }


def _heading_paired_row(run: CaseRun, method: str) -> dict[str, Any] | None:
    """Heading errors of OWL and of baseline ``method`` on the frames both gave a heading
    for: {"frames", "owl_median", "owl_p90", "median", "p90"} (deg), or None."""
    mine, theirs = run.heading_pairs.get(method, ([], []))
    return _paired_stats("frames", mine, theirs)


def _method_row(run: CaseRun, method: str) -> dict[str, Any]:
    s = summarize(run.scores[method], run.has_mask)
    if method != "owl":
        s["range_paired"] = _paired_row(run, method)
        s["heading_paired"] = _heading_paired_row(run, method)
    total = run.track_s + run.estimate_s[method]
    s["fps"] = run.frames / total if total > 0 else None
    s["estimate_ms_per_frame"] = 1e3 * run.estimate_s[method] / max(run.frames, 1)
    return s


def _inf(x: Any) -> float:
    return math.inf if x is None else float(x)


def _rank(row: dict[str, Any]) -> tuple[float, ...]:
    """Sort key of a method's row: heading median, then p90; with no translating frame,
    fewer false headings first."""
    if not row["translating_frames"]:
        return (float(row["false_heading_frames"]), 0.0)
    missing = 1.0 - _inf(row["heading_availability"]) if row["heading_availability"] else 1.0
    return (_inf(row["heading_deg_median"]), _inf(row["heading_deg_p90"]), missing)


def best_baselines(methods: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The best baseline per family and overall (by heading median, then p90), and whether
    OWL's figures are at or below the lowest any baseline/gap reaches.

    Keys: "cv-5pt", "cv-gyro" (best gap's method name of each family), "heading" (best
    method overall), "range" (lowest r/|t| median over each method's own points),
    "range_paired" (the baseline with the lowest r/|t| p90 on the tracks OWL and it both
    gave a range for), "owl_heading_ok" (OWL heading median and p90 <= the lowest median
    and p90 over every baseline and gap; None without a translating frame),
    "owl_range_ok" (on the tracks both gave a range for, OWL's r/|t| median and p90 <=
    the baseline's, for every baseline and gap; None when nothing is scored),
    "owl_heading_paired_ok" (the same for the heading on the frames OWL and the baseline
    both gave one for: each median over one set of frames; None when no frame is shared),
    "owl_heading_paired_ok_filtered" (the same against the filtered baselines only).
    """
    base = [m for m in methods if not m.startswith("owl")]
    out: dict[str, Any] = {}
    for fam in BASELINES:
        members = [m for m in base if m.startswith(fam + "@")]
        out[fam] = min(members, key=lambda m: _rank(methods[m]))
    out["heading"] = min(base, key=lambda m: _rank(methods[m]))
    out["range"] = min(base, key=lambda m: _inf(methods[m]["range_rel_median"]))
    owl = methods["owl"]
    if owl["translating_frames"]:
        lows = [
            min(_inf(methods[m][k]) for m in base)
            for k in ("heading_deg_median", "heading_deg_p90")
        ]
        out["owl_heading_ok"] = bool(
            _inf(owl["heading_deg_median"]) <= lows[0] and _inf(owl["heading_deg_p90"]) <= lows[1]
        )
    else:
        out["owl_heading_ok"] = bool(
            owl["false_heading_frames"] <= min(methods[m]["false_heading_frames"] for m in base)
        )
    # the heading on the same frames: against each baseline, where both gave one
    hp = {m: methods[m].get("heading_paired") for m in base}
    hp = {m: p for m, p in hp.items() if p}
    for key, members in (
        ("owl_heading_paired_ok", list(hp)),
        ("owl_heading_paired_ok_filtered", [m for m in hp if "+kf" in m]),
    ):
        out[key] = (
            all(
                hp[m]["owl_median"] <= hp[m]["median"] and hp[m]["owl_p90"] <= hp[m]["p90"]
                for m in members
            )
            if members
            else None
        )
    # r/|t| on the same tracks: against each baseline, on the points both gave a range for
    pairs = {m: methods[m].get("range_paired") for m in base}
    pairs = {m: p for m, p in pairs.items() if p}
    if not pairs:
        out["owl_range_ok"] = None
    else:
        out["range_paired"] = min(pairs, key=lambda m: (pairs[m]["p90"], pairs[m]["median"]))
        out["owl_range_ok"] = all(
            p["owl_median"] <= p["median"] and p["owl_p90"] <= p["p90"] for p in pairs.values()
        )
    return out


def case_report(run: CaseRun) -> dict[str, Any]:
    """JSON-ready row of one case: every method (OWL, each baseline at each gap) and the
    best baselines (:func:`best_baselines`)."""
    stages = {k: 1e3 * v / max(run.frames, 1) for k, v in run.owl_stage_s.items()}
    methods = {m: _method_row(run, m) for m in run.scores}
    gaps = sorted({int(m.split("@")[1]) for m in methods if m.startswith("cv-") and "+" not in m})
    return {
        "case": run.case.label,
        "scenario": run.case.scenario,
        "gaps": gaps,
        "gyro_bias_rad_s": run.case.bias,
        "frames": run.frames,
        "tracks_per_frame": run.tracks_per_frame,
        "owl_stage_ms_per_frame": stages,
        "methods": methods,
        "best": best_baselines(methods),
    }


def _pooled(
    runs: Sequence[CaseRun],
    method: str | Callable[[CaseRun], str],
    biased: bool,
    only: set[str] | None = None,
) -> dict[str, Any]:
    scores = [
        s
        for r in runs
        if not (r.case.bag or r.case.rate_hz or r.case.imu or r.case.effects)
        and r.case.scenario in STATIC
        and bool(r.case.bias) == biased
        and (only is None or r.case.scenario in only)
        for s in r.scores[method if isinstance(method, str) else method(r)]
    ]
    return summarize(scores, False) if scores else {}


def _ratio(a: Any, b: Any) -> float | None:
    return float(a) / float(b) if a is not None and b not in (None, 0) else None


def run_bench(
    profile: Profile,
    cache_dir: Path | None,
    log: Callable[[str], None] = lambda s: None,
) -> dict[str, Any]:
    """Run every case of ``profile``; returns the JSON object.

    Keys: profile, image_size ("WxH"), features (requested), features_per_frame (tracks
    per frame, mean over cases), owl_fps, baseline_fps (cv-5pt at gap 1),
    baseline_gyro_fps (cv-gyro at gap 1), estimation_speedup (that cv-5pt estimation time /
    OWL estimation time, tracking excluded), estimation_speedup_gyro,
    estimate_ms_per_frame (every method), owl_/baseline_/baseline_gyro_/baseline_best_
    heading_deg_median/p90 and range_rel_median/p90 pooled over the static scenarios
    without bias (baseline = cv-5pt at each case's best gap, baseline_gyro = cv-gyro at
    its best gap, baseline_best = each case's best baseline), the same with suffix
    ``_bias`` for the biased rows and ``_nobias_matched`` for the unbiased rows of the same
    scenarios, pooled (every method, each pool), owl_points_per_frame, frames_held_mb,
    owl_stage_ms_per_frame, heading_ratio and range_ratio (OWL / baseline_best medians),
    peak_rss_mb, machine, cases (per-case rows: stage times, per method every owl_eval
    summary key + fps, and "best").
    """
    cv2.setNumThreads(1)
    runs: list[CaseRun] = []
    images: dict[str, Frames] = {}
    frames_mb = 0.0
    t_start = time.monotonic()
    per_seed: list[dict[str, Any] | None] = []
    for i, case in enumerate(profile.cases, start=1):
        seeds = (0,) if case.bag else profile.seeds
        seed_runs = []
        for seed in seeds:
            tag = f" seed {seed}" if len(seeds) > 1 else ""
            log(f"[{i}/{len(profile.cases)}] {case.label}{tag}: frames")
            if case.bag:
                src = bag_source(case.bag)
            else:
                sim = _sim(case, profile, seed)
                key = _cache_key(sim, case.effects)
                if key not in images:
                    images = {key: load_frames(sim, cache_dir, log, case)}
                frames = images[key]
                held = frames.images.nbytes + frames.range_m.nbytes + frames.velocity.nbytes
                held += frames.mask.nbytes if frames.mask is not None else 0
                frames_mb = max(frames_mb, held / 2**20)
                src = sim_source(case, frames, sim)
            log(
                f"[{i}/{len(profile.cases)}] {case.label}{tag}: OWL + baselines on "
                f"{src.num_frames} frames ({time.monotonic() - t_start:.0f} s elapsed)"
            )
            seed_runs.append(run_source(case, profile, src))
        runs.append(merge_runs(seed_runs))
        per_seed.append(
            {str(sd): _seed_row(r) for sd, r in zip(seeds, seed_runs, strict=True)}
            if len(seed_runs) > 1
            else None
        )
    reports = [case_report(r) for r in runs]
    for rep_row, seeds_rep in zip(reports, per_seed, strict=True):
        if seeds_rep is not None:
            rep_row["per_seed"] = seeds_rep
    best_of = {id(r): rep["best"] for r, rep in zip(runs, reports, strict=True)}
    total_frames = max(sum(r.frames for r in runs), 1)
    track = sum(r.track_s for r in runs)
    est = {m: sum(r.estimate_s[m] for r in runs) for m in METHODS}
    stages: dict[str, float] = {}
    for r in runs:
        for k, v in r.owl_stage_s.items():
            stages[k] = stages.get(k, 0.0) + v

    def _div(a: float, b: float) -> float | None:
        return a / b if b > 0 else None

    out: dict[str, Any] = {
        "profile": profile.name,
        "image_size": f"{profile.width}x{profile.height}",
        "features": profile.features,
        "seconds_per_case": profile.seconds,
        "seeds": list(profile.seeds),
        "engine_params": dict(profile.engine_params),
        "gaps": list(GAPS),
        "clock": profile.clock,
        "features_per_frame": float(np.mean([r.tracks_per_frame for r in runs])),
        "owl_fps": _div(total_frames, track + est["owl"]),
        "baseline_fps": _div(total_frames, track + est["cv-5pt@1"]),
        "baseline_gyro_fps": _div(total_frames, track + est["cv-gyro@1"]),
        "estimation_speedup": _div(est["cv-5pt@1"], est["owl"]),
        "estimation_speedup_gyro": _div(est["cv-gyro@1"], est["owl"]),
        "owl_stage_ms_per_frame": {k: 1e3 * v / total_frames for k, v in stages.items()},
        "estimate_ms_per_frame": {m: 1e3 * est[m] / total_frames for m in METHODS},
        "baseline_estimate_ms_per_frame": 1e3 * est["cv-5pt@1"] / total_frames,
        "baseline_gyro_estimate_ms_per_frame": 1e3 * est["cv-gyro@1"] / total_frames,
    }
    pickers: dict[str, str | Callable[[CaseRun], str]] = {
        "owl": "owl",
        "baseline": lambda r: str(best_of[id(r)]["cv-5pt"]),
        "baseline_gyro": lambda r: str(best_of[id(r)]["cv-gyro"]),
        "baseline_best": lambda r: str(best_of[id(r)]["heading"]),
    }
    with_bias = {r.case.scenario for r in runs if r.case.bias}
    pools = ((False, "", None), (False, "_nobias_matched", with_bias), (True, "_bias", None))
    keys = ("heading_deg_median", "heading_deg_p90", "range_rel_median", "range_rel_p90")
    pooled_all: dict[str, dict[str, Any]] = {}
    for biased, suffix, only in pools:
        for prefix, pick in pickers.items():
            pooled = _pooled(runs, pick, biased, only)
            for key in keys:
                out[f"{prefix}_{key}{suffix}"] = pooled.get(key)
        pool_name = suffix.lstrip("_") or "nobias"
        pooled_all[pool_name] = {}
        for m in METHODS:
            pooled = _pooled(runs, m, biased, only)
            pooled_all[pool_name][m] = {k: pooled.get(k) for k in keys}
    out["pooled"] = pooled_all
    owl_pooled = _pooled(runs, "owl", False)
    out["owl_points_per_frame"] = owl_pooled.get("points_per_frame")
    out["heading_ratio"] = _ratio(
        out["owl_heading_deg_median"], out["baseline_best_heading_deg_median"]
    )
    out["range_ratio"] = _ratio(out["owl_range_rel_median"], out["baseline_best_range_rel_median"])
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    out["frames_held_mb"] = frames_mb
    out["machine"] = {
        "cpu": _cpu_name(),
        "cores": os.cpu_count(),
        "threads_used": 1,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
    }
    out["wall_s"] = time.monotonic() - t_start
    out["cases"] = reports
    return out


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _stages_text(ms: dict[str, float]) -> str:
    """ "track 8.9 (LK 7.1, detect 1.4), integrate 2.2, ..." from per-stage milliseconds."""
    parts = []
    if "track" in ms:
        sub = [
            f"{label} {ms[k]:.1f}" for k, label in (("lk", "LK"), ("detect", "detect")) if k in ms
        ]
        parts.append(f"track {ms['track']:.1f}" + (f" ({', '.join(sub)})" if sub else ""))
    parts += [f"{k} {ms[k]:.1f}" for k in ("integrate", "heading", "looming", "total") if k in ms]
    return ", ".join(parts)


def _f(x: Any, fmt: str = ".2f", scale: float = 1.0) -> str:
    return "n/a" if x is None else format(x * scale, fmt)


def _head(s: dict[str, Any]) -> str:
    if s["translating_frames"] == 0:
        return f"{s['false_heading_frames']} false"
    return f"{_f(s['heading_deg_median'])}/{_f(s['heading_deg_p90'])}"


def _seeds_text(doc: dict[str, Any]) -> str:
    seeds = doc.get("seeds", [0])
    if len(seeds) <= 1:
        return ""
    return f" x {len(seeds)} render seeds (figures over the frames of all)"


def _yes(x: Any) -> str:
    return "-" if x is None else ("yes" if x else "NO")


def report_lines(doc: dict[str, Any]) -> list[str]:
    """The benchmark as text tables."""
    lines = [
        f"{PROG} ({doc['profile']}): {doc['image_size']}, {doc['features']} features requested"
        + "".join(f", {k}={v}" for k, v in doc.get("engine_params", {}).items())
        + " "
        f"({doc['features_per_frame']:.0f} tracked/frame), {doc['seconds_per_case']:g} s per "
        f"synthetic case{_seeds_text(doc)}, baselines at frame gaps "
        f"{', '.join(map(str, doc['gaps']))}, one "
        f"thread, {doc['machine']['cpu']}, "
        f"{'CPU' if doc.get('clock', 'wall') == 'cpu' else 'wall'} time",
        "",
        "per case and method (heading error deg median/p90, heading availability on "
        "translating frames, r/|t| relative error median/p90, points/frame, moving P/R):",
    ]
    for c in doc["cases"]:
        best = c["best"]
        lines.append(
            f"  {c['case']} ({c['frames']} frames; best baseline: {best['heading']}, best "
            f"r/|t|: {best['range']}; OWL <= every baseline: heading "
            f"{_yes(best['owl_heading_ok'])}, on the frames both gave one "
            f"{_yes(best.get('owl_heading_paired_ok'))}, r/|t| {_yes(best['owl_range_ok'])})"
        )
        for name, s in c["methods"].items():
            mark = "*" if name in (best["heading"], best["range"]) else " "
            pr = (
                f"{_f(s['moving_precision'], '.0%')}/{_f(s['moving_recall'], '.0%')}"
                if s["moving_precision"] is not None or s["moving_recall"] is not None
                else "-"
            )
            lines.append(
                f"   {mark}{name:<10} {_head(s):>11} {_f(s['heading_availability'], '.0%'):>5} "
                f"{_f(s['range_rel_median'], '.1%'):>7}/{_f(s['range_rel_p90'], '.1%'):<7} "
                f"{_f(s['points_per_frame'], '.0f'):>5} {pr:>9}"
            )
    lines += [
        "",
        "summary per case (OWL against the best baseline at its best gap; r/|t| on the "
        "tracks both gave a range for, against the baseline with the lowest p90 there):",
        f"  {'case':<22} {'OWL head':>11} {'best head':>11} {'best':<10} {'OWL r/|t|':>12} "
        f"{'base r/|t|':>12} {'base':<10} {'head ok':>7} {'r ok':>5}",
    ]
    for c in doc["cases"]:
        m, best = c["methods"], c["best"]
        o, b = m["owl"], m[best["heading"]]
        p = m[best["range_paired"]]["range_paired"] if best.get("range_paired") else None
        own = f"{_f(p and p['owl_median'], '.1%'):>5}/{_f(p and p['owl_p90'], '.1%'):<6}"
        theirs = f"{_f(p and p['median'], '.1%'):>5}/{_f(p and p['p90'], '.1%'):<6}"
        lines.append(
            f"  {c['case']:<22} {_head(o):>11} {_head(b):>11} {best['heading']:<10} "
            f"{own} {theirs} {best.get('range_paired') or '-':<10} "
            f"{_yes(best['owl_heading_ok']):>7} {_yes(best['owl_range_ok']):>5}"
        )
    stage_ms = doc["owl_stage_ms_per_frame"]
    owl_est = stage_ms.get("total", 0.0) - stage_ms.get("track", 0.0)
    est = doc["estimate_ms_per_frame"]
    lines += [
        "",
        "time per frame (ms; tracking shared by all methods):",
        "  OWL stages: " + _stages_text(stage_ms),
        f"  estimation: OWL {owl_est:.1f}, "
        + ", ".join(f"{m} {v:.1f}" for m, v in est.items() if m != "owl"),
        f"  frames/s (tracking + estimation): OWL {_f(doc['owl_fps'], '.1f')}, cv-5pt@1 "
        f"{_f(doc['baseline_fps'], '.1f')}, cv-gyro@1 {_f(doc['baseline_gyro_fps'], '.1f')}",
        f"  estimation speedup (baseline / OWL): cv-5pt@1 "
        f"{_f(doc['estimation_speedup'])}x, cv-gyro@1 {_f(doc['estimation_speedup_gyro'])}x",
        "",
        "pooled over the static synthetic scenarios (heading deg median/p90, r/|t| "
        "median/p90; 'same' = the scenarios that also have a bias row; a baseline family at "
        "each case's best gap, 'best' = each case's best baseline):",
    ]
    rows = (
        ("no bias, all", ""),
        ("no bias, same", "_nobias_matched"),
        (f"bias {BIAS:g} rad/s", "_bias"),
    )
    names = (
        ("OWL", "owl"),
        ("cv-5pt", "baseline"),
        ("cv-gyro", "baseline_gyro"),
        ("best", "baseline_best"),
    )
    for label, suffix in rows:
        for name, prefix in names:
            h50 = doc.get(f"{prefix}_heading_deg_median{suffix}")
            if h50 is None and doc.get(f"{prefix}_range_rel_median{suffix}") is None:
                continue
            h90 = doc.get(f"{prefix}_heading_deg_p90{suffix}")
            r50 = doc.get(f"{prefix}_range_rel_median{suffix}")
            r90 = doc.get(f"{prefix}_range_rel_p90{suffix}")
            lines.append(
                f"  {label:<18} {name:<8} {_f(h50)}/{_f(h90)} deg, "
                f"{_f(r50, '.1%')}/{_f(r90, '.1%')}"
            )
    lines += [
        f"  ratios OWL / best baseline: heading {_f(doc['heading_ratio'])}, r/|t| "
        f"{_f(doc['range_ratio'])}",
        "",
        f"peak memory (max RSS, rendering included): {doc['peak_rss_mb']:.0f} MB, of which "
        f"{doc.get('frames_held_mb', 0):.0f} MB are one scenario's frames and truth held in "
        "memory; "
        f"wall time {doc['wall_s']:.0f} s",
    ]
    return lines


# ------------------------------------------------------------------------ real bags

#: Topics of the standard bag layout (owl_make_bag, owl_import).
BAG_TOPICS = {
    "camera_info" if role == "info" else role: layout.TOPICS[role][0]
    for role in ("image", "info", "imu", "tf", "twist", "range", "mask")
}


def bag_source(path: str | Path) -> Source:
    """A recorded or imported bag in the standard layout as a :class:`Source`.

    Reads camera_info, the IMU, /tf_static (camera -> IMU rotation, as ``owl_process``
    takes it) and /ground_truth/twist in one pass; the images (sensor_msgs/Image or
    CompressedImage) stream in a second pass, paired with the twist by header stamp.
    /ground_truth/range and /ground_truth/moving_mask are used when present; without a
    range, r/|t| is not scored ("n/a"). Frames without a twist are skipped. The true gyro
    bias is taken from ``owl_make_bag``'s metadata when present (else not scored).

    Raises:
        BagError: not a bag, or a required topic missing.
    """
    from rclpy.serialization import deserialize_message

    from msg_adapters.camera_info import camera_info_to_model
    from msg_adapters.image import compressed_to_frame, image_to_array, image_to_frame
    from msg_adapters.imu import imus_to_gyro
    from msg_adapters.msgtypes import message_class
    from msg_adapters.stamps import header_to_ns
    from owl_ros.process import tf_rotation
    from owl_ros.tools.evaluate import truth_info

    with BagReader(path) as bag:
        topics = bag.topics
        have = ", ".join(sorted(topics)) or "no topics"
        for role in ("image", "camera_info", "imu", "twist"):
            if BAG_TOPICS[role] not in topics:
                raise BagError(f"bag {path} has no {BAG_TOPICS[role]} (has: {have})")

        def decode(raw: RawMessage) -> Any:
            return deserialize_message(raw.data, message_class(raw.msgtype))

        small = [BAG_TOPICS[k] for k in ("camera_info", "imu", "twist")]
        if BAG_TOPICS["tf"] in topics:
            small.append(BAG_TOPICS["tf"])
        info = None
        imus: list[Any] = []
        twists: dict[int, npt.NDArray[np.float64]] = {}
        transforms: list[Any] = []
        for raw in bag.messages(small):
            if raw.topic == BAG_TOPICS["tf"]:
                transforms.extend(bag.deserialize(raw).transforms)
                continue
            msg = decode(raw)
            if raw.topic == BAG_TOPICS["camera_info"]:
                info = info or msg
            elif raw.topic == BAG_TOPICS["imu"]:
                imus.append(msg)
            else:
                lin = msg.twist.linear
                twists[header_to_ns(msg.header)] = np.array([lin.x, lin.y, lin.z])
        if info is None or not imus:
            raise BagError(f"bag {path}: no camera_info or no IMU message")
        camera = camera_info_to_model(info)
        imu_frame = imus[0].header.frame_id
        rot = tf_rotation(transforms, imu_frame, info.header.frame_id) or (0.0, 0.0, 0.0, 1.0)
        gyro = imus_to_gyro(imus)
        del imus
        count = topics[BAG_TOPICS["image"]].count
        has_range = BAG_TOPICS["range"] in topics
        has_mask = BAG_TOPICS["mask"] in topics
    meta = truth_info(path)
    truth_bias = np.asarray(meta["gyro_bias"], dtype=np.float64) if "gyro_bias" in meta else None
    shape = (camera.height, camera.width)
    no_range = np.full(shape, np.nan, dtype=np.float32)

    def frames() -> Iterator[tuple[int, npt.NDArray[np.uint8], Truth]]:
        read = [BAG_TOPICS["image"]]
        read += [BAG_TOPICS[k] for k, ok in (("range", has_range), ("mask", has_mask)) if ok]
        pending: dict[int, dict[str, Any]] = {}
        need = 1 + int(has_range) + int(has_mask)
        with BagReader(path) as bag:
            for raw in bag.messages(read):
                msg = decode(raw)
                stamp = header_to_ns(msg.header)
                slot = pending.setdefault(stamp, {})
                if raw.topic == BAG_TOPICS["range"]:
                    slot["range"] = image_to_array(msg).astype(np.float32)
                elif raw.topic == BAG_TOPICS["mask"]:
                    slot["mask"] = image_to_array(msg) > 0
                elif raw.msgtype.endswith("CompressedImage"):
                    slot["image"] = compressed_to_frame(msg).image
                else:
                    slot["image"] = image_to_frame(msg).image
                if len(slot) < need:
                    continue
                del pending[stamp]
                for old in [s for s in pending if s < stamp - 1_000_000_000]:
                    del pending[old]  # an image whose truth never came
                if stamp not in twists:
                    continue
                truth = Truth(stamp, twists[stamp], slot.get("range", no_range), slot.get("mask"))
                yield stamp, np.asarray(slot["image"], dtype=np.uint8), truth

    n = sum(1 for s in twists)  # frames with truth (upper bound of those yielded)
    return Source(camera, rot, 0.0, gyro, truth_bias, has_mask, frames, min(n, count))


# ------------------------------------------------------------------------ CLI


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    p = OneLineErrorParser(
        prog=PROG,
        description="Benchmark OWL against the OpenCV two-view baseline (5-point essential "
        "matrix, and a gyro-aided variant) on the standard synthetic scenarios: per-stage "
        "times, frames/s, peak memory and accuracy, on the same frames and tracks.",
    )
    p.add_argument("--quick", action="store_true", help="small, short cases (< 1 minute)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument(
        "--cases",
        default=None,
        help="comma-separated cases to run, e.g. street,street+bias (default: the profile's)",
    )
    p.add_argument(
        "--bag",
        action="append",
        default=[],
        metavar="BAG",
        help="a recorded or imported bag in the standard layout with /ground_truth/twist "
        "(repeatable); only the bags run unless --cases is given too",
    )
    p.add_argument("--seconds", type=float, default=None, help="override seconds per case")
    p.add_argument(
        "--features", type=int, default=None, help="override features requested per frame"
    )
    p.add_argument(
        "--clock",
        choices=("cpu", "wall"),
        default="cpu",
        help="stage timers: the process's CPU time (default; independent of other load) "
        "or wall time",
    )
    p.add_argument(
        "--cache-dir",
        default=None,
        help="rendered-frame cache (default $XDG_CACHE_HOME/owl_ros/frames, else "
        "~/.cache/owl_ros/frames; said on stderr)",
    )
    p.add_argument(
        "--seeds",
        type=int,
        default=1,
        help="render each synthetic case with this many noise seeds (0, 1, ...; image and "
        "IMU noise) and score every method over the frames of all of them: one seed's "
        "heading medians move by 5 to 40 %% from seed to seed (default 1)",
    )
    p.add_argument(
        "-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
        help="an engine setting of owl_node (e.g. tracker_lk_deformation_correction:=false) "
        "that OWL runs with; the tracks, and so the baselines, follow it; repeatable",
    )  # fmt: skip
    p.add_argument("--no-cache", action="store_true", help="render without reading/writing")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return p


def parse_case(item: str) -> Case:
    """A case from its label: ``NAME[@RATEhz][+IMU][+EFFECT]...[+bias]``, e.g.
    ``car@10hz+mems200+blur+jpeg`` (IMU one of :data:`bags.sim.sensors.IMU_MODELS`, effects of
    :data:`EFFECTS`; ``car`` runs :data:`CAR_SECONDS`)."""
    head, *extras = item.strip().split("+")
    name, _, rate_text = head.partition("@")
    scenarios.get(name)  # ScenarioError names the known ones
    rate = 0.0
    if rate_text:
        try:
            rate = float(rate_text.lower().removesuffix("hz"))
        except ValueError:
            rate = -1.0
        if not (math.isfinite(rate) and rate > 0):
            raise BenchError(f"case {item!r}: the rate must be like @10hz, got {rate_text!r}")
    imu = ""
    effects: list[str] = []
    bias = 0.0
    for x in extras:
        if x == "bias":
            bias = BIAS
        elif x in IMU_MODELS and not imu:
            imu = x
        elif x in EFFECTS and x not in effects:
            effects.append(x)
        else:
            known = ", ".join(("bias", *IMU_MODELS, *EFFECTS))
            raise BenchError(f"case {item!r}: unknown suffix {x!r} (known: {known})")
    seconds = CAR_SECONDS if name == "car" else 0.0
    return Case(name, bias, "", rate, seconds, imu, tuple(effects))


def _parse_cases(text: str) -> tuple[Case, ...]:
    return tuple(parse_case(item) for item in text.split(","))


def chosen_profile(
    profile: Profile,
    cases: str | None,
    bags: Sequence[str],
    seconds: float | None,
    seeds: int,
    features: int | None,
) -> Profile:
    """``profile`` with the command line's choices (``--cases`` labels joined by commas,
    ``--bag`` paths, ``--seconds``, ``--seeds``, ``--features``; None: the profile's);
    BenchError naming the option otherwise."""
    chosen = _parse_cases(cases) if cases else ()
    for bag in bags:
        if not Path(bag).exists():
            raise BenchError(f"--bag {bag}: no such file or directory")
    chosen += tuple(Case("bag", 0.0, str(b)) for b in bags)
    if chosen:
        profile = replace(profile, cases=chosen)
    if seconds is not None:
        if not (math.isfinite(seconds) and seconds > 0):
            raise BenchError(f"--seconds must be positive, got {seconds}")
        profile = replace(profile, seconds=seconds)
    if seeds < 1:
        raise BenchError(f"--seeds must be >= 1, got {seeds}")
    profile = replace(profile, seeds=tuple(range(seeds)))
    if features is not None:
        if features <= 0:
            raise BenchError(f"--features must be positive, got {features}")
        profile = replace(profile, features=features)
    return profile


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``owl_bench``; returns the exit status.

    Pins OpenCV and the loaded BLAS libraries to one thread (``owl_ros.threads``): the
    timings are per-thread figures. Importing this module changes nothing.
    """
    one_thread()
    keep_freed_memory()
    args = build_parser().parse_args(argv)
    profile = replace(QUICK if args.quick else FULL, clock=args.clock)
    try:
        profile = chosen_profile(
            profile, args.cases, args.bag, args.seconds, args.seeds, args.features
        )
        profile = replace(profile, engine_params=parse_engine_params(args.param))

        def log(text: str) -> None:
            if not args.quiet:
                print(f"{PROG}: {text}", file=sys.stderr, flush=True)

        cache = None if args.no_cache else Path(args.cache_dir or user_cache_dir("frames"))
        log(f"frame cache: {cache}" if cache is not None else "frame cache: off")
        doc = run_bench(profile, cache, log)
    except (ToolError, BagError, OwlError, OSError, EvalError) as err:
        print(f"{PROG}: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    if args.json:
        print(json.dumps(doc))
    else:
        print("\n".join(report_lines(doc)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
