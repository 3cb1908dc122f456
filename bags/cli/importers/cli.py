"""owl_import DATASET OUT_BAG: an EuRoC/TUM-VI (ASL) or KITTI odometry folder -> a bag.

The bag has the synthetic bags' topics, frames and QoS (``/camera/image_raw``,
``/camera/camera_info``, ``/imu/data``, ``/tf_static``, ``/ground_truth/twist``,
``/ground_truth/gyro_bias``), so ``owl_process``, ``owl_replay`` and ``owl_eval`` take it
unchanged. The camera-to-IMU rotation is printed on stdout as the node parameter line
``camera_to_imu_rotation_xyzw: [x, y, z, w]``; progress and the summary go to stderr.

A malformed folder (missing file, wrong column count, unreadable image, stamps out of
order) gets one line naming the file and the problem, exit status 1, and no bag: the bag
is built in a hidden directory beside OUT_BAG and renamed at the end. The output may not
be the input folder, inside it or contain it (bags.io.check_output, shared by every tool).

Run ``python -m bags.cli.importers.cli --help`` (console script ``owl_import``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from bags.cli import OneLineErrorParser
from bags.cli.importers.asl import is_asl, read_asl
from bags.cli.importers.common import (
    PROG,
    Dataset,
    DatasetError,
    ImportOptions,
    ImportSummary,
    default_progress,
    write_dataset,
)
from bags.cli.importers.kitti import is_kitti, read_kitti
from bags.errors import BagError, OutputOverlapError
from bags.io import check_output
from owl_core.errors import OwlError


def _quat(text: str) -> tuple[float, float, float, float]:
    try:
        q = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z,W numbers, got {text!r}") from None
    if len(q) != 4 or not any(q):
        raise argparse.ArgumentTypeError(f"expected 4 numbers X,Y,Z,W (not all 0), got {text!r}")
    return (q[0], q[1], q[2], q[3])


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    p = OneLineErrorParser(
        prog=PROG,
        description="Import an ASL (EuRoC MAV, TUM-VI) or KITTI odometry folder into a rosbag2 "
        "MCAP bag in the layout of the synthetic bags (images, camera_info, IMU, /tf_static, "
        "ground-truth twist and gyro bias when the folder has them).",
    )
    p.add_argument("dataset", help="ASL folder (holding mav0/) or KITTI sequence folder")
    p.add_argument("out_bag", help="output rosbag2 directory (must not exist)")
    p.add_argument("--layout", choices=("auto", "asl", "kitti"), default="auto")
    p.add_argument("--start", type=float, default=0.0, help="skip the first S seconds")
    p.add_argument("--seconds", type=float, default=None, help="keep S seconds (default: all)")
    p.add_argument("--every", type=int, default=1, help="keep every Nth image (default 1)")
    p.add_argument(
        "--scale", type=float, default=1.0, help="resize images by F (intrinsics adjusted)"
    )
    p.add_argument("--no-ground-truth", action="store_true", help="do not import poses/bias")
    p.add_argument("--colour", action="store_true", help="KITTI: image_2 (colour, to grey)")
    p.add_argument("--poses", type=Path, default=None, help="KITTI: poses file")
    p.add_argument("--imu", type=Path, default=None, help="KITTI: IMU CSV (see the README)")
    p.add_argument(
        "--camera-to-imu-rotation-xyzw",
        type=_quat,
        default=None,
        metavar="X,Y,Z,W",
        help="KITTI: rotation camera -> IMU frame of the IMU CSV (default identity)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    return p


def check_paths(dataset: Path, out: Path) -> None:
    """DatasetError when the input is missing or the output is the input, inside it or
    contains it (the check every writing tool shares: bags.io.check_output)."""
    if not dataset.is_dir():
        raise DatasetError(f"{dataset}: dataset folder does not exist")
    try:
        check_output(out, [dataset], overwrite=True)
    except OutputOverlapError as err:
        raise DatasetError(str(err)) from None


def read_dataset(args: argparse.Namespace) -> Dataset:
    """The Dataset of the parsed arguments (layout detected unless given)."""
    root = Path(args.dataset)
    layout = args.layout
    if layout == "auto":
        if is_asl(root):
            layout = "asl"
        elif is_kitti(root):
            layout = "kitti"
        else:
            msg = f"{root}: neither an ASL folder (mav0/cam0) nor KITTI (times.txt, calib.txt)"
            raise DatasetError(msg)
    if layout == "asl":
        return read_asl(root, ground_truth=not args.no_ground_truth)
    return read_kitti(
        root,
        colour=args.colour,
        poses=args.poses,
        imu=args.imu,
        camera_to_imu_xyzw=args.camera_to_imu_rotation_xyzw,
        ground_truth=not args.no_ground_truth,
    )


def run(argv: Sequence[str] | None = None) -> ImportSummary:
    """Parse, read, write; raises DatasetError/BagError (for tests and tools)."""
    args = build_parser().parse_args(argv)
    return _run(args)


def _run(args: argparse.Namespace) -> ImportSummary:
    check_paths(Path(args.dataset), Path(args.out_bag))
    opts = ImportOptions(
        start_s=args.start,
        seconds=args.seconds,
        every=args.every,
        scale=args.scale,
        overwrite=args.overwrite,
    )
    ds = read_dataset(args)
    return write_dataset(ds, args.out_bag, opts, default_progress(args.quiet))


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``owl_import``; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as done:  # --help, or a usage error already printed on one line
        return done.code if isinstance(done.code, int) else 2
    try:
        summary = _run(args)
    except (BagError, OwlError) as err:
        print(f"{PROG}: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted, nothing written", file=sys.stderr)
        return 130
    q = summary.camera_to_imu_rotation_xyzw
    print(f"camera_to_imu_rotation_xyzw: [{q[0]:.9f}, {q[1]:.9f}, {q[2]:.9f}, {q[3]:.9f}]")
    if not args.quiet:
        cam = summary.camera
        print(
            f"{PROG}: wrote {summary.out_path}: {summary.frames} frames {cam.width}x{cam.height}, "
            f"{summary.imu_samples} IMU samples, ground-truth twist on {summary.twist_frames} "
            f"and gyro bias on {summary.bias_frames} frames, in {summary.elapsed_s:.1f} s "
            f"({summary.frames / max(summary.elapsed_s, 1e-9):.1f} frames/s)",
            file=sys.stderr,
        )
        text = ",".join(f"{v:.9f}" for v in q)
        print(
            f"{PROG}: the rotation is in the bag's /tf_static (owl_process takes it from there); "
            f'for a live owl_node: -p "camera_to_imu_rotation_xyzw:=[{text}]"',
            file=sys.stderr,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
