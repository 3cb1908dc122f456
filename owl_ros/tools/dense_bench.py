"""Benchmark of the dense stage (``python -m owl_ros.tools.dense_bench``, ``make bench-dense``).

On the static synthetic scenarios (rendered at 640x480, 30 Hz, exact ground truth; the
frames are shared with ``owl_bench``'s cache), the sparse engine runs as in the node and
hands its heading and gyro bias to :class:`owl_core.dense.DenseOwl` (working resolution
320x240 by default). Scored against the truth, pooled over the scenarios after a warm-up:

- r/|t| relative error over the confident pixels (median, p90) and the fraction of
  textured pixels that are confident; the same error for the local rule alone and the
  heading route alone over the same pixels (the two inputs of the fusion);
- the time to contact reported for the path cone against the truth's (the same
  ``ttc_min_pixels``-th smallest ``r/(t.e)`` over the cone about the true heading);
- CPU time of the dense stage per frame (``time.process_time``, OpenCV on one thread),
  median over frames, per DIS preset.

Truth per working pixel: the mean range of the input pixels it covers; working pixels
whose block straddles a depth edge (range spread > 5 %) and pixels on independently moving
objects are not scored. ``--walk DIR`` also runs the ASL folder of a real recording (no
truth): the confident fraction per frame and a figure of the images.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from bags.cli import OneLineErrorParser
from bags.sim import scenarios
from bags.sim.scenarios import SimOptions
from owl_core.camera import CameraModel
from owl_core.dense import DenseOptions, DenseOwl, DenseResult
from owl_core.engine import EngineOptions, OwlEngine
from owl_core.geometry import matrix_to_quat_xyzw
from owl_core.types import GyroSamples, ImageFrame
from owl_ros.heap import keep_freed_memory
from owl_ros.threads import one_thread
from owl_ros.tools.bench import load_frames, sim_engine

STATIC = ("cube", "scaled", "accel", "turn", "street", "receding")
WARMUP = 8

F64 = npt.NDArray[np.float64]


def _block_truth(range_m: npt.NDArray[np.float32], h: int, w: int) -> F64:
    """(h, w) mean range over each working pixel's input block; NaN across depth edges."""
    big_h, big_w = range_m.shape
    r = range_m.astype(np.float64).reshape(h, big_h // h, w, big_w // w)
    lo, hi = r.min(axis=(1, 3)), r.max(axis=(1, 3))
    mean = r.mean(axis=(1, 3))
    ok = np.isfinite(mean) & (hi <= 1.05 * lo) & (mean < 1e3)
    return np.where(ok, mean, np.nan)


def _engine_pass(case: str, seconds: float, cache: Path | None) -> tuple[Any, list[Any]]:
    """Render (or load) a case and run the sparse engine; per frame what the dense stage
    needs: (stamp, image, rotation from each earlier stamp, heading, sigma, velocity, range)."""
    sim = scenarios.get(case).simulate(SimOptions(seconds=seconds, width=640, height=480))
    frames = load_frames(sim, cache)
    cam = sim.options.camera()
    eng = sim_engine(sim)
    out = []
    for k in range(frames.images.shape[0]):
        stamp = int(frames.stamps_ns[k])
        res = eng.process(ImageFrame(stamp, frames.images[k]))
        rots = {}
        for back in range(1, 6):
            if k - back >= 0:
                s0 = int(frames.stamps_ns[k - back])
                if eng.gyro.covers(s0, stamp):
                    rots[s0] = eng.gyro.relative_rotation(s0, stamp, eng.gyro_bias)
        mask = None if frames.mask is None else frames.mask[k]
        out.append(
            (
                stamp,
                frames.images[k],
                rots,
                res.heading,
                res.heading_sigma_rad,
                res.speed_rate,
                frames.velocity[k],
                frames.range_m[k],
                mask,
            )
        )
    return cam, out


def _run_dense(
    cam: CameraModel, frames: list[Any], options: DenseOptions
) -> tuple[dict[str, list[Any]], list[float]]:
    dense = DenseOwl(cam, options)
    grid = dense.grid
    h, w = options.height, options.width
    acc: dict[str, list[Any]] = {
        "rel": [],
        "rel_local": [],
        "rel_heading": [],
        "textured": [],
        "confident": [],
        "ttc": [],
    }
    cpu: list[float] = []
    cos_cone = math.cos(math.radians(options.ttc_cone_deg))
    for k, (stamp, image, rots, heading, sigma, rate, vel, rng, mask) in enumerate(frames):
        prev = dense.previous_stamp_ns
        rot = rots.get(prev) if prev is not None else None
        c0 = time.process_time()
        res = dense.process(image, stamp, rot, heading, sigma, rate)
        cpu.append(time.process_time() - c0)
        if res is None or k < WARMUP or heading is None:
            continue
        speed = float(np.linalg.norm(vel))
        truth_r = _block_truth(rng, h, w)
        if mask is not None:
            moving = mask.reshape(h, mask.shape[0] // h, w, mask.shape[1] // w).any(axis=(1, 3))
            truth_r[moving] = np.nan
        ros_t = truth_r / speed
        scored = np.isfinite(ros_t)
        conf = res.confident & scored
        acc["rel"].append(np.abs(res.range_over_speed[conf] - ros_t[conf]) / ros_t[conf])
        acc["textured"].append(int(np.count_nonzero(res.textured & scored)))
        acc["confident"].append(int(np.count_nonzero(res.confident & res.textured & scored)))
        e = grid.bearings.astype(np.float64)
        omega2 = np.sum(res.omega.astype(np.float64) ** 2, axis=-1)
        for key, looming in (
            ("rel_local", res.looming_local),
            ("rel_heading", res.looming_heading),
        ):
            # r/|t| from one route's L with the measured omega, on the same confident pixels
            ros = 1.0 / np.sqrt(looming.astype(np.float64) ** 2 + omega2)
            good = conf & np.isfinite(ros)
            acc[key].append(np.abs(ros[good] - ros_t[good]) / ros_t[good])
        acc["ttc"].append(_ttc_pair(res, e, vel, truth_r, cos_cone, options.ttc_min_pixels))
    return acc, cpu


def _ttc_pair(
    res: DenseResult, e: F64, vel: F64, truth_r: F64, cos_cone: float, k: int
) -> tuple[float, float, float]:
    """(estimated TTC, true k-th smallest TTC in the true path cone, true minimum), s."""
    h = vel / np.linalg.norm(vel)
    closing = e @ vel
    cone = (e @ h >= cos_cone) & np.isfinite(truth_r) & (closing > 0)
    true_ttc = truth_r[cone] / closing[cone]
    est = res.ttc.seconds if res.ttc is not None else math.nan
    if true_ttc.size == 0:
        return est, math.nan, math.nan
    kth = float(np.partition(true_ttc, min(k, true_ttc.size) - 1)[min(k, true_ttc.size) - 1])
    return est, kth, float(true_ttc.min())


def _pct(values: list[Any], q: float) -> float:
    flat = np.concatenate(values) if values else np.zeros(0)
    return float(np.percentile(flat, q)) * 100.0 if flat.size else math.nan


def _summary(acc: dict[str, list[Any]], cpu: list[float]) -> dict[str, Any]:
    ttc = np.array(acc["ttc"], dtype=np.float64).reshape(-1, 3)
    both = np.isfinite(ttc[:, 0]) & np.isfinite(ttc[:, 1])
    ttc_rel = np.abs(ttc[both, 0] - ttc[both, 1]) / ttc[both, 1]
    ttc_rel_min = np.abs(ttc[both, 0] - ttc[both, 2]) / ttc[both, 2]
    textured = sum(acc["textured"])
    return {
        "ros_median_pct": _pct(acc["rel"], 50),
        "ros_p90_pct": _pct(acc["rel"], 90),
        "local_only_median_pct": _pct(acc["rel_local"], 50),
        "local_only_p90_pct": _pct(acc["rel_local"], 90),
        "heading_only_median_pct": _pct(acc["rel_heading"], 50),
        "heading_only_p90_pct": _pct(acc["rel_heading"], 90),
        "confident_of_textured_pct": 100.0 * sum(acc["confident"]) / max(textured, 1),
        "ttc_frames": int(ttc.shape[0]),
        "ttc_frames_scored": int(np.count_nonzero(both)),
        "ttc_median_rel_pct": float(np.median(ttc_rel)) * 100 if ttc_rel.size else math.nan,
        "ttc_within_10pct_pct": float(np.mean(ttc_rel <= 0.1)) * 100 if ttc_rel.size else math.nan,
        "ttc_median_rel_to_true_min_pct": (
            float(np.median(ttc_rel_min)) * 100 if ttc_rel_min.size else math.nan
        ),
        "cpu_ms_median": float(np.median(cpu)) * 1e3 if cpu else math.nan,
        "fps_cpu": 1.0 / float(np.median(cpu)) if cpu else math.nan,
    }


def run_synthetic(
    cases: Sequence[str],
    presets: Sequence[str],
    seconds: float,
    cache: Path | None,
    log: Any,
    min_confidence: float = 0.5,
) -> dict[str, Any]:
    """The synthetic part: per preset pooled over ``cases``, and per case."""
    passes = []
    for case in cases:
        log(f"engine pass: {case}")
        passes.append((case, *_engine_pass(case, seconds, cache)))
    doc: dict[str, Any] = {"cases": list(cases), "seconds": seconds, "presets": {}}
    for preset in presets:
        opts = DenseOptions(preset=preset, min_confidence=min_confidence)
        pooled: dict[str, list[Any]] = {}
        cpu_all: list[float] = []
        per_case = {}
        for case, cam, frames in passes:
            log(f"dense {preset}: {case}")
            acc, cpu = _run_dense(cam, frames, opts)
            per_case[case] = _summary(acc, cpu)
            for key, value in acc.items():
                pooled.setdefault(key, []).extend(value)
            cpu_all.extend(cpu)
        doc["presets"][preset] = {"pooled": _summary(pooled, cpu_all), "per_case": per_case}
    return doc


# ------------------------------------------------------------------------- real data


def _asl_camera(folder: Path) -> tuple[CameraModel, tuple[float, float, float, float]]:
    import yaml

    cfg = yaml.safe_load((folder / "mav0" / "cam0" / "sensor.yaml").read_text())
    fx, fy, cx, cy = (float(v) for v in cfg["intrinsics"])
    w, h = (int(v) for v in cfg["resolution"])
    k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    d = np.array([float(v) for v in cfg["distortion_coefficients"]] + [0.0])
    cam = CameraModel(w, h, k, d, "plumb_bob")
    t_bs = np.array(cfg["T_BS"]["data"], dtype=np.float64).reshape(4, 4)
    q = matrix_to_quat_xyzw(t_bs[:3, :3])
    return cam, (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def run_walk(folder: Path, out_dir: Path, log: Any) -> dict[str, Any]:
    """The real recording: confident fraction per frame and a figure of a few frames."""
    cam, q = _asl_camera(folder)
    imu = np.loadtxt(folder / "mav0" / "imu0" / "data.csv", delimiter=",", comments="#")
    rows = [
        line.split(",")
        for line in (folder / "mav0" / "cam0" / "data.csv").read_text().splitlines()
        if line and not line.startswith("#")
    ]
    eng = OwlEngine(cam, EngineOptions(camera_to_imu_rotation_xyzw=q))
    eng.add_gyro(GyroSamples(imu[:, 0].astype(np.int64), imu[:, 1:4]))
    dopts = DenseOptions(width=320, height=180)
    dense = DenseOwl(cam, dopts)
    fractions: list[float] = []
    picks: list[tuple[int, Any, DenseResult]] = []
    cpu: list[float] = []
    for k, (stamp_text, name) in enumerate(rows):
        stamp = int(stamp_text)
        img = cv2.imread(
            str(folder / "mav0" / "cam0" / "data" / name.strip()), cv2.IMREAD_GRAYSCALE
        )
        if img is None:
            log(f"unreadable image {name}")
            continue
        res = eng.process(ImageFrame(stamp, img))
        prev = dense.previous_stamp_ns
        rot = None
        if prev is not None and eng.gyro.covers(prev, stamp):
            rot = eng.gyro.relative_rotation(prev, stamp, eng.gyro_bias)
        c0 = time.process_time()
        d = dense.process(img, stamp, rot, res.heading, res.heading_sigma_rad, res.speed_rate)
        cpu.append(time.process_time() - c0)
        if d is None or res.heading is None:
            fractions.append(math.nan)
            continue
        fractions.append(d.confident_fraction)
        if k % 40 == 20 and len(picks) < 4:
            picks.append((k, img, d))
    frac = np.array(fractions)
    out_dir.mkdir(parents=True, exist_ok=True)
    figure = out_dir / "dense_realsense_walk.png"
    _walk_figure(picks, figure)
    valid = np.isfinite(frac)
    return {
        "frames": len(rows),
        "frames_with_dense_result": int(np.count_nonzero(valid)),
        "confident_fraction_median_pct": float(np.median(frac[valid])) * 100
        if valid.any()
        else math.nan,
        "confident_fraction_p10_p90_pct": [
            float(np.percentile(frac[valid], 10)) * 100 if valid.any() else math.nan,
            float(np.percentile(frac[valid], 90)) * 100 if valid.any() else math.nan,
        ],
        "cpu_ms_median": float(np.median(cpu)) * 1e3,
        "figure": str(figure),
    }


def _walk_figure(picks: list[tuple[int, Any, DenseResult]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not picks:
        return
    fig, axes = plt.subplots(len(picks), 4, figsize=(14, 2.4 * len(picks)), squeeze=False)
    for row, (k, img, d) in zip(axes, picks, strict=True):
        conf = d.confident
        row[0].imshow(img, cmap="gray")
        row[0].set_title(f"frame {k}")
        looming = np.where(conf, d.looming, np.nan)
        ros = np.where(conf, d.range_over_speed, np.nan)
        l_hi = float(np.nanpercentile(np.abs(looming), 95)) if conf.any() else 1.0
        r_hi = float(np.nanpercentile(ros, 95)) if conf.any() else 10.0
        im = row[1].imshow(looming, cmap="coolwarm", vmin=-l_hi, vmax=l_hi)
        row[1].set_title("L (1/s), confident")
        fig.colorbar(im, ax=row[1], fraction=0.03)
        im = row[2].imshow(ros, cmap="viridis", vmin=0, vmax=r_hi)
        row[2].set_title("r/|t| (s), confident")
        fig.colorbar(im, ax=row[2], fraction=0.03)
        im = row[3].imshow(d.confidence, cmap="gray", vmin=0, vmax=1)
        row[3].set_title(f"confidence ({100 * d.confident_fraction:.0f} % of textured)")
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


# ------------------------------------------------------------------- demo figure


def dense_figure(sim: Any, frames: Any, path: Path, frame: int | None = None) -> Path:
    """The paper's dense figure from real pixels: L, omega_x, omega_y and the scaled cloud
    of one frame of ``sim`` (a bags Simulation whose ``frames`` were loaded by
    ``owl_ros.tools.bench.load_frames``), each beside the truth; written to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cam = sim.options.camera()
    eng = sim_engine(sim)
    # the benchmark's 320x240 from VGA; smaller inputs at their own size
    div = 2 if cam.width >= 640 and cam.height >= 480 else 1
    dense = DenseOwl(cam, DenseOptions(width=cam.width // div, height=cam.height // div))
    n = frames.images.shape[0]
    last = min(n - 1, frame if frame is not None else WARMUP + 8)
    res = None
    for k in range(last + 1):
        stamp = int(frames.stamps_ns[k])
        sparse = eng.process(ImageFrame(stamp, frames.images[k]))
        prev = dense.previous_stamp_ns
        rot = None
        if prev is not None and eng.gyro.covers(prev, stamp):
            rot = eng.gyro.relative_rotation(prev, stamp, eng.gyro_bias)
        res = dense.process(
            frames.images[k],
            stamp,
            rot,
            sparse.heading,
            sparse.heading_sigma_rad,
            sparse.speed_rate,
        )
    if res is None:
        raise ValueError("dense figure: no dense result (too few frames)")
    o = dense.options
    e = dense.grid.bearings.astype(np.float64)
    vel = frames.velocity[last]
    r = _block_truth(frames.range_m[last], o.height, o.width)
    l_true = (e @ vel) / r
    w_true = np.cross(e, vel) / r[..., None]
    conf = res.confident
    pairs = [
        ("L (1/s)", np.where(conf, res.looming, np.nan), l_true, "magma"),
        ("omega_x (1/s)", np.where(conf, res.omega[..., 0], np.nan), w_true[..., 0], "coolwarm"),
        ("omega_y (1/s)", np.where(conf, res.omega[..., 1], np.nan), w_true[..., 1], "coolwarm"),
    ]
    fig, axes = plt.subplots(4, 2, figsize=(10, 13))
    for row, (name, est, truth, cmap) in zip(axes[:3], pairs, strict=True):
        lim = float(np.nanpercentile(np.abs(truth), 98))
        lo = 0.0 if cmap == "magma" else -lim
        for ax, img, who in ((row[0], est, "OWL dense"), (row[1], truth, "truth")):
            im = ax.imshow(img, cmap=cmap, vmin=lo, vmax=lim)
            ax.set_title(f"{name}: {who}")
            ax.set_xticks([])
            ax.set_yticks([])
        fig.colorbar(im, ax=row, fraction=0.025)
    step = 3
    sub = (slice(None, None, step), slice(None, None, step))
    speed = float(np.linalg.norm(vel))
    pts_est = res.points[sub][conf[sub]]
    truth_pts = (e * (r / speed)[..., None])[sub]
    truth_pts = truth_pts[np.all(np.isfinite(truth_pts), axis=-1)]
    for ax, pts, who in ((axes[3, 0], pts_est, "OWL dense"), (axes[3, 1], truth_pts, "truth")):
        near = pts[:, 2] < 15.0
        ax.scatter(pts[near, 0], pts[near, 2], s=0.5, c=-pts[near, 1], cmap="viridis")
        ax.set_xlim(-8, 8)
        ax.set_ylim(0, 15)
        ax.set_xlabel("x (s)")
        ax.set_ylabel("z (s)")
        ax.set_title(f"scaled cloud e r/|t|, top view: {who}")
    fig.suptitle(
        f"{sim.scenario.name}, frame {last}: dense OWL from pixels "
        f"({100 * res.confident_fraction:.0f} % of textured pixels confident)"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------- CLI


def build_parser() -> argparse.ArgumentParser:
    p = OneLineErrorParser(prog="owl_dense_bench", description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", default=",".join(STATIC), help="comma-separated scenarios")
    p.add_argument(
        "--presets", default="balanced,medium,fast,ultrafast", help="DIS presets to run"
    )
    p.add_argument("--seconds", type=float, default=1.5, help="seconds per case (30 Hz)")
    p.add_argument("--cache-dir", default="results/cache", help="rendered-frame cache")
    p.add_argument(
        "--min-confidence", type=float, default=0.5, help="confidence of a confident pixel"
    )
    p.add_argument("--walk", default=None, help="ASL folder of a real recording")
    p.add_argument("--out", default="results/dense", help="figures go here")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    one_thread()
    keep_freed_memory()
    cases = [c for c in args.cases.split(",") if c]
    for c in cases:
        if c not in scenarios.names():
            print(f"owl_dense_bench: unknown scenario {c!r}", file=sys.stderr)
            return 2
    presets = [p for p in args.presets.split(",") if p]

    def log(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    if not 0.0 <= args.min_confidence <= 1.0:
        print(
            f"owl_dense_bench: --min-confidence must be in [0, 1], got {args.min_confidence}",
            file=sys.stderr,
        )
        return 2
    doc = run_synthetic(
        cases, presets, args.seconds, Path(args.cache_dir), log, args.min_confidence
    )
    if args.walk:
        walk = Path(args.walk)
        if not (walk / "mav0" / "cam0" / "data.csv").is_file():
            print(f"owl_dense_bench: no mav0/cam0/data.csv under {walk}", file=sys.stderr)
            return 2
        doc["walk"] = run_walk(walk, Path(args.out), log)
    if args.json:
        print(json.dumps(doc, indent=1))
    else:
        for preset, part in doc["presets"].items():
            print(f"preset {preset}: " + json.dumps(part["pooled"]))
            for case, s in part["per_case"].items():
                print(f"  {case}: " + json.dumps(s))
        if "walk" in doc:
            print("walk: " + json.dumps(doc["walk"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["build_parser", "dense_figure", "main", "run_synthetic", "run_walk"]
