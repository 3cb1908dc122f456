"""OWL's heading against the OpenCV 5-point two-view heading on the same tracks of a bag.

For recordings without ground truth (the handheld walk): the engine runs over the bag's
images and gyro with the node's default parameters (the extrinsic from ``/tf_static``);
on each frame's very tracks (``OwlEngine.last_tracks``) OpenCV's 5-point essential matrix
+ recoverPose (:mod:`owl_core.baseline`) pairs the current frame with the one ``gap``
frames earlier. Per frame where both give a heading, the angle between them (degrees) is
the disagreement; its median and 90th percentile are reported per gap. As a yardstick of
the two-view estimates' own scatter on the same frames, the gyro-aided two-view heading
(derotated with the gyro less the bias OWL has estimated by then, translation only) is
compared with the 5-point one too.

On the frames where all three give a heading the two disagreements are paired: the excess
``median(OWL vs 5-point) - median(gyro-aided vs 5-point)`` and its 90 % interval from a
moving-block bootstrap over frames (blocks of :data:`BLOCK_FRAMES`, longer than the tracks
and the gaps, so that blocks are close to independent; seeded, so the interval is
reproducible). An interval that contains 0 says that on this recording OWL's agreement with
the 5-point heading cannot be told from a second two-view estimator's.

``python -m owl_ros.tools.agreement BAG [--gap 1 --gap 2 --gap 4] [--json]``
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from bags.cli import OneLineErrorParser
from bags.errors import BagError
from bags.io import BagReader
from owl_ros.tools.evaluate import heading_error_deg

PROG = "owl_agreement"
#: gyro samples fed ahead of each image, ns (what an IMU arriving with the image gives)
LEAD_NS = 50_000_000
#: frames per bootstrap block (0.6 s at the walk's 17 Hz; its tracks live 2 to 10 frames)
BLOCK_FRAMES = 10
#: bootstrap resamples
RESAMPLES = 2000


def median_excess(
    a: npt.ArrayLike, b: npt.ArrayLike, block: int = BLOCK_FRAMES, resamples: int = RESAMPLES
) -> tuple[float, float, float]:
    """Paired difference of medians with a moving-block bootstrap 90 % interval.

    Args:
        a, b: (N,) paired per-frame values in frame order (here angles, degrees).
        block: frames per block (>= 1); the blocks are drawn with replacement from the N -
            block + 1 overlapping ones and concatenated to N values.
        resamples: bootstrap resamples (>= 1).

    Returns:
        (median(a) - median(b), 5th percentile, 95th percentile of the resampled
        differences); NaNs when N == 0.
    """
    x = np.asarray(a, dtype=np.float64)
    y = np.asarray(b, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f"paired values need equal 1-D shapes, got {x.shape} and {y.shape}")
    n = x.size
    if n == 0:
        return math.nan, math.nan, math.nan
    block = max(1, min(int(block), n))
    rng = np.random.default_rng(0)
    starts = rng.integers(0, n - block + 1, size=(resamples, -(-n // block)))
    idx = (starts[:, :, None] + np.arange(block)).reshape(resamples, -1)[:, :n]
    diff = np.median(x[idx], axis=1) - np.median(y[idx], axis=1)
    lo, hi = np.percentile(diff, [5.0, 95.0])
    return float(np.median(x) - np.median(y)), float(lo), float(hi)


def heading_agreement(
    bag_path: str | Path,
    gaps: Sequence[int] = (4,),
    image_topic: str = "/camera/image_raw",
    info_topic: str = "/camera/camera_info",
    imu_topic: str = "/imu/data",
    params: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Run the engine and the 5-point baseline over a bag (see the module docstring).

    Returns:
        {"frames", "owl_headings", "final_gyro_bias" (IMU frame, rad/s), "per_gap": {gap:
        {"baseline_headings", "both", "median_deg", "p90_deg", "angles_deg": [...],
        "gyro_vs_5pt_median_deg", "paired": {"frames", "owl_vs_5pt_median_deg" (on the
        frames where the gyro-aided heading exists too), "excess_deg", "excess_90_deg":
        [lo, hi]}}}}.
    """
    from rclpy.serialization import deserialize_message

    from msg_adapters.camera_info import camera_info_to_model
    from msg_adapters.image import image_to_frame
    from msg_adapters.imu import imus_to_gyro
    from msg_adapters.msgtypes import message_class
    from owl_core.baseline import BaselineOptions, TwoViewBaseline
    from owl_core.engine import OwlEngine
    from owl_core.types import GyroSamples
    from owl_ros.params import build_options
    from owl_ros.process import tf_rotation

    with BagReader(bag_path) as bag:
        transforms: list[Any] = []
        if "/tf_static" in bag.topics:
            for raw in bag.messages(["/tf_static"]):
                transforms.extend(bag.deserialize(raw).transforms)
        imu_cls = message_class("sensor_msgs/msg/Imu")
        imus = [deserialize_message(r.data, imu_cls) for r in bag.messages([imu_topic])]
        info = deserialize_message(
            next(iter(bag.messages([info_topic]))).data,
            message_class("sensor_msgs/msg/CameraInfo"),
        )
        camera = camera_info_to_model(info)
        imu_frame = imus[0].header.frame_id if imus else None
        rotation = tf_rotation(transforms, imu_frame, info.header.frame_id)
        values = {} if rotation is None else {"camera_to_imu_rotation_xyzw": list(rotation)}
        values.update(params or {})
        engine = OwlEngine(camera, build_options(values).engine)
        gyro = imus_to_gyro(imus)
        fed = 0
        baselines = {
            g: TwoViewBaseline(camera, BaselineOptions(method="essential", gap_frames=g))
            for g in gaps
        }
        buffer = engine.gyro

        def rotation(t0: int, t1: int) -> Any:
            # the bias OWL has estimated by then: the stronger yardstick (the raw gyro
            # leaves a real gyro's bias in the derotation)
            if not buffer.covers(t0, t1):
                return None
            return buffer.relative_rotation(t0, t1, engine.gyro_bias)

        gyro_baselines = {
            g: TwoViewBaseline(camera, BaselineOptions(method="gyro", gap_frames=g), rotation)
            for g in gaps
        }
        angles: dict[int, list[float]] = {g: [] for g in gaps}
        two_view: dict[int, list[float]] = {g: [] for g in gaps}
        paired: dict[int, list[float]] = {g: [] for g in gaps}
        base_count = dict.fromkeys(gaps, 0)
        frames = owl_count = 0
        img_cls = message_class("sensor_msgs/msg/Image")
        for raw in bag.messages([image_topic]):
            frame = image_to_frame(deserialize_message(raw.data, img_cls))
            # feed the gyro as the node gets it: up to the image (+ the IMU's lead), not all
            # at once (the gyro buffer keeps a bounded window)
            upto = int(np.searchsorted(gyro.stamp_ns, frame.stamp_ns + LEAD_NS, side="right"))
            if upto > fed:
                engine.add_gyro(
                    GyroSamples(gyro.stamp_ns[fed:upto], gyro.angular_velocity[fed:upto])
                )
                fed = upto
            res = engine.process(frame)
            frames += 1
            owl_count += res.heading is not None
            tracks = engine.last_tracks
            if tracks is None:
                continue
            for g, base in baselines.items():
                out = base.process(tracks)
                if out.heading is None:
                    continue
                base_count[g] += 1
                if res.heading is not None:
                    angles[g].append(float(heading_error_deg(res.heading, out.heading)))
                    other = gyro_baselines[g].process(tracks)
                    if other.heading is not None:
                        two_view[g].append(float(heading_error_deg(out.heading, other.heading)))
                        paired[g].append(angles[g][-1])
    per_gap = {}
    for g in gaps:
        a = np.asarray(angles[g])
        b = np.asarray(two_view[g])
        p = np.asarray(paired[g])
        excess, lo, hi = median_excess(p, b)
        per_gap[g] = {
            "gyro_vs_5pt_median_deg": float(np.median(b)) if b.size else None,
            "baseline_headings": base_count[g],
            "both": int(a.size),
            "median_deg": float(np.median(a)) if a.size else None,
            "p90_deg": float(np.percentile(a, 90)) if a.size else None,
            "angles_deg": a.tolist(),
            "paired": {
                "frames": int(p.size),
                "owl_vs_5pt_median_deg": float(np.median(p)) if p.size else None,
                "excess_deg": excess,
                "excess_90_deg": [lo, hi],
            },
        }
    return {
        "frames": frames,
        "owl_headings": owl_count,
        "final_gyro_bias": [float(v) for v in engine.gyro_bias],
        "per_gap": per_gap,
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    p = OneLineErrorParser(prog=PROG, description=__doc__.splitlines()[0])
    p.add_argument("bag", help="bag with images, camera_info, IMU (e.g. from owl_import)")
    p.add_argument("--gap", type=int, action="append", default=None, help="baseline gap(s)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("-p", "--param", action="append", default=[], metavar="NAME:=VALUE")
    args = p.parse_args(argv)
    try:
        from owl_ros.params import parse_assignment

        params = dict(parse_assignment(item) for item in args.param)
        out = heading_agreement(args.bag, tuple(args.gap or (1, 2, 4)), params=params)
    except (BagError, StopIteration, ValueError) as err:
        print(f"{PROG}: error: {' '.join(str(err).split()) or 'empty topic'}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(out))
        return 0
    print(
        f"{PROG}: {args.bag}: {out['frames']} frames, OWL headings on {out['owl_headings']}, "
        f"final gyro bias estimate {np.round(out['final_gyro_bias'], 4).tolist()} rad/s"
    )
    for g, r in out["per_gap"].items():
        med, p90 = r["median_deg"], r["p90_deg"]
        text = "n/a" if med is None else f"{med:.2f} / {p90:.2f} deg"
        yard = r["gyro_vs_5pt_median_deg"]
        print(
            f"  5-point gap {g}: headings on {r['baseline_headings']}, both on {r['both']}, "
            f"OWL vs 5-point median / p90 {text}; gyro-aided two-view vs 5-point median "
            + ("n/a" if yard is None else f"{yard:.2f} deg")
        )
        q = r["paired"]
        if q["frames"]:
            lo, hi = q["excess_90_deg"]
            print(
                f"    on the {q['frames']} frames with all three: OWL's excess disagreement "
                f"{q['excess_deg']:+.2f} deg, 90 % interval [{lo:+.2f}, {hi:+.2f}] deg"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
