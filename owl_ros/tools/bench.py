"""owl_bench: OWL against the classical two-view baseline, side by side, in one process.

For each standard case (a named scenario from :mod:`bags.sim.scenarios`, with or without a
constant gyro bias) the frames are rendered in memory (no bags, no DDS) or loaded from the
cache (``~/.cache/owl_ros/frames``, see ``--cache-dir``; the images do not depend on the
IMU, so the biased and unbiased rows share them). Then one pass over the frames:

1. the OWL engine (:class:`owl_core.engine.OwlEngine`) processes the image and the gyro;
2. on exactly the engine's tracks of that frame, the baseline runs twice
   (:mod:`owl_core.baseline`): OpenCV's 5-point essential matrix + recoverPose +
   triangulation ("cv-5pt"), and the gyro-aided translation-only variant ("cv-gyro",
   derotated with the same gyro, without bias estimation);
3. all three are scored by the same :mod:`owl_ros.tools.evaluate` functions against the
   exact truth.

Timing: per-stage times from the engine (track = LK + detection, integrate, heading,
looming) and the baseline's estimation time; frames/s = frames / (tracking + estimation)
for each method (they share tracking); ``estimation_speedup`` = baseline estimation time /
OWL estimation time (tracking excluded). One thread (OpenCV and BLAS). Peak memory is the
process's maximum resident set size (it includes rendering).

``owl_bench`` (full, ``make bench``): 640x480, 1000 features, 3 s at 30 Hz per case.
``owl_bench --quick``: 320x240, 300 features, 1 s, four cases, under a minute.
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
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from bags.cli import OneLineErrorParser, user_cache_dir
from bags.errors import BagError
from bags.sim import scenarios
from bags.sim.scenarios import SimOptions, Simulation
from bags.sim.sensors import ImuOptions
from owl_core.baseline import BaselineFrame, BaselineOptions, TwoViewBaseline
from owl_core.engine import EngineOptions, OwlEngine
from owl_core.errors import OwlError
from owl_core.types import FrameResult, ImageFrame
from owl_ros.tools.errors import BenchError, ToolError
from owl_ros.tools.evaluate import Estimate, FrameScore, Truth, score_frame, summarize
from owl_ros.tools.threads import one_thread

PROG = "owl_bench"
#: Thread-count variables main() sets to 1 (unless already set) for one-thread timings.
METHODS = ("owl", "cv-5pt", "cv-gyro")
#: Bias magnitude of the biased rows, rad/s, along (1, 1, 1)/sqrt(3) in the IMU frame.
BIAS = 0.01
#: Scenarios without independently moving objects and with translation (pooled accuracy).
STATIC = ("cube", "scaled", "accel", "turn", "street", "receding")


@dataclass(frozen=True)
class Case:
    """One benchmark row: a scenario and a gyro-bias magnitude (rad/s)."""

    scenario: str
    bias: float = 0.0

    @property
    def label(self) -> str:
        """e.g. "street" or "street+bias"."""
        return self.scenario + ("+bias" if self.bias else "")


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


FULL = Profile(
    "full",
    640,
    480,
    3.0,
    1000,
    tuple(Case(s) for s in (*STATIC, "mover", "rotation_only"))
    + tuple(Case(s, BIAS) for s in ("street", "turn", "cube", "mover")),
)
QUICK = Profile(
    "quick",
    320,
    240,
    1.0,
    300,
    (Case("street"), Case("street", BIAS), Case("cube"), Case("mover")),
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


def _sim(case: Case, profile: Profile) -> Simulation:
    b = case.bias / math.sqrt(3.0)
    opts = SimOptions(
        seconds=profile.seconds,
        rate_hz=profile.rate_hz,
        width=profile.width,
        height=profile.height,
        imu=ImuOptions(gyro_bias=(b, b, b)),
    )
    return scenarios.get(case.scenario).simulate(opts)


def _cache_key(sim: Simulation) -> str:
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
    ]
    return "_".join(parts)


def load_frames(
    sim: Simulation, cache_dir: Path | None, log: Callable[[str], None] = lambda s: None
) -> Frames:
    """The simulation's frames, from ``cache_dir`` when cached there (else rendered, stored)."""
    path = cache_dir / f"{_cache_key(sim)}.npz" if cache_dir is not None else None
    if path is not None and path.is_file():
        try:
            with np.load(path) as z:
                mask = z["mask"] if z["has_mask"] else None
                return Frames(
                    z["stamps"], z["images"], z["range"].astype(np.float32), mask, z["velocity"]
                )
        except (OSError, ValueError, KeyError):
            log(f"cache {path} unreadable: rendering again")
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
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(
            tmp,
            stamps=frames.stamps_ns,
            images=images,
            range=ranges.astype(np.float16),  # 5e-4 relative: far below the errors scored
            mask=masks,
            has_mask=has_mask,
            velocity=vel,
        )
        tmp.replace(path)
    return frames


# ------------------------------------------------------------------------ one case


def owl_estimate(res: FrameResult) -> Estimate:
    """What owl_eval scores of an engine FrameResult."""
    return Estimate(
        res.stamp_ns, res.heading, res.pixels, res.range_over_speed, res.flags, res.gyro_bias
    )


def baseline_estimate(res: BaselineFrame) -> Estimate:
    """What owl_eval scores of a baseline frame (no bias estimate)."""
    return Estimate(res.stamp_ns, res.heading, res.pixels, res.range_over_speed, res.flags)


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


def run_case(
    case: Case,
    profile: Profile,
    frames: Frames,
    sim: Simulation,
    keep_results: bool = False,
) -> CaseRun:
    """Run OWL and both baselines over the frames, on the same tracks, and score them."""
    engine = OwlEngine(
        sim.camera,
        EngineOptions(
            camera_to_imu_rotation_xyzw=sim.camera_to_imu_xyzw,
            imu_time_offset_s=sim.imu_time_offset_ns * 1e-9,
            max_features=profile.features,
        ),
    )
    clock = time.process_time if profile.clock == "cpu" else time.perf_counter
    engine.clock = clock
    engine.add_gyro(sim.gyro_samples())
    gyro = engine.gyro

    def rotation(t0: int, t1: int) -> npt.NDArray[np.float64] | None:
        return gyro.relative_rotation(t0, t1) if gyro.covers(t0, t1) else None

    baselines = {
        "cv-5pt": TwoViewBaseline(sim.camera, BaselineOptions(method="essential")),
        "cv-gyro": TwoViewBaseline(sim.camera, BaselineOptions(method="gyro"), rotation),
    }
    b = case.bias / math.sqrt(3.0)
    truth_bias = np.array([b, b, b])
    run = CaseRun(case, int(frames.stamps_ns.size), {m: [] for m in METHODS})
    run.has_mask = frames.mask is not None
    run.estimate_s = dict.fromkeys(METHODS, 0.0)
    run.baseline_results = {m: [] for m in baselines}
    for base in baselines.values():
        base.clock = clock
    n_tracks = 0
    for k in range(frames.stamps_ns.size):
        truth = frames.truth(k)
        res = engine.process(ImageFrame(truth.stamp_ns, frames.images[k]))
        for key, value in res.timings.items():
            run.owl_stage_s[key] = run.owl_stage_s.get(key, 0.0) + value
        track_s = res.timings.get("track", 0.0)
        run.track_s += track_s
        run.estimate_s["owl"] += res.timings.get("total", 0.0) - track_s
        run.scores["owl"].append(score_frame(owl_estimate(res), truth, truth_bias))
        tracks = engine.last_tracks  # the very tracks OWL used for this frame
        if tracks is not None:
            n_tracks += tracks.num_tracks
        for name, base in baselines.items():
            if tracks is None:
                continue
            out = base.process(tracks)
            run.estimate_s[name] += out.timings["estimate"]
            run.scores[name].append(score_frame(baseline_estimate(out), truth))
            if keep_results:
                run.baseline_results[name].append(out)
        if keep_results:
            run.owl_results.append(res)
    run.tracks_per_frame = n_tracks / max(run.frames, 1)
    return run


# ------------------------------------------------------------------------ reporting


def _method_row(run: CaseRun, method: str) -> dict[str, Any]:
    s = summarize(run.scores[method], run.has_mask)
    total = run.track_s + run.estimate_s[method]
    s["fps"] = run.frames / total if total > 0 else None
    s["estimate_ms_per_frame"] = 1e3 * run.estimate_s[method] / max(run.frames, 1)
    return s


def case_report(run: CaseRun) -> dict[str, Any]:
    """JSON-ready row of one case."""
    stages = {k: 1e3 * v / max(run.frames, 1) for k, v in run.owl_stage_s.items()}
    return {
        "case": run.case.label,
        "scenario": run.case.scenario,
        "gyro_bias_rad_s": run.case.bias,
        "frames": run.frames,
        "tracks_per_frame": run.tracks_per_frame,
        "owl_stage_ms_per_frame": stages,
        "methods": {m: _method_row(run, m) for m in METHODS},
    }


def _pooled(
    runs: Sequence[CaseRun], method: str, biased: bool, only: set[str] | None = None
) -> dict[str, Any]:
    scores = [
        s
        for r in runs
        if r.case.scenario in STATIC
        and bool(r.case.bias) == biased
        and (only is None or r.case.scenario in only)
        for s in r.scores[method]
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
    per frame, mean over cases), owl_fps, baseline_fps (cv-5pt), baseline_gyro_fps,
    estimation_speedup (cv-5pt estimation time / OWL estimation time, tracking excluded),
    estimation_speedup_gyro, owl_/baseline_/baseline_gyro_ heading_deg_median/p90 and
    range_rel_median/p90 pooled over the static scenarios without bias, the same with suffix
    ``_bias`` for the biased rows and ``_nobias_matched`` for the unbiased rows of the same
    scenarios, owl_points_per_frame, frames_held_mb (rendered frames + truth in memory),
    owl_stage_ms_per_frame, heading_ratio and range_ratio (OWL / cv-5pt medians),
    peak_rss_mb, machine, cases (per-case rows: stage times, and per method every owl_eval
    summary key + fps).
    """
    cv2.setNumThreads(1)
    runs: list[CaseRun] = []
    images: dict[str, Frames] = {}
    frames_mb = 0.0
    t_start = time.monotonic()
    for i, case in enumerate(profile.cases, start=1):
        sim = _sim(case, profile)
        log(f"[{i}/{len(profile.cases)}] {case.label}: frames")
        if case.scenario not in images:
            images = {case.scenario: load_frames(sim, cache_dir, log)}
        frames = images[case.scenario]
        held = frames.images.nbytes + frames.range_m.nbytes + frames.velocity.nbytes
        frames_mb = max(
            frames_mb, (held + (frames.mask.nbytes if frames.mask is not None else 0)) / 2**20
        )
        log(
            f"[{i}/{len(profile.cases)}] {case.label}: OWL + baselines on {frames.stamps_ns.size} "
            f"frames ({time.monotonic() - t_start:.0f} s elapsed)"
        )
        runs.append(run_case(case, profile, frames, sim))
    total_frames = sum(r.frames for r in runs)
    track = sum(r.track_s for r in runs)
    est = {m: sum(r.estimate_s[m] for r in runs) for m in METHODS}
    stages: dict[str, float] = {}
    for r in runs:
        for k, v in r.owl_stage_s.items():
            stages[k] = stages.get(k, 0.0) + v
    out: dict[str, Any] = {
        "profile": profile.name,
        "image_size": f"{profile.width}x{profile.height}",
        "features": profile.features,
        "seconds_per_case": profile.seconds,
        "clock": profile.clock,
        "features_per_frame": float(np.mean([r.tracks_per_frame for r in runs])),
        "owl_fps": total_frames / (track + est["owl"]),
        "baseline_fps": total_frames / (track + est["cv-5pt"]),
        "baseline_gyro_fps": total_frames / (track + est["cv-gyro"]),
        "estimation_speedup": est["cv-5pt"] / est["owl"],
        "estimation_speedup_gyro": est["cv-gyro"] / est["owl"],
        "owl_stage_ms_per_frame": {k: 1e3 * v / total_frames for k, v in stages.items()},
        "baseline_estimate_ms_per_frame": 1e3 * est["cv-5pt"] / total_frames,
        "baseline_gyro_estimate_ms_per_frame": 1e3 * est["cv-gyro"] / total_frames,
    }
    prefix = {"owl": "owl", "cv-5pt": "baseline", "cv-gyro": "baseline_gyro"}
    with_bias = {r.case.scenario for r in runs if r.case.bias}
    pools = ((False, "", None), (False, "_nobias_matched", with_bias), (True, "_bias", None))
    for biased, suffix, only in pools:
        for m in METHODS:
            pooled = _pooled(runs, m, biased, only)
            for key in (
                "heading_deg_median",
                "heading_deg_p90",
                "range_rel_median",
                "range_rel_p90",
            ):
                out[f"{prefix[m]}_{key}{suffix}"] = pooled.get(key)
    owl_pooled = _pooled(runs, "owl", False)
    out["owl_points_per_frame"] = owl_pooled.get("points_per_frame")
    out["heading_ratio"] = _ratio(
        out["owl_heading_deg_median"], out["baseline_heading_deg_median"]
    )
    out["range_ratio"] = _ratio(out["owl_range_rel_median"], out["baseline_range_rel_median"])
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
    out["cases"] = [case_report(r) for r in runs]
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


def report_lines(doc: dict[str, Any]) -> list[str]:
    """The benchmark as text tables."""
    lines = [
        f"{PROG} ({doc['profile']}): {doc['image_size']}, {doc['features']} features requested "
        f"({doc['features_per_frame']:.0f} tracked/frame), {doc['seconds_per_case']:g} s per "
        f"case at 30 Hz, one thread, {doc['machine']['cpu']}, "
        f"{'CPU' if doc.get('clock', 'wall') == 'cpu' else 'wall'} time",
        "",
        "accuracy per case (heading error deg median/p90; r/|t| relative error median; "
        "moving P/R):",
        f"  {'case':<16} {'OWL head':>13} {'cv-5pt head':>13} {'cv-gyro head':>13} "
        f"{'OWL r/|t|':>9} {'5pt r/|t|':>9} {'gyro r/|t|':>10} {'OWL pts':>7} {'moving P/R':>11}",
    ]
    for c in doc["cases"]:
        m = c["methods"]

        def head(s: dict[str, Any]) -> str:
            if s["translating_frames"] == 0:
                return f"{s['false_heading_frames']} false"
            return f"{_f(s['heading_deg_median'])}/{_f(s['heading_deg_p90'])}"

        pr = m["owl"]
        mov = (
            f"{_f(pr['moving_precision'], '.0%')}/{_f(pr['moving_recall'], '.0%')}"
            if pr["moving_precision"] is not None or pr["moving_recall"] is not None
            else "-"
        )
        lines.append(
            f"  {c['case']:<16} {head(m['owl']):>13} {head(m['cv-5pt']):>13} "
            f"{head(m['cv-gyro']):>13} {_f(m['owl']['range_rel_median'], '.1%'):>9} "
            f"{_f(m['cv-5pt']['range_rel_median'], '.1%'):>9} "
            f"{_f(m['cv-gyro']['range_rel_median'], '.1%'):>10} "
            f"{_f(m['owl']['points_per_frame'], '.0f'):>7} {mov:>11}"
        )
    stage_ms = doc["owl_stage_ms_per_frame"]
    owl_est = stage_ms.get("total", 0.0) - stage_ms.get("track", 0.0)
    lines += [
        "",
        "time per frame (ms; tracking shared by all methods):",
        "  OWL stages: " + _stages_text(stage_ms),
        f"  estimation: OWL {owl_est:.1f}, "
        f"cv-5pt {doc['baseline_estimate_ms_per_frame']:.1f}, "
        f"cv-gyro {doc['baseline_gyro_estimate_ms_per_frame']:.1f}",
        f"  frames/s (tracking + estimation): OWL {doc['owl_fps']:.1f}, cv-5pt "
        f"{doc['baseline_fps']:.1f}, cv-gyro {doc['baseline_gyro_fps']:.1f}",
        f"  estimation speedup (baseline / OWL): cv-5pt {doc['estimation_speedup']:.2f}x, "
        f"cv-gyro {doc['estimation_speedup_gyro']:.2f}x",
        "",
        "pooled over the static scenarios (heading deg median/p90, r/|t| median/p90; 'same' ="
        " the scenarios that also have a bias row):",
    ]
    rows = (
        ("no bias, all", ""),
        ("no bias, same", "_nobias_matched"),
        (f"bias {BIAS:g} rad/s", "_bias"),
    )
    for label, suffix in rows:
        for name, prefix in (("OWL", "owl"), ("cv-5pt", "baseline"), ("cv-gyro", "baseline_gyro")):
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
        f"  ratios OWL / cv-5pt: heading {_f(doc['heading_ratio'])}, r/|t| "
        f"{_f(doc['range_ratio'])}",
        "",
        f"peak memory (max RSS, rendering included): {doc['peak_rss_mb']:.0f} MB, of which "
        f"{doc.get('frames_held_mb', 0):.0f} MB are one scenario's frames and truth held in "
        "memory; "
        f"wall time {doc['wall_s']:.0f} s",
    ]
    return lines


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
    p.add_argument("--no-cache", action="store_true", help="render without reading/writing")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return p


def _parse_cases(text: str) -> tuple[Case, ...]:
    out = []
    for item in text.split(","):
        name, _, extra = item.strip().partition("+")
        if extra not in ("", "bias"):
            raise BenchError(f"case {item!r}: only the suffix '+bias' is known")
        scenarios.get(name)  # ScenarioError names the known ones
        out.append(Case(name, BIAS if extra else 0.0))
    return tuple(out)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``owl_bench``; returns the exit status.

    Pins OpenCV and the loaded BLAS libraries to one thread (``tools.threads``): the
    timings are per-thread figures. Importing this module changes nothing.
    """
    one_thread()
    args = build_parser().parse_args(argv)
    profile = replace(QUICK if args.quick else FULL, clock=args.clock)
    try:
        if args.cases:
            profile = replace(profile, cases=_parse_cases(args.cases))
        if args.seconds is not None:
            if not (math.isfinite(args.seconds) and args.seconds > 0):
                raise BenchError(f"--seconds must be positive, got {args.seconds}")
            profile = replace(profile, seconds=args.seconds)
        if args.features is not None:
            if args.features <= 0:
                raise BenchError(f"--features must be positive, got {args.features}")
            profile = replace(profile, features=args.features)

        def log(text: str) -> None:
            if not args.quiet:
                print(f"{PROG}: {text}", file=sys.stderr, flush=True)

        cache = None if args.no_cache else Path(args.cache_dir or user_cache_dir("frames"))
        log(f"frame cache: {cache}" if cache is not None else "frame cache: off")
        doc = run_bench(profile, cache, log)
    except (ToolError, BagError, OwlError, OSError) as err:
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
