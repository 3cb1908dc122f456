"""The engine's CPU time per frame against features and against image size.

Runs :class:`owl_core.engine.OwlEngine` alone (no baselines, no DDS) over one rendered
scenario (the ``owl_bench`` frame cache is shared) once per setting, one thread, and
times every stage in the process's CPU time (``time.process_time``: independent of other
load on the machine). Prints a table (``--json`` for one object) and, with ``--plot``,
writes a PNG with ms/frame against tracked features and against megapixels. ``--runs N``
measures every setting N times (interleaved: all settings, then again) and reports each
figure's median over the runs (CPU time still varies by +-15 % from run to run on a shared
VM).

    python -m owl_ros.tools.cost --runs 3 --plot docs/images/cost.png
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from owl_core.types import ImageFrame
from owl_ros.heap import keep_freed_memory
from owl_ros.threads import one_thread
from owl_ros.tools import bench

PROG = "python -m owl_ros.tools.cost"
STAGES = ("track", "lk", "detect", "integrate", "heading", "looming", "total")


def measure(
    scenario: str, width: int, height: int, features: int, seconds: float, cache: Path | None
) -> dict[str, Any]:
    """CPU ms per frame of each engine stage on ``scenario`` at one setting."""
    profile = replace(bench.FULL, width=width, height=height, features=features, seconds=seconds)
    case = bench.Case(scenario)
    sim = bench._sim(case, profile)
    frames = bench.load_frames(sim, cache)
    engine = bench.sim_engine(sim, max_features=features)
    engine.clock = time.process_time
    sums = dict.fromkeys(STAGES, 0.0)
    tracks = 0
    n = int(frames.stamps_ns.size)
    for k in range(n):
        res = engine.process(ImageFrame(int(frames.stamps_ns[k]), frames.images[k]))
        for key in STAGES:
            sums[key] += res.timings.get(key, 0.0)
        tracks += engine.last_tracks.num_tracks if engine.last_tracks is not None else 0
    return {
        "size": f"{width}x{height}",
        "features": features,
        "tracked_per_frame": tracks / max(n, 1),
        "frames": n,
        "ms_per_frame": {k: 1e3 * v / max(n, 1) for k, v in sums.items()},
    }


def plot(
    rows_features: list[dict[str, Any]], rows_sizes: list[dict[str, Any]], path: Path
) -> None:
    """Two panels: CPU ms/frame (total and per stage) against features and against size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, rows, xkey, label in (
        (axes[0], rows_features, "tracked_per_frame", "tracked features per frame (640x480)"),
        (axes[1], rows_sizes, "mpix", "image size, megapixels (1000 features requested)"),
    ):
        if not rows:
            continue
        for r in rows:
            w, h = (int(v) for v in r["size"].split("x"))
            r["mpix"] = w * h / 1e6
        xs = [r[xkey] for r in rows]
        for stage in ("total", "lk", "detect", "integrate", "heading", "looming"):
            ax.plot(xs, [r["ms_per_frame"][stage] for r in rows], marker="o", label=stage)
        ax.set_xlabel(label)
        ax.set_ylabel("CPU ms per frame")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def median_rows(runs: Sequence[Sequence[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Per setting, the median over ``runs`` (each a list of :func:`measure` rows in the
    same order) of the tracked features and of every stage's ms per frame."""
    out = []
    for rows in zip(*runs, strict=True):
        first = dict(rows[0])
        first["tracked_per_frame"] = float(np.median([r["tracked_per_frame"] for r in rows]))
        first["ms_per_frame"] = {
            k: float(np.median([r["ms_per_frame"][k] for r in rows])) for k in STAGES
        }
        first["runs"] = len(rows)
        out.append(first)
    return out


def image_size(text: str) -> tuple[int, int]:
    """``WxH`` (each >= 32) -> (width, height); argparse's error otherwise."""
    w, _, h = text.partition("x")
    if not (w.isdigit() and h.isdigit()) or int(w) < 32 or int(h) < 32:
        raise argparse.ArgumentTypeError(f"size must be WxH (>= 32x32), got {text!r}")
    return int(w), int(h)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: measure the two series, print them, optionally plot."""
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default="street", help="scenario (owl_make_bag --list)")
    p.add_argument("--features", type=int, nargs="*", default=[250, 500, 1000, 2000])
    p.add_argument(
        "--sizes",
        type=image_size,
        nargs="*",
        default=[(320, 240), (640, 480), (960, 540), (1280, 720)],
    )
    p.add_argument("--seconds", type=float, default=3.0, help="clip per feature setting, s")
    p.add_argument("--size-seconds", type=float, default=1.0, help="clip per image size, s")
    p.add_argument("--cache-dir", default="results/cache")
    p.add_argument("--plot", default=None, help="write the PNG here")
    p.add_argument("--json", action="store_true")
    p.add_argument("--runs", type=int, default=1, help="runs per setting; medians reported")
    args = p.parse_args(argv)
    if any(f < 1 for f in args.features):
        p.error(f"--features must be positive, got {args.features}")
    if args.runs < 1:
        p.error(f"--runs must be >= 1, got {args.runs}")
    one_thread()
    keep_freed_memory()
    cache = Path(args.cache_dir)
    runs_f, runs_s = [], []
    for _ in range(args.runs):
        runs_f.append(
            [measure(args.scenario, 640, 480, f, args.seconds, cache) for f in args.features]
        )
        runs_s.append(
            [measure(args.scenario, w, h, 1000, args.size_seconds, cache) for w, h in args.sizes]
        )
    by_features, by_size = median_rows(runs_f), median_rows(runs_s)
    if args.json:
        print(json.dumps({"features": by_features, "sizes": by_size}))
    else:
        print("size      requested  tracked  " + "  ".join(f"{s:>9}" for s in STAGES))
        for r in by_features + by_size:
            ms = r["ms_per_frame"]
            print(
                f"{r['size']:<9} {r['features']:>9} {r['tracked_per_frame']:>8.0f}  "
                + "  ".join(f"{ms[s]:>9.2f}" for s in STAGES)
            )
    if args.plot:
        plot(by_features, by_size, Path(args.plot))
    return 0


if __name__ == "__main__":
    sys.exit(main())
