"""The pipeline's /diagnostics statuses, built by pure functions from one snapshot.

:class:`~owl_ros.pipeline.Pipeline` gathers a :class:`StatusInputs` (its counters, the
window since the last report, the last problem of each kind, the engine's bias) and
:func:`build_status` turns it into the three records ``owl: input``, ``owl: processing``
and ``owl: gyro``. Nothing here reads a clock or changes state, so a test can build any
status from a hand-made snapshot. The key names are the published API (eval, soak and the
DDS tests read them): keep them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from bags.dds import DEFAULT_SEGMENT_BYTES
from msg_adapters.diagnostics import Level, StatusRecord
from owl_core.calib_check import MonitorVerdict
from owl_ros.counters import Counters

DIAG_PREFIX = "owl"
#: ``owl: input`` warns when more than this share of the window's images is missing
#: between the received stamps.
MISSING_IMAGES_WARN = 0.05


def _percentile(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else math.nan


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if values else math.nan


@dataclass(frozen=True)
class StatusInputs:
    """Everything the statuses report, as of one diagnostics call.

    Attributes:
        span_s: length of the window, s (NaN before the first window started).
        counts: counter increments in the window.
        totals: counters since start.
        points: points per processed frame in the window.
        process_s, cycle_s, latency_s, stamp_latency_s: per-frame engine time, worker
            cycle, arrival -> publication and image stamp -> publication, s, in the window.
        camera_known: a valid camera_info has been received.
        camera_error: why the last camera_info was rejected, or None.
        wrong_type: one text per input-topic publisher of the wrong message type.
        last_bad_image, last_imu_problem, last_empty_reason, last_jump, last_worker_error:
            the newest text of each kind ("" for none).
        qos_events: QoS event texts, oldest first.
        image_bytes: size of the newest image message's data, bytes (0 before one).
        heading_sigma_rad: the last result's heading sigma, rad (NaN without a result).
        gyro_bias, gyro_bias_sigma: (3,) engine bias estimate and its sigma, rad/s, IMU
            frame (zeros / NaN without an engine).
        queue_size: the frame queue's capacity.
        require_gyro: the engine option of that name.
        calibration: the live calibration check's latest verdict (None before one).
        imu_time_offset_s: the IMU time offset the engine uses, s (NaN without an engine).
        imu_time_offset_sigma_s: 1-sigma of its online estimate, s (NaN when not
            estimated: ``estimate_imu_time_offset`` off).
        dense_max_rate_hz: the dense stage's rate cap, Hz (0: every frame it can), or None
            when the dense stage is off.
    """

    span_s: float
    counts: Counters
    totals: Counters
    points: Sequence[int] = ()
    process_s: Sequence[float] = ()
    cycle_s: Sequence[float] = ()
    latency_s: Sequence[float] = ()
    stamp_latency_s: Sequence[float] = ()
    camera_known: bool = False
    camera_error: str | None = None
    wrong_type: Sequence[str] = ()
    last_bad_image: str = ""
    last_imu_problem: str = ""
    last_empty_reason: str = ""
    last_jump: str = ""
    last_worker_error: str = ""
    qos_events: Sequence[str] = ()
    image_bytes: int = 0
    heading_sigma_rad: float = math.nan
    gyro_bias: npt.NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    gyro_bias_sigma: npt.NDArray[np.float64] = field(default_factory=lambda: np.full(3, np.nan))
    queue_size: int = 0
    require_gyro: bool = True
    calibration: MonitorVerdict | None = None
    imu_time_offset_s: float = math.nan
    imu_time_offset_sigma_s: float = math.nan
    dense_max_rate_hz: float | None = None

    def rate(self, count: int) -> float:
        """A window count per second (NaN for an empty window)."""
        return count / self.span_s if self.span_s > 0 else math.nan


def build_status(s: StatusInputs) -> list[StatusRecord]:
    """The three statuses: ``owl: input``, ``owl: processing``, ``owl: gyro``."""
    return [input_status(s), processing_status(s), gyro_status(s)]


def _input_problems(s: StatusInputs) -> tuple[Level, list[str]]:
    c = s.counts
    level = Level.OK
    problems = []
    if s.camera_error is not None:
        level = Level.ERROR
        problems.append(f"camera_info invalid: {s.camera_error}")
    elif not s.camera_known:
        level = Level.ERROR
        problems.append("no camera_info received")
    if s.wrong_type:
        level = Level.ERROR
        problems.append(f"wrong message type: {s.wrong_type[0]}")
    warnings = []
    if c.images == 0:
        warnings.append("no images")
    if c.imu == 0:
        warnings.append("no IMU")
    if c.skipped_bad_image:
        warnings.append(f"bad image: {s.last_bad_image}")
    if c.imu_non_finite + c.imu_duplicate + c.imu_out_of_order + c.imu_invalid:
        warnings.append(f"bad IMU samples dropped: {s.last_imu_problem}")
    elif c.imu_gaps:
        warnings.append(s.last_imu_problem)
    if c.qos_events:
        warnings.append(f"QoS: {s.qos_events[-1]}")
    if c.backlog_dropped:
        warnings.append(
            f"{c.backlog_dropped} IMU/camera_info/speed messages dropped: the worker fell "
            "behind by more than its input backlog holds"
        )
    if c.images_missing > MISSING_IMAGES_WARN * (c.images + c.images_missing):
        warnings.append(_missing_images_text(c.images_missing, c.images, s.image_bytes))
    if warnings:
        level = max(level, Level.WARN)
    return level, problems + warnings


def _missing_images_text(missing: int, received: int, image_bytes: int) -> str:
    text = (
        f"{missing} of {missing + received} images missing between the received stamps "
        "(lost before the node: camera driver or transport)"
    )
    if image_bytes > DEFAULT_SEGMENT_BYTES:
        text += (
            f"; images of {image_bytes / 1024:.0f} KiB exceed Fast DDS's default 512 KiB "
            "shared-memory segment and go over UDP: give the camera driver "
            "FASTRTPS_DEFAULT_PROFILES_FILE=<owl_ros share>/config/fastdds_large_images.xml"
        )
    return text


def input_status(s: StatusInputs) -> StatusRecord:
    """``owl: input``: rates, drops, bad input, QoS events, wrong-type publishers."""
    t = s.totals
    level, problems = _input_problems(s)
    return StatusRecord.build(
        f"{DIAG_PREFIX}: input",
        level,
        "; ".join(problems) if problems else "inputs OK",
        {
            "image_rate_hz": s.rate(s.counts.images),
            "imu_rate_hz": s.rate(s.counts.imu),
            "camera_info_rate_hz": s.rate(s.counts.camera_info),
            "speed_rate_hz": s.rate(s.counts.speed),
            "images_total": t.images,
            "imu_total": t.imu,
            "bad_images_total": t.skipped_bad_image,
            "last_bad_image": s.last_bad_image,
            "camera_info_error": s.camera_error or "",
            "imu_invalid_total": t.imu_invalid,
            "imu_gaps_total": t.imu_gaps,
            "imu_non_finite_total": t.imu_non_finite,
            "imu_duplicate_total": t.imu_duplicate,
            "imu_out_of_order_total": t.imu_out_of_order,
            "last_imu_problem": s.last_imu_problem,
            "qos_events_total": t.qos_events,
            "images_missing_total": t.images_missing,
            "backlog_dropped_total": t.backlog_dropped,
            "qos_last_event": s.qos_events[-1] if s.qos_events else "",
            "wrong_type_publishers": "; ".join(s.wrong_type),
        },
    )


def _processing_message(s: StatusInputs) -> tuple[Level, str]:
    c = s.counts
    dropped = c.dropped_queue_full
    level = Level.OK
    if c.processed == 0 or c.frames_with_points == 0 or dropped or c.time_jumps:
        level = Level.WARN
    if c.worker_errors:
        level = Level.ERROR
    if c.processed == 0:
        if c.images == 0 and s.totals.images:  # the camera (or a replay) stopped
            message = (
                f"no frames processed: no images in this period ({s.totals.images} received, "
                f"{s.totals.processed} processed since start)"
            )
        elif c.images == 0:
            message = "no frames processed: no images received"
        else:
            why = s.last_empty_reason or "waiting for IMU/camera_info"
            message = f"no frames processed: {why}"
    elif c.frames_with_points:
        mean_points = float(np.mean(s.points)) if s.points else 0
        message = f"{s.rate(c.processed):.1f} frames/s, {mean_points:.0f} points/frame"
    else:
        message = f"no points: {s.last_empty_reason or 'no frames processed'}"
    if dropped:
        message += f"; {dropped} frames dropped (queue full, newest wins)"
        engine_s = _mean(s.process_s)
        interval_s = 1.0 / s.rate(c.images) if c.images else math.nan
        if engine_s > 0.9 * interval_s:  # not a burst: the engine is slower than the camera
            helps = "fewer max_features keep up"
            if s.dense_max_rate_hz is not None:  # the dense thread shares the two cores
                cap = f"{s.dense_max_rate_hz:g} Hz" if s.dense_max_rate_hz > 0 else "none"
                helps = f"fewer max_features or a lower dense_max_rate_hz (now {cap}) keep up"
            message += (
                f": the engine takes {1e3 * engine_s:.0f} ms a frame, images arrive every "
                f"{1e3 * interval_s:.0f} ms ({helps}; the README's "
                "'Cost per frame' says what each setting costs)"
            )
    if c.time_jumps:
        message += f"; time jump: {s.last_jump}"
    if c.worker_errors:
        message += f"; {c.worker_errors} worker errors, the last: {s.last_worker_error}"
    return level, message


def processing_status(s: StatusInputs) -> StatusRecord:
    """``owl: processing``: frames, points, timing, latency, why empty, time jumps."""
    t = s.totals
    level, message = _processing_message(s)
    return StatusRecord.build(
        f"{DIAG_PREFIX}: processing",
        level,
        message,
        {
            "processed_rate_hz": s.rate(s.counts.processed),
            "frames_processed_total": t.processed,
            "frames_with_points_total": t.frames_with_points,
            "frames_metric_total": t.frames_metric,
            "headings_total": t.headings,
            "points_per_frame_mean": _mean(s.points),
            "processing_ms_mean": 1e3 * _mean(s.process_s),
            "processing_ms_max": 1e3 * max(s.process_s) if s.process_s else math.nan,
            "frame_cycle_ms_max": 1e3 * max(s.cycle_s) if s.cycle_s else math.nan,
            "latency_ms_p50": 1e3 * _percentile(s.latency_s, 50),
            "latency_ms_p95": 1e3 * _percentile(s.latency_s, 95),
            "stamp_to_publish_ms_p50": 1e3 * _percentile(s.stamp_latency_s, 50),
            "stamp_to_publish_ms_p95": 1e3 * _percentile(s.stamp_latency_s, 95),
            "dropped_queue_full_total": t.dropped_queue_full,
            "skipped_no_camera_info_total": t.skipped_no_camera_info,
            "skipped_bad_image_total": t.skipped_bad_image,
            "skipped_duplicate_stamp_total": t.skipped_duplicate_stamp,
            "skipped_out_of_order_total": t.skipped_out_of_order,
            "skipped_engine_error_total": t.skipped_engine_error,
            "time_jumps_total": t.time_jumps,
            "last_time_jump": s.last_jump,
            "last_empty_reason": s.last_empty_reason,
            "worker_errors_total": t.worker_errors,
            "last_worker_error": s.last_worker_error,
            "heading_sigma_deg": math.degrees(s.heading_sigma_rad),
            "queue_size": s.queue_size,
        },
    )


def gyro_status(s: StatusInputs) -> StatusRecord:
    """``owl: gyro``: the bias estimate and its sigma, frames without IMU coverage."""
    c = s.counts
    bias = s.gyro_bias
    gaps = c.frames_imu_not_covered
    level = Level.WARN if gaps or (c.imu == 0 and c.images) else Level.OK
    message = f"bias [{bias[0]:.4g}, {bias[1]:.4g}, {bias[2]:.4g}] rad/s"
    if gaps:
        message += f"; {gaps} frames without full IMU coverage"
    if c.frames_imu_late:
        message += (
            f" ({c.frames_imu_late} of them reached by the IMU only after processing: it "
            "arrives later than the queue keeps a frame waiting; raise queue_size or "
            "imu_wait_s)"
        )
    if math.isfinite(s.imu_time_offset_sigma_s):
        message += (
            f"; imu_time_offset estimate {1e3 * s.imu_time_offset_s:.2f} ms "
            f"(1-sigma {1e3 * s.imu_time_offset_sigma_s:.2f} ms)"
        )
    verdict = s.calibration
    if verdict is not None and verdict.disagrees:
        level = Level.WARN
        message += f"; calibration: {verdict.message}"
    return StatusRecord.build(
        f"{DIAG_PREFIX}: gyro",
        level,
        message,
        {
            "bias_x_rad_s": float(bias[0]),
            "bias_y_rad_s": float(bias[1]),
            "bias_z_rad_s": float(bias[2]),
            "bias_sigma_rad_s": float(np.max(s.gyro_bias_sigma)),
            "frames_imu_not_covered_total": s.totals.frames_imu_not_covered,
            "frames_imu_late_total": s.totals.frames_imu_late,
            "require_gyro": s.require_gyro,
            "imu_time_offset_s": s.imu_time_offset_s,
            "imu_time_offset_sigma_s": s.imu_time_offset_sigma_s,
            **_calibration_values(verdict),
        },
    )


def _calibration_values(verdict: MonitorVerdict | None) -> dict[str, object]:
    """Diagnostic values of the live calibration check (empty before its first verdict)."""
    if verdict is None:
        return {}
    out: dict[str, object] = {
        "calibration_ok": not verdict.disagrees,
        "calibration_angle_deg": verdict.angle_deg,
        "calibration_offset_s": verdict.offset_s,
        "calibration_offset_sigma_s": verdict.offset_sigma_s,
        "calibration_source": verdict.source,
    }
    if verdict.rotation_xyzw is not None:
        out["calibration_rotation_xyzw"] = (
            "[" + ", ".join(f"{v:.4f}" for v in verdict.rotation_xyzw) + "]"
        )
    return out
