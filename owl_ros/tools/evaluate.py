"""owl_eval RESULT_BAG --truth TRUTH_BAG: score an OWL result against ground truth.

Metrics (per frame, then pooled over the bag; the same functions score OWL and the
baseline in ``owl_bench``, see :func:`score_frame` and :func:`summarize`):

- **heading error** (degrees): angle between the estimated heading and the true one, the
  normalised camera velocity in the camera optical frame at the image stamp
  (``/ground_truth/twist``). Frames where the camera does not translate
  (``|v| < MIN_SPEED``) have no true heading; a heading there is counted as a false one.
- **range_over_speed relative error**: ``|est - true| / true`` per point, on static
  points only, where ``true = range(u, v) / |v|`` with the range image
  (``/ground_truth/range``, metres along the pixel's ray) sampled at the nearest pixel to
  the point's ``(u, v)``; points on the moving-object mask or the sky are not scored.
- **points per frame** and **coverage**: fraction of the cells of a ``GRID`` over the image
  holding at least one point.
- **moving points**: precision and recall of the ``flags`` MOVING bit (4) against the
  moving mask (``/ground_truth/moving_mask``) sampled at the point, over the points farther
  than ``MASK_MARGIN_PX`` from the mask's edge: a feature whose tracking window (15 px)
  overlaps a moving object's outline is tracked partly with it, so neither label is right
  there (those points are not scored for r/|t| either). The strict figures, every point
  labelled by its own pixel, are kept as ``moving_precision_strict`` / ``_recall_strict``.
- **gyro-bias error** (rad/s, IMU frame): ``|b_est - b_true|``; the estimate comes from the
  result's ``/owl/gyro_bias`` (geometry_msgs/Vector3Stamped, the estimate after each frame,
  matched by image stamp), the truth from the
  truth bag's ``/ground_truth/gyro_bias`` (geometry_msgs/Vector3Stamped, IMU frame, at image
  stamps: ``owl_import`` writes it from EuRoC's ``b_w``), else from its ``owl_make_bag``
  options (``--gyro-bias``; metadata ``custom_data``). A bias random walk
  (``--gyro-bias-walk``) is not recorded in a synthetic bag, so the truth is then only the
  initial bias (the text says so). Without either, the bias is "not scored" (a note).

A truth bag without ``/ground_truth/range`` (an imported real recording) scores headings
and points only: r/|t| is reported as "not scored: no range ground truth" (summary key
``range_scored`` false; the image size then comes from ``/camera/camera_info``).

Result topics: ``/owl/points`` (sensor_msgs/PointCloud2 with at least ``u v
range_over_speed flags``), ``/owl/heading`` and ``/owl/gyro_bias``
(geometry_msgs/Vector3Stamped), matched to the truth by header stamp (= image stamp).
Text for people; ``--json`` prints one object ``{"summary": {...}, "frames": [...]}``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from bags import layout
from bags.cli import OneLineErrorParser
from bags.errors import BagError
from bags.io import BagReader
from owl_ros.tools import eval_checks
from owl_ros.tools.errors import EvalError, ToolError
from owl_ros.topics import DIAGNOSTICS, GYRO_BIAS, HEADING, POINTS, RESULT_TOPICS

PROG = "owl_eval"
FloatArray = npt.NDArray[np.float64]

#: Below this camera speed (m/s) a frame has no true heading.
MIN_SPEED = 1e-3
#: Coverage grid (columns, rows) over the image.
GRID = (16, 12)
MOVING_BIT = 4
#: Points this close to a moving object's outline (pixels; half the tracker's 15 px
#: Lucas-Kanade window) have no clear moving/static truth (see the module docstring).
MASK_MARGIN_PX = 7.0
TRUTH_TOPICS = {role: layout.TOPICS[role][0] for role in ("twist", "range", "mask", "bias")}
CAMERA_INFO_TOPIC = layout.TOPICS["info"][0]
NO_RANGE = "not scored: no range ground truth"
#: Result topics as owl_process writes them, then as a recording may name them.
POINTS_TOPICS = (POINTS.bag, POINTS.name)
HEADING_TOPICS = (HEADING.bag, HEADING.name)
BIAS_TOPICS = (GYRO_BIAS.bag, GYRO_BIAS.name)


# ------------------------------------------------------------------------ records


@dataclass(frozen=True)
class Estimate:
    """One frame of an estimator's output, as scored. N points.

    Attributes:
        stamp_ns: image stamp, ns.
        heading: (3,) translation direction, camera optical frame (any length), or None.
        pixels: (N, 2) float64 (u, v) pixels.
        range_over_speed: (N,) float64 r/|t|, seconds (NaN = no range for the point).
        flags: (N,) uint8 PointFlag bits (4 = MOVING).
        gyro_bias: (3,) bias estimate, IMU frame, rad/s, or None.
    """

    stamp_ns: int
    heading: FloatArray | None
    pixels: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    range_over_speed: FloatArray = field(default_factory=lambda: np.zeros(0))
    flags: npt.NDArray[np.uint8] = field(default_factory=lambda: np.zeros(0, dtype=np.uint8))
    gyro_bias: FloatArray | None = None


@dataclass(frozen=True)
class Truth:
    """Ground truth at one image stamp.

    Attributes:
        stamp_ns: image stamp, ns.
        velocity: (3,) camera velocity relative to the static scene, optical frame, m/s.
        range_m: (H, W) float32 range along each pixel's ray, metres (+inf sky, NaN invalid).
        mask: (H, W) bool, True on independently moving objects, or None (no mask).
    """

    stamp_ns: int
    velocity: FloatArray
    range_m: npt.NDArray[np.float32]
    mask: npt.NDArray[np.bool_] | None = None


@dataclass(frozen=True)
class FrameScore:
    """The metrics of one frame.

    Attributes:
        stamp_ns: image stamp, ns.
        translating: the camera moves (|v| >= MIN_SPEED): the frame has a true heading.
        has_heading: the estimate gave a heading.
        heading_deg: heading error, degrees (NaN without estimate or true heading).
        points: number of output points.
        coverage: fraction of GRID cells with a point, 0..1.
        range_rel: (M,) relative r/|t| errors of the scored static points.
        range_signed: (M,) signed relative errors (est - true) / true.
        range_true: (M,) true r/|t| of those points, seconds.
        range_est: (M,) estimated r/|t| of those points, seconds.
        moving_tp, moving_fp, moving_fn: MOVING flags against the mask (counts), points
            within ``MASK_MARGIN_PX`` of the mask's edge left out.
        moving_flagged: points flagged MOVING.
        moving_strict: (tp, fp, fn) counting every point by the mask at its own pixel.
        bias_error: |b_est - b_true|, rad/s (NaN when either is unknown).
    """

    stamp_ns: int
    translating: bool
    has_heading: bool
    heading_deg: float
    points: int
    coverage: float
    range_rel: FloatArray
    range_signed: FloatArray
    range_true: FloatArray
    range_est: FloatArray
    moving_tp: int
    moving_fp: int
    moving_fn: int
    moving_flagged: int
    bias_error: float
    moving_strict: tuple[int, int, int] = (0, 0, 0)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready per-frame record (point arrays reduced to medians)."""
        return {
            "stamp_ns": self.stamp_ns,
            "translating": self.translating,
            "has_heading": self.has_heading,
            "heading_deg": _num(self.heading_deg),
            "points": self.points,
            "coverage": _num(self.coverage),
            "range_scored": int(self.range_rel.size),
            "range_rel_median": _num(_median(self.range_rel)),
            "moving_tp": self.moving_tp,
            "moving_fp": self.moving_fp,
            "moving_fn": self.moving_fn,
            "bias_error_rad_s": _num(self.bias_error),
        }


# ------------------------------------------------------------------------ metrics


def _num(x: float) -> float | None:
    """JSON number or null (NaN/inf -> None)."""
    return float(x) if x is not None and math.isfinite(x) else None


def _median(x: FloatArray) -> float:
    return float(np.median(x)) if x.size else math.nan


def _p90(x: FloatArray) -> float:
    return float(np.percentile(x, 90)) if x.size else math.nan


def heading_error_deg(estimated: npt.ArrayLike, true: npt.ArrayLike) -> FloatArray:
    """Angle between directions, degrees (atan2 form: exact for small angles too).

    Args:
        estimated: (..., 3) directions (any non-zero length).
        true: (..., 3) directions, broadcastable to ``estimated``.

    Returns:
        (...) float64 degrees in [0, 180]; NaN where either vector is zero or not finite.
    """
    a = np.asarray(estimated, dtype=np.float64)
    b = np.asarray(true, dtype=np.float64)
    if a.shape[-1:] != (3,) or b.shape[-1:] != (3,):
        raise EvalError(f"directions must have shape (..., 3), got {a.shape} and {b.shape}")
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.einsum("...i,...i->...", a, b)
    ok = (np.linalg.norm(a, axis=-1) > 0) & (np.linalg.norm(b, axis=-1) > 0)
    out = np.degrees(np.arctan2(cross, dot))
    return np.where(ok & np.isfinite(out), out, np.nan)


def sample_nearest(image: npt.NDArray[Any], pixels: npt.ArrayLike) -> FloatArray:
    """Values of ``image`` at the nearest pixel centres of ``pixels``.

    Args:
        image: (H, W) array (pixel centres at integer coordinates).
        pixels: (N, 2) (u, v) float pixels.

    Returns:
        (N,) float64; NaN outside the image or for non-finite pixels.
    """
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    h, w = image.shape[:2]
    finite = np.isfinite(px).all(axis=1)
    iu = np.rint(np.where(finite, px[:, 0], -1)).astype(np.int64)
    iv = np.rint(np.where(finite, px[:, 1], -1)).astype(np.int64)
    inside = finite & (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    out = np.full(px.shape[0], np.nan)
    out[inside] = image[iv[inside], iu[inside]]
    return out


def true_range_over_speed(
    pixels: npt.ArrayLike, range_m: npt.NDArray[Any], speed: float
) -> FloatArray:
    """True r/|t| at each pixel: range image at the nearest pixel / camera speed.

    Args:
        pixels: (N, 2) (u, v) pixels.
        range_m: (H, W) metres along each pixel's ray (+inf sky).
        speed: |v|, m/s (> 0).

    Returns:
        (N,) float64 seconds; NaN outside the image, on the sky, or for speed <= 0.
    """
    if not speed > 0:
        return np.full(np.asarray(pixels).reshape(-1, 2).shape[0], np.nan)
    r = sample_nearest(range_m, pixels)
    return np.where(np.isfinite(r) & (r > 0), r / speed, np.nan)


def paired_range_errors(
    ids_a: npt.ArrayLike,
    pixels_a: npt.ArrayLike,
    range_a: npt.ArrayLike,
    ids_b: npt.ArrayLike,
    range_b: npt.ArrayLike,
    truth: Truth,
) -> tuple[FloatArray, FloatArray]:
    """Relative r/|t| errors of two estimators on the same tracks: the track ids both gave
    a finite r/|t| for, static and away from a moving object's outline (as
    :func:`score_frame` scores them), each error against the truth at A's pixel.

    Args:
        ids_a, pixels_a, range_a: (N,) track ids, (N, 2) pixels and (N,) r/|t| (s) of A.
        ids_b, range_b: (M,) track ids and (M,) r/|t| (s) of B.
        truth: the frame's truth.

    Returns:
        ((K,), (K,)) absolute relative errors of A and of B on the K common points.
    """
    speed = float(np.linalg.norm(truth.velocity))
    common, ia, ib = np.intersect1d(
        np.asarray(ids_a), np.asarray(ids_b), assume_unique=True, return_indices=True
    )
    if common.size == 0 or speed < MIN_SPEED:
        return np.zeros(0), np.zeros(0)
    px = np.asarray(pixels_a, dtype=np.float64).reshape(-1, 2)[ia]
    ra = np.asarray(range_a, dtype=np.float64)[ia]
    rb = np.asarray(range_b, dtype=np.float64)[ib]
    true = true_range_over_speed(px, truth.range_m, speed)
    ok = np.isfinite(true) & np.isfinite(ra) & np.isfinite(rb)
    if truth.mask is not None:
        ok &= ~(sample_nearest(truth.mask.astype(np.float64), px) > 0.5)
        ok &= ~(sample_nearest(mask_edge_distance(truth.mask), px) <= MASK_MARGIN_PX)
    return np.abs(relative_error(ra[ok], true[ok])), np.abs(relative_error(rb[ok], true[ok]))


def relative_error(estimated: npt.ArrayLike, true: npt.ArrayLike) -> FloatArray:
    """Signed relative error ``(est - true) / true`` (NaN where either is not finite)."""
    e = np.asarray(estimated, dtype=np.float64)
    t = np.asarray(true, dtype=np.float64)
    ok = np.isfinite(e) & np.isfinite(t) & (t != 0)
    return np.where(ok, (e - t) / np.where(ok, t, 1.0), np.nan)


def coverage(
    pixels: npt.ArrayLike, width: int, height: int, grid: tuple[int, int] = GRID
) -> float:
    """Fraction of the ``grid`` (cols, rows) cells over a width x height image with a point."""
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    px = px[np.isfinite(px).all(axis=1)]
    cols, rows = grid
    cu = np.floor(px[:, 0] / width * cols).astype(np.int64)
    cv = np.floor(px[:, 1] / height * rows).astype(np.int64)
    ok = (cu >= 0) & (cu < cols) & (cv >= 0) & (cv < rows)
    return float(np.unique(cv[ok] * cols + cu[ok]).size) / (cols * rows)


def score_frame(
    est: Estimate | None, truth: Truth, truth_bias: npt.ArrayLike | None = None
) -> FrameScore:
    """All metrics of one frame (``est`` None = the estimator gave nothing for it)."""
    est = est if est is not None else Estimate(truth.stamp_ns, None)
    speed = float(np.linalg.norm(truth.velocity))
    translating = speed >= MIN_SPEED
    has_heading = est.heading is not None and bool(np.all(np.isfinite(est.heading)))
    heading_deg = math.nan
    if has_heading and translating:
        heading_deg = float(heading_error_deg(est.heading, truth.velocity))
    h, w = truth.range_m.shape[:2]
    n = int(est.pixels.shape[0])
    moving_true = np.zeros(n, dtype=bool)
    clear = np.ones(n, dtype=bool)
    if truth.mask is not None:
        moving_true = sample_nearest(truth.mask.astype(np.float64), est.pixels) > 0.5
        clear = ~(sample_nearest(mask_edge_distance(truth.mask), est.pixels) <= MASK_MARGIN_PX)
    flagged = (np.asarray(est.flags, dtype=np.uint8) & MOVING_BIT) > 0
    ros_true = (
        true_range_over_speed(est.pixels, truth.range_m, speed)
        if translating
        else np.full(n, np.nan)
    )
    signed = relative_error(est.range_over_speed, ros_true)
    scored = np.isfinite(signed) & ~moving_true & clear
    bias_error = math.nan
    if est.gyro_bias is not None and truth_bias is not None:
        bias_error = float(np.linalg.norm(np.asarray(est.gyro_bias) - np.asarray(truth_bias)))
    return FrameScore(
        stamp_ns=truth.stamp_ns,
        translating=translating,
        has_heading=has_heading,
        heading_deg=heading_deg,
        points=n,
        coverage=coverage(est.pixels, w, h),
        range_rel=np.abs(signed[scored]),
        range_signed=signed[scored],
        range_true=ros_true[scored],
        range_est=np.asarray(est.range_over_speed, dtype=np.float64)[scored],
        moving_tp=int(np.count_nonzero(flagged & moving_true & clear)),
        moving_fp=int(np.count_nonzero(flagged & ~moving_true & clear)),
        moving_fn=int(np.count_nonzero(~flagged & moving_true & clear)),
        moving_flagged=int(np.count_nonzero(flagged)),
        bias_error=bias_error,
        moving_strict=(
            int(np.count_nonzero(flagged & moving_true)),
            int(np.count_nonzero(flagged & ~moving_true)),
            int(np.count_nonzero(~flagged & moving_true)),
        ),
    )


def mask_edge_distance(mask: npt.NDArray[np.bool_]) -> FloatArray:
    """(H, W) exact Euclidean distance of each pixel centre to the nearest pixel centre of
    the other label (moving / static) of ``mask`` (H, W) bool, pixels; inf when the mask
    holds one label only."""
    m = np.ascontiguousarray(mask, dtype=np.uint8)
    if not m.any() or m.all():
        return np.full(m.shape, np.inf)
    inside = cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform(1 - m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.asarray(np.maximum(inside, outside), dtype=np.float64)


def summarize(scores: Sequence[FrameScore], has_mask: bool) -> dict[str, Any]:
    """Pooled metrics over frames (JSON-ready; null where a metric does not apply).

    Keys: frames, translating_frames, heading_frames (translating frames with a heading),
    heading_availability, false_heading_frames (heading while not translating),
    heading_deg_median/p90/mean/max, range_rel_median/p90 (pooled over static points),
    range_signed_median, range_points, points_per_frame, coverage_mean,
    moving_precision/recall (null without a mask or without flags / moving points; points
    within MASK_MARGIN_PX of the mask's edge left out), moving_precision/recall_strict
    (every point),
    moving_flagged_fraction, bias_error_final_rad_s, bias_error_median_rad_s (second half).
    """
    trans = [s for s in scores if s.translating]
    head = np.array([s.heading_deg for s in trans if s.has_heading], dtype=np.float64)
    rel = np.concatenate([s.range_rel for s in scores]) if scores else np.zeros(0)
    signed = np.concatenate([s.range_signed for s in scores]) if scores else np.zeros(0)
    tp = sum(s.moving_tp for s in scores)
    fp = sum(s.moving_fp for s in scores)
    fn = sum(s.moving_fn for s in scores)
    stp, sfp, sfn = (sum(s.moving_strict[k] for s in scores) for k in range(3))
    npts = sum(s.points for s in scores)
    bias = np.array([s.bias_error for s in scores], dtype=np.float64)
    bias_known = bias[np.isfinite(bias)]
    half = bias_known[bias_known.size // 2 :]
    return {
        "frames": len(scores),
        "translating_frames": len(trans),
        "heading_frames": int(head.size),
        "heading_availability": _num(head.size / len(trans)) if trans else None,
        "false_heading_frames": sum(1 for s in scores if s.has_heading and not s.translating),
        "heading_deg_median": _num(_median(head)),
        "heading_deg_p90": _num(_p90(head)),
        "heading_deg_mean": _num(float(head.mean())) if head.size else None,
        "heading_deg_max": _num(float(head.max())) if head.size else None,
        "range_rel_median": _num(_median(rel)),
        "range_rel_p90": _num(_p90(rel)),
        "range_signed_median": _num(_median(signed)),
        "range_points": int(rel.size),
        "points_per_frame": _num(npts / len(scores)) if scores else None,
        "coverage_mean": _num(float(np.mean([s.coverage for s in scores]))) if scores else None,
        "moving_precision": _num(tp / (tp + fp)) if has_mask and tp + fp else None,
        "moving_recall": _num(tp / (tp + fn)) if has_mask and tp + fn else None,
        "moving_precision_strict": _num(stp / (stp + sfp)) if has_mask and stp + sfp else None,
        "moving_recall_strict": _num(stp / (stp + sfn)) if has_mask and stp + sfn else None,
        "moving_flagged_fraction": _num((tp + fp) / npts) if npts else None,
        "bias_error_final_rad_s": _num(float(bias_known[-1])) if bias_known.size else None,
        "bias_error_median_rad_s": _num(_median(half)),
    }


# ------------------------------------------------------------------------ bag reading


def _rclpy_msg(reader: BagReader, raw: Any) -> Any:
    from rclpy.serialization import deserialize_message

    from msg_adapters.msgtypes import message_class

    try:
        return deserialize_message(raw.data, message_class(raw.msgtype))
    except Exception as err:  # CDR errors have no common base
        msg = f"cannot decode {raw.msgtype} on {raw.topic} in {reader.path}: {err}"
        raise EvalError(" ".join(msg.split())) from None


def _pick(topics: dict[str, Any], names: Iterable[str], wanted: str | None) -> str | None:
    if wanted is not None:
        return wanted if wanted in topics else None
    return next((n for n in names if n in topics), None)


def read_estimates(
    path: str | Path,
    points_topic: str | None = None,
    heading_topic: str | None = None,
    notes: list[str] | None = None,
) -> dict[int, Estimate]:
    """The result bag's frames by image stamp (ns): points, heading, and the gyro-bias
    estimate after that frame (``owl/gyro_bias``, matched by the image stamp).

    A truncated result bag (e.g. a recorder that was killed) is read up to the damage and
    the damage is appended to ``notes``.

    Raises:
        EvalError: neither a points nor a heading topic, a cloud without the needed fields.
        BagError: missing, not a bag, corrupt.
    """
    from msg_adapters.diagnostics import msg_to_records
    from msg_adapters.heading import msg_to_heading
    from msg_adapters.imu import msg_to_gyro_bias
    from msg_adapters.pointcloud import cloud_to_array
    from msg_adapters.stamps import header_to_ns

    with BagReader(path, recover=True) as bag:
        topics = bag.topics
        named = eval_checks.check_named_topics(path, topics, points_topic, heading_topic)
        if named is not None:
            raise EvalError(named)
        pts_t = _pick(topics, POINTS_TOPICS, points_topic)
        head_t = _pick(topics, HEADING_TOPICS, heading_topic)
        if pts_t is None and head_t is None:
            want = points_topic or heading_topic or "/owl/points or /owl/heading"
            msg = f"result bag {path} has no {want} (has: {', '.join(sorted(topics)) or 'none'})"
            if bag.damage:
                msg += f"; it is damaged: {bag.damage}"
            raise EvalError(msg)
        bias_t = _pick(topics, BIAS_TOPICS, None)
        read = [t for t in (pts_t, head_t, bias_t) if t is not None]
        if DIAGNOSTICS.bag in topics:  # its "owl: input" statuses say whether IMU arrived
            read.append(DIAGNOSTICS.bag)
        clouds: dict[int, Any] = {}
        headings: dict[int, FloatArray] = {}
        biases: dict[int, FloatArray] = {}
        inputs: list[dict[str, str]] = []  # values of the "owl: input" statuses
        for raw in bag.messages(read):
            msg = _rclpy_msg(bag, raw)
            if raw.topic == pts_t:
                arr = cloud_to_array(msg)
                missing = [f for f in ("u", "v", "range_over_speed") if f not in arr.dtype.names]
                if missing:
                    raise EvalError(f"{pts_t} in {path} has no field {missing[0]!r}")
                clouds[header_to_ns(msg.header)] = arr
            elif raw.topic == head_t:
                headings[header_to_ns(msg.header)] = msg_to_heading(msg)
            elif raw.topic == bias_t:
                biases[header_to_ns(msg.header)] = msg_to_gyro_bias(msg)
            else:
                _, records = msg_to_records(msg)
                inputs += [r.value_map() for r in records if r.name.endswith(": input")]
        if bag.damage and notes is not None:  # found on opening or while reading
            notes.append(f"result bag damaged, scored what was readable: {bag.damage}")
    empty = eval_checks.check_points(path, pts_t, [a.size for a in clouds.values()])
    if empty is not None and points_topic is not None:  # the topic the user asked for
        raise EvalError(empty)
    if empty is not None and notes is not None:  # e.g. a still camera: headings, bias
        notes.append(empty.replace(": nothing to score", ": no r/|t| to score"))
    if eval_checks.imu_was_used(inputs) is False:  # the bias never moved: not an estimate
        biases = {}
        if notes is not None:
            notes.append("result had no IMU samples: gyro-bias error not scored")
    stamps = sorted(set(clouds) | set(headings))
    out: dict[int, Estimate] = {}
    for stamp in stamps:
        arr = clouds.get(stamp)
        bias = biases.get(stamp)  # owl/gyro_bias carries the image stamp
        if arr is not None:
            flags = arr["flags"] if "flags" in arr.dtype.names else np.zeros(arr.size)
            pixels = np.c_[arr["u"], arr["v"]].astype(np.float64)
            range_over_speed = arr["range_over_speed"].astype(np.float64)
        else:
            pixels, range_over_speed, flags = np.zeros((0, 2)), np.zeros(0), np.zeros(0)
        out[stamp] = Estimate(
            stamp,
            headings.get(stamp),
            pixels,
            range_over_speed,
            np.asarray(flags, dtype=np.uint8),
            bias,
        )
    return out


def read_results(path: str | Path, points_topic: str | None = None) -> list[Any]:
    """A result bag's clouds and headings back as owl_core FrameResults, in stamp order.

    Fields the cloud does not carry (timings, reasons, heading sigma) are empty/NaN;
    ``bearings`` are the unit vectors of ``x y z`` (or zero when a point has none). For
    plots of results written by owl_process.
    """
    from msg_adapters.heading import msg_to_heading
    from msg_adapters.pointcloud import cloud_to_array
    from msg_adapters.stamps import header_to_ns
    from owl_core.types import FrameResult

    with BagReader(path) as bag:
        topics = bag.topics
        pts_t = _pick(topics, POINTS_TOPICS, points_topic)
        if pts_t is None:
            msg = f"result bag {path} has no {points_topic or '/owl/points'} (has: "
            raise EvalError(msg + ", ".join(sorted(topics)) + ")")
        head_t = _pick(topics, HEADING_TOPICS, None)
        clouds: dict[int, Any] = {}
        headings: dict[int, FloatArray] = {}
        for raw in bag.messages([t for t in (pts_t, head_t) if t is not None]):
            msg = _rclpy_msg(bag, raw)
            if raw.topic == pts_t:
                clouds[header_to_ns(msg.header)] = cloud_to_array(msg)
            else:
                headings[header_to_ns(msg.header)] = msg_to_heading(msg)
    out = []
    for stamp in sorted(clouds):
        a = clouds[stamp]

        def col(*names: str, arr: Any = a) -> FloatArray:
            return np.stack([np.asarray(arr[n], dtype=np.float64) for n in names], axis=-1)

        pts = col("x", "y", "z")
        norm = np.linalg.norm(pts, axis=1, keepdims=True)
        out.append(
            FrameResult(
                stamp_ns=stamp,
                pixels=col("u", "v"),
                bearings=np.where(norm > 0, pts / np.where(norm > 0, norm, 1.0), 0.0),
                looming=np.asarray(a["L"], dtype=np.float64),
                omega=col("omega_x", "omega_y", "omega_z"),
                rot=col("rot_w", "rot_x", "rot_y", "rot_z"),
                range_over_speed=np.asarray(a["range_over_speed"], dtype=np.float64),
                points=pts,
                quality=np.asarray(a["quality"], dtype=np.float64),
                ids=np.asarray(a["id"], dtype=np.uint32),
                flags=np.asarray(a["flags"], dtype=np.uint8),
                heading=headings.get(stamp),
                heading_sigma_rad=math.nan,
                gyro_bias=np.full(3, np.nan),
            )
        )
    return out


def truth_info(path: str | Path) -> dict[str, Any]:
    """The truth bag's owl_make_bag options (metadata custom_data), {} when absent."""
    with BagReader(path) as bag:
        text = bag.custom_data.get("owl_make_bag")
    try:
        return dict(json.loads(text)) if text else {}
    except (ValueError, TypeError):
        return {}


def iter_truth(path: str | Path) -> Iterator[Truth]:
    """Truth frames of a truth bag in stamp order (twist + range [+ mask] per image stamp).

    Raises:
        EvalError: the bag lacks /ground_truth/twist or /ground_truth/range.
    """
    from msg_adapters.image import image_to_array
    from msg_adapters.stamps import header_to_ns

    with BagReader(path) as bag:
        topics = bag.topics
        if TRUTH_TOPICS["twist"] not in topics:
            msg = f"truth bag {path} has no {TRUTH_TOPICS['twist']} (has: "
            raise EvalError(
                msg + ", ".join(sorted(topics)) + "): no ground truth to score against "
                "(owl_make_bag renders it; owl_import writes it from a dataset's poses: "
                "EuRoC state_groundtruth_estimate0, TUM-VI mocap0, KITTI poses)"
            )
        has_range = TRUTH_TOPICS["range"] in topics
        no_range = None if has_range else _no_range_image(bag)
        has_mask = TRUTH_TOPICS["mask"] in topics
        need = 1 + has_range + has_mask
        partial: dict[int, dict[str, Any]] = {}
        present = {"twist": True, "range": has_range, "mask": has_mask}
        read = [TRUTH_TOPICS[k] for k, there in present.items() if there]
        for raw in bag.messages(read):
            msg = _rclpy_msg(bag, raw)
            stamp = header_to_ns(msg.header)
            slot = partial.setdefault(stamp, {})
            if raw.topic == TRUTH_TOPICS["twist"]:
                lin = msg.twist.linear
                slot["velocity"] = np.array([lin.x, lin.y, lin.z], dtype=np.float64)
            elif raw.topic == TRUTH_TOPICS["range"]:
                slot["range"] = image_to_array(msg).astype(np.float32)
            else:
                slot["mask"] = image_to_array(msg) > 0
            if len(slot) == need:
                del partial[stamp]
                rng = slot["range"] if has_range else no_range
                yield Truth(stamp, slot["velocity"], rng, slot.get("mask"))


def _no_range_image(bag: BagReader) -> npt.NDArray[np.float32]:
    """An all-NaN (H, W) range image (nothing scored), sized from the bag's camera_info."""
    if CAMERA_INFO_TOPIC not in bag.topics:
        msg = f"truth bag {bag.path} has neither {TRUTH_TOPICS['range']} nor {CAMERA_INFO_TOPIC}"
        raise EvalError(msg + " (the image size is needed for coverage)")
    info = _rclpy_msg(bag, next(iter(bag.messages([CAMERA_INFO_TOPIC]))))
    return np.full((int(info.height), int(info.width)), np.nan, dtype=np.float32)


def truth_has_range(path: str | Path) -> bool:
    """Whether the truth bag has a range image topic (r/|t| can be scored)."""
    with BagReader(path) as bag:
        return TRUTH_TOPICS["range"] in bag.topics


def truth_bias_track(path: str | Path) -> dict[int, FloatArray]:
    """The truth bag's /ground_truth/gyro_bias by header stamp (ns), {} when absent."""
    from msg_adapters.stamps import header_to_ns

    with BagReader(path) as bag:
        if TRUTH_TOPICS["bias"] not in bag.topics:
            return {}
        out: dict[int, FloatArray] = {}
        for raw in bag.messages([TRUTH_TOPICS["bias"]]):
            msg = _rclpy_msg(bag, raw)
            v = msg.vector
            out[header_to_ns(msg.header)] = np.array([v.x, v.y, v.z], dtype=np.float64)
        return out


def truth_has_mask(path: str | Path) -> bool:
    """Whether the truth bag has a moving-object mask topic."""
    with BagReader(path) as bag:
        return TRUTH_TOPICS["mask"] in bag.topics


def write_result_bag(
    path: str | Path,
    results: Iterable[Any],
    frame_id: str = "camera_optical_frame",
    overwrite: bool = False,
    imu_frame_id: str = "imu_link",
) -> int:
    """Write engine FrameResults as a result bag in owl_process's layout.

    ``/owl/points`` (every frame, possibly empty), ``/owl/heading`` (frames with a heading)
    and ``/owl/gyro_bias`` (every frame), all stamped with the image stamp; the topics of
    :data:`owl_ros.topics.RESULT_TOPICS` (``/diagnostics`` stays empty). For tests,
    ``owl_bench`` and the demo; ``owl_process`` writes the same topics from real bags.
    Returns the number of frames written.
    """
    from bags.io import BagWriter
    from msg_adapters.heading import heading_to_msg
    from msg_adapters.imu import gyro_bias_to_msg
    from msg_adapters.pointcloud import frame_result_to_cloud
    from msg_adapters.stamps import make_header

    count = 0
    with BagWriter(path, overwrite=overwrite) as bag:
        for topic in RESULT_TOPICS:
            bag.add_topic(topic.bag, topic.msgtype, topic.qos)
        for res in results:
            stamp = int(res.stamp_ns)
            header = make_header(stamp, frame_id)
            bag.write(POINTS.bag, stamp, frame_result_to_cloud(res, header))
            if res.heading is not None:
                bag.write(HEADING.bag, stamp, heading_to_msg(res.heading, header))
            bias_header = make_header(stamp, imu_frame_id)
            bag.write(GYRO_BIAS.bag, stamp, gyro_bias_to_msg(res.gyro_bias, bias_header))
            count += 1
    return count


@dataclass(frozen=True)
class Evaluation:
    """The result of :func:`evaluate`: summary, per-frame scores and notes."""

    summary: dict[str, Any]
    frames: list[FrameScore]
    notes: list[str]

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready object."""
        return {
            "summary": self.summary,
            "notes": self.notes,
            "frames": [s.as_dict() for s in self.frames],
        }


def _check_same_recording(
    result_path: str | Path,
    truth_path: str | Path,
    estimates: dict[int, Estimate],
    truth_stamps: list[int],
    truth_size: tuple[int, int] | None,
) -> None:
    """EvalError when the result is of another bag (stamps, image size)."""
    pixels = [e.pixels for e in estimates.values() if e.pixels.size]
    top = None
    if pixels:
        both = np.concatenate(pixels)
        top = (float(both[:, 0].max()), float(both[:, 1].max()))
    why = eval_checks.check_against_truth(
        result_path, truth_path, sorted(estimates), truth_stamps, top, truth_size
    )
    if why is not None:
        raise EvalError(why)


def evaluate(
    result_path: str | Path,
    truth_path: str | Path,
    *,
    points_topic: str | None = None,
    heading_topic: str | None = None,
    progress: bool = False,
) -> Evaluation:
    """Score a result bag against a truth bag (see the module docstring)."""
    notes: list[str] = []
    estimates = read_estimates(result_path, points_topic, heading_topic, notes)
    info = truth_info(truth_path)
    truth_bias = None
    bias_track = truth_bias_track(truth_path)
    if bias_track:
        truth_bias = bias_track[max(bias_track)]
    elif "gyro_bias" in info:
        truth_bias = np.asarray(info["gyro_bias"], dtype=np.float64)
        if float(info.get("gyro_bias_walk", 0.0) or 0.0) > 0:
            notes.append("truth bias = the initial bias only (the bag has a bias random walk)")
    else:
        notes.append("truth bag records no gyro bias: bias error not scored")
    has_range = truth_has_range(truth_path)
    if not has_range:
        notes.append(f"range_over_speed {NO_RANGE}")
    has_mask = truth_has_mask(truth_path)
    scores: list[FrameScore] = []
    every = dict(estimates)
    truth_stamps: list[int] = []
    truth_size: tuple[int, int] | None = None
    t0 = time.monotonic()
    last = t0
    for truth in iter_truth(truth_path):
        truth_stamps.append(truth.stamp_ns)
        if truth.range_m is not None:
            truth_size = (truth.range_m.shape[1], truth.range_m.shape[0])
        frame_bias = bias_track.get(truth.stamp_ns) if bias_track else truth_bias
        scores.append(score_frame(estimates.pop(truth.stamp_ns, None), truth, frame_bias))
        if progress and time.monotonic() - last > 2.0:
            last = time.monotonic()
            print(f"{PROG}: {len(scores)} frames scored", file=sys.stderr, flush=True)
    if not scores:
        raise EvalError(f"truth bag {truth_path} has no complete ground-truth frame")
    _check_same_recording(result_path, truth_path, every, truth_stamps, truth_size)
    if estimates:
        notes.append(f"{len(estimates)} result frames have no ground truth (ignored)")
    summary = summarize(scores, has_mask)
    summary["truth_gyro_bias_rad_s"] = None if truth_bias is None else truth_bias.tolist()
    summary["range_scored"] = has_range
    summary["bias_scored"] = truth_bias is not None
    summary["scenario"] = info.get("scenario")
    return Evaluation(summary, scores, notes)


# ------------------------------------------------------------------------ text


def _fmt(value: Any, unit: str = "", scale: float = 1.0, digits: int = 3) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, int):
        return f"{value}{unit}"
    return f"{value * scale:.{digits}g}{unit}"


def summary_lines(summary: dict[str, Any]) -> list[str]:
    """The summary as aligned text lines."""
    s = summary
    rows = [
        (
            "frames (translating / with heading)",
            f"{s['frames']} ({s['translating_frames']} / {s['heading_frames']})",
        ),
        (
            "heading error median / p90",
            f"{_fmt(s['heading_deg_median'], ' deg')} / {_fmt(s['heading_deg_p90'], ' deg')}",
        ),
        ("heading availability", _fmt(s["heading_availability"], " %", 100.0)),
        ("false headings (camera not translating)", str(s["false_heading_frames"])),
        (
            "range_over_speed rel. error median / p90",
            f"{_fmt(s['range_rel_median'], ' %', 100)}"
            f" / {_fmt(s['range_rel_p90'], ' %', 100)} ({s['range_points']} static points)"
            if s.get("range_scored", True)
            else NO_RANGE,
        ),
        (
            "range_over_speed signed median",
            _fmt(s["range_signed_median"], " %", 100) if s.get("range_scored", True) else NO_RANGE,
        ),
        ("points per frame", _fmt(s["points_per_frame"], "", 1.0, 4)),
        ("image coverage (16x12 cells)", _fmt(s["coverage_mean"], " %", 100)),
        (
            "moving points precision / recall",
            f"{_fmt(s['moving_precision'], ' %', 100)} / {_fmt(s['moving_recall'], ' %', 100)}",
        ),
        ("points flagged moving", _fmt(s["moving_flagged_fraction"], " %", 100)),
        (
            "gyro-bias error final / median",
            f"{_fmt(s['bias_error_final_rad_s'], ' rad/s')} / "
            f"{_fmt(s['bias_error_median_rad_s'], ' rad/s')}"
            if s.get("bias_scored", True)
            else "not scored: no gyro-bias ground truth",
        ),
    ]
    width = max(len(k) for k, _ in rows)
    return [f"  {k:<{width}}  {v}" for k, v in rows]


# ------------------------------------------------------------------------ CLI


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    p = OneLineErrorParser(
        prog=PROG,
        description="Score an OWL result bag (owl/points, owl/heading) against the ground "
        "truth of a synthetic bag (owl_make_bag): heading error, range_over_speed error, "
        "points and coverage, moving-point precision/recall, gyro-bias error.",
    )
    p.add_argument("result_bag", help="bag written by owl_process (or recorded from owl_node)")
    p.add_argument("--truth", required=True, help="bag with /ground_truth/* (owl_make_bag)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--per-frame", action="store_true", help="text: also one line per frame")
    p.add_argument("--points-topic", default=None, help="default /owl/points or owl/points")
    p.add_argument("--heading-topic", default=None, help="default /owl/heading or owl/heading")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``owl_eval``; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        ev = evaluate(
            args.result_bag,
            args.truth,
            points_topic=args.points_topic,
            heading_topic=args.heading_topic,
            progress=not args.json,
        )
    except (ToolError, BagError, ValueError) as err:
        print(f"{PROG}: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(ev.as_dict()))
        return 0
    print(
        f"{PROG}: {args.result_bag} vs {args.truth}"
        + (f" (scenario {ev.summary['scenario']})" if ev.summary.get("scenario") else "")
    )
    for line in summary_lines(ev.summary):
        print(line)
    for note in ev.notes:
        print(f"  note: {note}")
    if args.per_frame:
        print("  stamp_ns              heading_deg  points  coverage  range_rel_med")
        for s in ev.frames:
            d = s.as_dict()
            print(
                f"  {s.stamp_ns:<20d}  {_fmt(d['heading_deg']):>11}  {s.points:>6}  "
                f"{_fmt(d['coverage']):>8}  {_fmt(d['range_rel_median']):>13}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
