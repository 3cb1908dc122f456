"""OWL against itself: two engine settings on the same rendered frames, case by case.

The accuracy check of an engine or tracker change (issue 16: "every case's heading median
and p90 and r/|t| median and p90 within 5 % of the figures before the change, or better"):
OWL runs with settings A (the defaults unless ``-a`` is given) and with settings B (``-b``)
over every case of the ``owl_bench`` profile and every render seed, and each of the four
figures of B is divided by A's. Only OWL runs (no baselines: those are ``owl_bench``'s
job), so four seeds of the 24 cases take a fraction of one ``owl_bench`` run; the frames
come from, and go to, the bench's frame cache.

A figure of one seed moves by 5 to 40 % from seed to seed, so each case pools the frames
(heading) and points (r/|t|) of all seeds, as ``owl_bench --seeds`` does, and also reports
the spread of the per-seed log ratios: a ratio beyond the tolerance is counted as worse
only when it is also more than two standard errors of the seed-to-seed ratio away from 1
("worse"); beyond the tolerance but within the noise it is "worse?" (more seeds decide).
CPU ms a frame of both settings, each case's A and B run back to back on the same frames,
one thread.

    python -m owl_ros.tools.compare --seeds 4 -b tracker_lk_window_px:=13
    python -m owl_ros.tools.compare --cases street,cube --seeds 2 --size 1280x720 \
        -b tracker_detect_level:=1
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from bags.cli import OneLineErrorParser, user_cache_dir
from bags.errors import BagError
from owl_core.errors import OwlError
from owl_core.types import ImageFrame
from owl_ros.heap import keep_freed_memory
from owl_ros.threads import one_thread
from owl_ros.tools import bench, cost
from owl_ros.tools.errors import BenchError, EvalError, ToolError
from owl_ros.tools.evaluate import FrameScore, score_frame, summarize

PROG = "python -m owl_ros.tools.compare"
#: The four figures compared, as :func:`owl_ros.tools.evaluate.summarize` names them.
FIGURES = ("heading_deg_median", "heading_deg_p90", "range_rel_median", "range_rel_p90")
#: Default tolerance: a figure of B more than this fraction above A's is worse (issue 16).
TOLERANCE = 0.05


@dataclass
class _Side:
    """One setting's scores and CPU time on one case, over its seeds."""

    scores: list[FrameScore]
    seed_figures: list[dict[str, Any]]
    cpu_s: float = 0.0


def run_owl(profile: bench.Profile, src: bench.Source) -> tuple[list[FrameScore], float]:
    """OWL alone over ``src`` with ``profile``'s engine settings: its frame scores and the
    CPU seconds the engine took (its own ``total`` timing, ``time.process_time``)."""
    engine = bench._source_engine(src, profile, src.readout_s)
    engine.clock = time.process_time
    scores = []
    cpu = 0.0
    for stamp, image, truth in src.frames():
        res = engine.process(ImageFrame(stamp, image))
        cpu += res.timings.get("total", 0.0)
        scores.append(score_frame(bench.owl_estimate(res), truth, src.truth_bias))
    return scores, cpu


def ratio(b: Any, a: Any) -> float | None:
    """b / a of two figures (None when either is missing or a is not positive)."""
    if a is None or b is None or not a > 0:
        return None
    return float(b) / float(a)


def verdict(pooled: float | None, seed_ratios: Sequence[float | None], tolerance: float) -> str:
    """ "worse" when ``pooled`` (B / A over the frames of every seed) exceeds 1 + tolerance
    and the per-seed log ratios put it more than two standard errors above 1; "worse?" when
    it exceeds the tolerance within that noise (or with one seed); "better" likewise below
    1 - tolerance (and two standard errors); "same" otherwise, "n/a" without a figure."""
    if pooled is None:
        return "n/a"
    logs = np.log([r for r in seed_ratios if r is not None and r > 0])
    if logs.size >= 2:
        se = float(np.std(logs, ddof=1) / math.sqrt(logs.size))
        beyond = abs(math.log(pooled)) > 2.0 * se
    else:
        beyond = False
    if pooled > 1.0 + tolerance:
        return "worse" if beyond else "worse?"
    if pooled < 1.0 - tolerance:
        return "better" if beyond else "better?"
    return "same"


def compare(
    profile_a: bench.Profile,
    profile_b: bench.Profile,
    cache: Path | None,
    tolerance: float = TOLERANCE,
    log: Callable[[str], None] = lambda s: None,
) -> dict[str, Any]:
    """Run both settings over every case and seed of ``profile_a`` (whose cases, sizes and
    seeds ``profile_b`` shares); returns the JSON object: settings, tolerance, cases (per
    case: the figures of A and B, each figure's pooled ratio, per-seed ratios and verdict,
    and CPU ms a frame of both), and a summary (the number of worse / better figures, the
    geometric mean of every ratio, CPU ms a frame over all frames)."""
    rows = []
    totals = {"a": [0.0, 0], "b": [0.0, 0]}
    for i, case in enumerate(profile_a.cases, start=1):
        sides = {"a": _Side([], []), "b": _Side([], [])}
        seeds = (0,) if case.bag else profile_a.seeds
        has_mask = False
        for seed in seeds:
            log(f"[{i}/{len(profile_a.cases)}] {case.label} seed {seed}")
            if case.bag:
                src = bench.bag_source(case.bag)
            else:
                sim = bench._sim(case, profile_a, seed)
                src = bench.sim_source(case, bench.load_frames(sim, cache, log, case), sim)
            has_mask = src.has_mask
            for key, profile in (("a", profile_a), ("b", profile_b)):
                scores, cpu = run_owl(profile, src)
                side = sides[key]
                side.scores.extend(scores)
                side.seed_figures.append(summarize(scores, src.has_mask))
                side.cpu_s += cpu
        pooled = {k: summarize(s.scores, has_mask) for k, s in sides.items()}
        figures = {}
        for name in FIGURES:
            per_seed = [
                ratio(b.get(name), a.get(name))
                for a, b in zip(sides["a"].seed_figures, sides["b"].seed_figures, strict=True)
            ]
            r = ratio(pooled["b"].get(name), pooled["a"].get(name))
            figures[name] = {
                "a": pooled["a"].get(name),
                "b": pooled["b"].get(name),
                "ratio": r,
                "seed_ratios": per_seed,
                "verdict": verdict(r, per_seed, tolerance),
            }
        for key, side in sides.items():
            totals[key][0] += side.cpu_s
            totals[key][1] += len(side.scores)
        rows.append(
            {
                "case": case.label,
                "seeds": len(seeds),
                "figures": figures,
                "cpu_ms_per_frame": {
                    k: 1e3 * s.cpu_s / max(len(s.scores), 1) for k, s in sides.items()
                },
            }
        )
    ratios = [f["ratio"] for r in rows for f in r["figures"].values() if f["ratio"]]
    verdicts = [f["verdict"] for r in rows for f in r["figures"].values()]
    return {
        "a": dict(profile_a.engine_params),
        "b": dict(profile_b.engine_params),
        "features": profile_a.features,
        "image_size": f"{profile_a.width}x{profile_a.height}",
        "seeds": list(profile_a.seeds),
        "tolerance": tolerance,
        "cases": rows,
        "summary": {
            "figures": len(verdicts),
            **{v: verdicts.count(v) for v in ("worse", "worse?", "better", "better?", "same")},
            "geometric_mean_ratio": float(np.exp(np.mean(np.log(ratios)))) if ratios else None,
            "cpu_ms_per_frame": {k: 1e3 * t[0] / max(t[1], 1) for k, t in totals.items()},
        },
    }


def _fig(x: Any, scale: float = 1.0, fmt: str = ".3f") -> str:
    return "-" if x is None else format(x * scale, fmt)


def report_lines(doc: dict[str, Any]) -> list[str]:
    """The comparison as text: one row per case, A -> B (ratio, verdict) per figure."""

    def setting(d: dict[str, Any]) -> str:
        return " ".join(f"{k}:={v}" for k, v in d.items()) or "the defaults"

    out = [
        f"A: {setting(doc['a'])}",
        f"B: {setting(doc['b'])}",
        f"{doc['image_size']}, {doc['features']} features, seeds {doc['seeds']}; a figure "
        f"of B more than {100 * doc['tolerance']:g} % above A's is worse",
        "",
        "case | heading median, deg | heading p90, deg | r/|t| median, % | r/|t| p90, % | "
        "CPU ms/frame A, B",
        "---|---|---|---|---|---",
    ]
    for row in doc["cases"]:
        cells = []
        for name in FIGURES:
            f = row["figures"][name]
            scale, fmt = (100.0, ".2f") if name.startswith("range") else (1.0, ".3f")
            mark = "" if f["verdict"] in ("same", "n/a") else f" {f['verdict']}"
            cells.append(
                f"{_fig(f['a'], scale, fmt)} -> {_fig(f['b'], scale, fmt)} "
                f"(x{_fig(f['ratio'], 1.0, '.2f')}{mark})"
            )
        cpu = row["cpu_ms_per_frame"]
        out.append(f"{row['case']} | " + " | ".join(cells) + f" | {cpu['a']:.1f}, {cpu['b']:.1f}")
    s = doc["summary"]
    out += [
        "",
        f"{s['figures']} figures: {s['worse']} worse, {s['worse?']} worse within the seed "
        f"noise, {s['better']} better, {s['better?']} better within the noise, {s['same']} "
        f"within {100 * doc['tolerance']:g} %; geometric mean of the ratios "
        f"{_fig(s['geometric_mean_ratio'], 1.0, '.3f')}; CPU ms a frame "
        f"{s['cpu_ms_per_frame']['a']:.1f} (A), {s['cpu_ms_per_frame']['b']:.1f} (B)",
    ]
    return out


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    p = OneLineErrorParser(
        prog=PROG,
        description="OWL with settings A and B on the same frames: per case, the heading "
        "median and p90 and r/|t| median and p90 of B against A's, over render seeds.",
    )
    p.add_argument(
        "-a", action="append", default=[], metavar="NAME:=VALUE",
        help="an engine setting of A (default: the node's defaults); repeatable",
    )  # fmt: skip
    p.add_argument(
        "-b", action="append", default=[], metavar="NAME:=VALUE",
        help="an engine setting of B; repeatable",
    )  # fmt: skip
    p.add_argument("--quick", action="store_true", help="owl_bench --quick's cases and size")
    p.add_argument("--cases", default=None, help="comma-separated cases (owl_bench labels)")
    p.add_argument("--bag", action="append", default=[], help="a bag with ground truth")
    p.add_argument("--seeds", type=int, default=4, help="render seeds per case (default 4)")
    p.add_argument("--seconds", type=float, default=None, help="override seconds per case")
    p.add_argument("--features", type=int, default=None, help="features requested, both")
    p.add_argument(
        "--size", type=cost.image_size, default=None, metavar="WxH",
        help="image size of the rendered cases (default the profile's: 640x480, --quick 320x240)",
    )  # fmt: skip
    p.add_argument("--tolerance", type=float, default=TOLERANCE, help="fraction (default 0.05)")
    p.add_argument("--cache-dir", default=None, help="owl_bench's frame cache")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit status (2 with one line on bad input)."""
    one_thread()
    keep_freed_memory()
    args = build_parser().parse_args(argv)
    try:
        profile = bench.chosen_profile(
            bench.QUICK if args.quick else bench.FULL,
            args.cases,
            args.bag,
            args.seconds,
            args.seeds,
            args.features,
        )
        if args.size is not None:
            profile = replace(profile, width=args.size[0], height=args.size[1])
        if not (math.isfinite(args.tolerance) and args.tolerance >= 0):
            raise BenchError(f"--tolerance must be >= 0, got {args.tolerance}")
        if not args.b:
            raise BenchError("give B's settings with -b NAME:=VALUE (A: the defaults or -a)")
        profile_a = replace(profile, engine_params=bench.parse_engine_params(args.a))
        profile_b = replace(profile, engine_params=bench.parse_engine_params(args.b))

        def log(text: str) -> None:
            if not args.quiet:
                print(f"{PROG}: {text}", file=sys.stderr, flush=True)

        cache = Path(args.cache_dir or user_cache_dir("frames"))
        doc = compare(profile_a, profile_b, cache, args.tolerance, log)
    except (ToolError, BagError, OwlError, OSError, EvalError) as err:
        print(f"{PROG}: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    print(json.dumps(doc) if args.json else "\n".join(report_lines(doc)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
