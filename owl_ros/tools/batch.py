"""owl_batch BAG_OR_FOLDER... -o OUT_DIR: owl_process + owl_eval over many bags, on Ray.

Each bag is one Ray task (``num_cpus=1``, one OpenCV and BLAS thread): ``process_bag`` into
``OUT_DIR/<bag name>``, then ``evaluate`` against the bag itself when it carries
``/ground_truth/twist`` (synthetic bags, imported datasets with poses); a bag without
ground truth is reported with its processing counts and "not scored: no ground truth". A
task that raises is retried once (``max_retries=1, retry_exceptions=True``); if it fails
again its row says why and the other bags are still scored.

Ray: an embedded local instance by default (``--num-cpus``, default all cores), stopped at
the end with every process it started; ``--address HOST:PORT`` (or ``auto``) joins an
existing cluster instead (every node needs this package installed, as ``pip install .``
gives it). Output: one text table (per bag, then pooled over every scored frame of every
bag with owl_eval's own ``summarize``) and, with ``--json FILE``, one JSON object
``{"bags": [...], "pooled": {...}, "wall_s": ...}``. Every output path is checked before
Ray starts: OUT_DIR must be a directory (or not exist yet), no result bag may lie inside an
input, and FILE must not exist, be an input or lie inside one, be or hold a result bag, or
be in a missing directory; FILE is written all at once (temporary file + ``os.replace``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bags.cli import OneLineErrorParser
from bags.errors import BagError, OutputOverlapError
from bags.io import check_output, write_text_atomic
from owl_ros.tools.errors import BatchError

PROG = "owl_batch"
ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@dataclass
class BagResult:
    """One bag's outcome (JSON-ready through ``as_dict``)."""

    bag: str
    ok: bool
    error: str = ""
    attempts: int = 1
    frames: int = 0
    frames_with_points: int = 0
    frames_with_heading: int = 0
    final_gyro_bias: list[float] | None = None
    scored: bool = False
    not_scored: str = ""
    summary: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0
    scores: list[Any] = field(default_factory=list)
    has_mask: bool = False

    def as_dict(self) -> dict[str, Any]:
        """Everything but the per-frame score objects."""
        out = {k: v for k, v in self.__dict__.items() if k != "scores"}
        return out


def find_bags(inputs: Sequence[str]) -> list[Path]:
    """Bags named or found one level inside the given folders (sorted, no duplicates).

    A bag is a rosbag2 directory (metadata.yaml or .mcap files) or a bare .mcap file.
    """

    def is_bag(p: Path) -> bool:
        return (p.is_dir() and ((p / "metadata.yaml").exists() or any(p.glob("*.mcap")))) or (
            p.is_file() and p.suffix == ".mcap"
        )

    out: list[Path] = []
    for text in inputs:
        p = Path(text)
        if not p.exists():
            raise BatchError(f"{p}: no such bag or folder")
        if is_bag(p):
            out.append(p)
        elif p.is_dir():
            found = sorted(c for c in p.iterdir() if is_bag(c))
            if not found:
                raise BatchError(f"{p}: no bags in this folder")
            out.extend(found)
        else:
            raise BatchError(f"{p}: not a bag (rosbag2 directory or .mcap file)")
    seen: set[Path] = set()
    unique = [b for b in out if not (b.resolve() in seen or seen.add(b.resolve()))]  # type: ignore[func-returns-value]
    names = [b.name for b in unique]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise BatchError(f"two bags are called {dup!r}: their results would collide in OUT_DIR")
    return unique


def run_one(bag: str, out: str, params: dict[str, Any]) -> BagResult:
    """owl_process + owl_eval of one bag (what a Ray task runs; also usable directly).

    Raises whatever processing raises (BagError, ProcessError, ...) after removing the
    partial result, so that a retry starts clean.
    """
    import cv2

    from bags.io import BagReader
    from owl_ros.params import build_options
    from owl_ros.process import ProcessOptions, process_bag
    from owl_ros.tools.evaluate import TRUTH_TOPICS, evaluate, read_estimates, truth_has_mask

    cv2.setNumThreads(1)
    t0 = time.monotonic()
    out_path = Path(out)
    if out_path.exists():  # a previous attempt of this task
        shutil.rmtree(out_path)
    try:
        summary = process_bag(bag, out_path, ProcessOptions(node=build_options(params)))
        if summary.damage is not None:
            raise BatchError(summary.damage)
        est = read_estimates(out_path)
        last = est[max(est)] if est else None
        res = BagResult(
            bag=bag,
            ok=True,
            frames=summary.frames_processed,
            frames_with_points=summary.frames_with_points,
            frames_with_heading=len(summary.headings),
            final_gyro_bias=None
            if last is None or last.gyro_bias is None
            else [float(v) for v in last.gyro_bias],
        )
        with BagReader(bag) as reader:
            has_truth = TRUTH_TOPICS["twist"] in reader.topics
        if has_truth:
            ev = evaluate(out_path, bag)
            res.scored, res.summary, res.notes = True, ev.summary, ev.notes
            res.scores, res.has_mask = ev.frames, truth_has_mask(bag)
        else:
            res.not_scored = "not scored: no ground truth (no /ground_truth/twist)"
    except BaseException:
        shutil.rmtree(out_path, ignore_errors=True)
        raise
    res.seconds = time.monotonic() - t0
    return res


def check_outputs(bags: Sequence[Path], out_dir: Path, json_path: Path | None) -> None:
    """Refuse the output paths before any work (owl_batch has no overwrite option).

    ``out_dir`` must be a directory or not exist; no result bag ``out_dir/<bag name>`` may
    exist or lie inside an input bag; ``json_path`` must not exist, must not be an input,
    lie inside one or contain one, must not be or contain a result bag, and its directory
    must exist.

    Raises:
        BatchError: one of the above, naming the path.
        OutputOverlapError: a result bag or ``json_path`` is, is inside or contains an input.
    """
    if out_dir.exists() and not out_dir.is_dir():
        raise BatchError(f"--out-dir {out_dir} exists and is not a directory")
    results = [out_dir / b.name for b in bags]
    for res in results:
        if res.exists() or res.is_symlink():
            raise BatchError(f"{res} exists: choose another --out-dir")
        check_output(res, bags, overwrite=True)
    if json_path is None:
        return
    check_output(json_path, bags, overwrite=True)
    try:
        check_output(json_path, results, overwrite=True)
    except OutputOverlapError:
        raise BatchError(
            f"--json {json_path}: the result bags are written there ({out_dir}/<bag name>): "
            "choose another file"
        ) from None
    if json_path.exists() or json_path.is_symlink():
        raise BatchError(f"--json {json_path} exists: choose another file (it is not replaced)")
    if not json_path.parent.is_dir():
        raise BatchError(f"--json {json_path}: directory {json_path.parent} does not exist")


def _one_line(err: BaseException) -> str:
    cause = getattr(err, "cause", None)  # ray.exceptions.RayTaskError wraps the real one
    base = cause if isinstance(cause, BaseException) else err
    text = " ".join(str(base).split()) or type(base).__name__
    return f"{type(base).__name__}: {text}"


def run_batch(
    bags: Sequence[Path],
    out_dir: Path,
    *,
    params: dict[str, Any] | None = None,
    address: str | None = None,
    num_cpus: int | None = None,
    progress: Any = None,
) -> dict[str, Any]:
    """Run every bag as a Ray task; returns {"bags", "pooled", "wall_s", "ray"}.

    ``address`` None starts a local Ray (``num_cpus``) and shuts it down at the end.
    """
    import ray

    from owl_ros.tools.evaluate import summarize

    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    env = {"env_vars": dict(ONE_THREAD)}
    if address is None:
        ray.init(
            num_cpus=num_cpus,
            include_dashboard=False,
            runtime_env=env,
            logging_level="ERROR",
            log_to_driver=False,
        )
    else:
        ray.init(address=address, runtime_env=env, logging_level="ERROR", log_to_driver=False)
    try:
        task = ray.remote(num_cpus=1, max_retries=1, retry_exceptions=True)(run_one)
        pending = {task.remote(str(b), str(out_dir / b.name), dict(params or {})): b for b in bags}
        results: dict[Path, BagResult] = {}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            ref = done[0]
            bag = pending.pop(ref)
            try:
                results[bag] = ray.get(ref)
            except Exception as err:  # failed twice: report, keep the others going
                results[bag] = BagResult(bag=str(bag), ok=False, error=_one_line(err), attempts=2)
            if progress is not None:
                r = results[bag]
                state = "ok" if r.ok else "FAILED"
                print(
                    f"{PROG}: {len(results)}/{len(bags)} {bag.name}: {state}",
                    file=progress,
                    flush=True,
                )
        cluster = {"address": address or "local", "cpus": ray.cluster_resources().get("CPU")}
    finally:
        ray.shutdown()
    ordered = [results[b] for b in bags]
    scored = [r for r in ordered if r.ok and r.scored]
    pooled = (
        summarize([s for r in scored for s in r.scores], any(r.has_mask for r in scored))
        if scored
        else {}
    )
    if scored:
        pooled["range_scored"] = any(r.summary.get("range_scored", True) for r in scored)
        pooled["bags"] = len(scored)
        finals = [
            r.summary["bias_error_final_rad_s"]
            for r in scored
            if r.summary.get("bias_error_final_rad_s") is not None
        ]
        pooled["bias_scored"] = bool(finals)
        pooled["bias_error_final_median_rad_s"] = statistics.median(finals) if finals else None
    return {
        "bags": [r.as_dict() for r in ordered],
        "pooled": pooled,
        "wall_s": time.monotonic() - t0,
        "ray": cluster,
    }


def _f(value: Any, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return format(value, fmt)


def table_lines(report: dict[str, Any]) -> list[str]:
    """The report as a text table: one row per bag, then the pooled row."""
    head = (
        f"{'bag':<24} {'status':<7} {'frames':>6} {'points':>6} {'heading':>7} "
        f"{'head med/p90 deg':>17} {'r/|t| med':>10} {'bias err':>9} {'s':>6}"
    )
    lines = [head]  # bias err: rad/s, final per bag; pooled: median of the bags' finals

    def row(
        name: str, status: str, r: dict[str, Any], s: dict[str, Any], pooled_row: bool = False
    ) -> str:
        if s:
            med = f"{_f(s.get('heading_deg_median'), '.2f')}/{_f(s.get('heading_deg_p90'), '.2f')}"
            rng = (
                _f(s.get("range_rel_median"), ".1%")
                if s.get("range_scored", True)
                else "not scored"
            )
            key = "bias_error_final_median_rad_s" if pooled_row else "bias_error_final_rad_s"
            bias = _f(s.get(key), ".4f") if s.get("bias_scored", True) else "n/a"
        else:
            med, rng, bias = "not scored", "-", "-"
        return (
            f"{name[:24]:<24} {status:<7} {r.get('frames', 0):>6} "
            f"{r.get('frames_with_points', 0):>6} {r.get('frames_with_heading', 0):>7} "
            f"{med:>17} {rng:>10} {bias:>9} {_f(r.get('seconds'), '.1f'):>6}"
        )

    for r in report["bags"]:
        name = Path(r["bag"]).name
        if not r["ok"]:
            lines.append(f"{name[:24]:<24} FAILED  {r['error']}")
            continue
        lines.append(row(name, "ok", r, r["summary"] if r["scored"] else {}))
    pooled = report["pooled"]
    if pooled:
        ok = [r for r in report["bags"] if r["ok"]]
        tot = {
            "frames": sum(r["frames"] for r in ok),
            "frames_with_points": sum(r["frames_with_points"] for r in ok),
            "frames_with_heading": sum(r["frames_with_heading"] for r in ok),
            "seconds": report["wall_s"],
        }
        lines.append(row(f"pooled ({pooled['bags']} scored)", "", tot, pooled, True))
    return lines


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    p = OneLineErrorParser(
        prog=PROG,
        description="owl_process + owl_eval over many bags as Ray tasks (a local Ray by "
        "default, --address to join a cluster); one table per bag and pooled, plus JSON.",
    )
    p.add_argument("inputs", nargs="+", help="bags, or folders holding bags")
    p.add_argument("-o", "--out-dir", required=True, help="folder for the result bags")
    p.add_argument("--address", default=None, help="Ray cluster address (default: local Ray)")
    p.add_argument("--num-cpus", type=int, default=None, help="local Ray CPUs (default: all)")
    p.add_argument("--json", default=None, metavar="FILE", help="write the report as JSON")
    p.add_argument(
        "-p",
        "--param",
        action="append",
        default=[],
        metavar="NAME:=VALUE",
        help="a node parameter for every bag (see config/owl.yaml), repeatable",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``owl_batch``; returns 0, 1 when a bag failed, 2 on bad input."""
    from owl_ros.params import ParameterError, build_options, parse_assignment

    args = build_parser().parse_args(argv)
    try:
        bags = find_bags(args.inputs)
        params: dict[str, Any] = {}
        for item in args.param:
            name, params[name] = parse_assignment(item)
        build_options(params)  # refuse bad values before starting Ray
        out_dir = Path(args.out_dir)
        json_path = Path(args.json) if args.json else None
        check_outputs(bags, out_dir, json_path)
        if args.num_cpus is not None and args.num_cpus < 1:
            raise BatchError(f"--num-cpus must be >= 1, got {args.num_cpus}")
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise BatchError(f"--out-dir {out_dir}: cannot create it ({err.strerror})") from None
    except ParameterError as err:
        print(f"{PROG}: error: {err.lines[0] if err.lines else err}", file=sys.stderr)
        return 2
    except (BatchError, BagError, ValueError) as err:
        print(f"{PROG}: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    for k, v in ONE_THREAD.items():
        os.environ.setdefault(k, v)
    report = run_batch(
        bags,
        out_dir,
        params=params,
        address=args.address,
        num_cpus=args.num_cpus,
        progress=None if args.quiet else sys.stderr,
    )
    for line in table_lines(report):
        print(line)
    print(f"{PROG}: {len(bags)} bags in {report['wall_s']:.1f} s on Ray ({report['ray']})")
    if json_path is not None:
        try:
            if json_path.exists() or json_path.is_symlink():  # appeared during the run
                raise BatchError(f"--json {json_path} appeared during the run: not replaced")
            write_text_atomic(json_path, json.dumps(report, indent=1))
        except (BatchError, OSError) as err:
            print(f"{PROG}: error: {' '.join(str(err).split())}", file=sys.stderr)
            return 1
    return 0 if all(r["ok"] for r in report["bags"]) else 1


if __name__ == "__main__":
    sys.exit(main())
