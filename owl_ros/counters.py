"""The pipeline's counters: one typed record instead of string keys.

The field names are the keys the diagnostics publish (``<name>_total`` and the rates in
:mod:`owl_ros.status`) and the keys of ``owl_process``'s ``Summary.counts``; eval, soak
and the tests read them, so they stay as they are.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from enum import StrEnum

from owl_ros.roles import Role

__all__ = ["Counters", "Skip"]


class Skip(StrEnum):
    """Why a queued frame was not processed; the value is its counter's name."""

    NO_CAMERA_INFO = "skipped_no_camera_info"
    BAD_IMAGE = "skipped_bad_image"
    DUPLICATE_STAMP = "skipped_duplicate_stamp"
    OUT_OF_ORDER = "skipped_out_of_order"
    ENGINE_ERROR = "skipped_engine_error"


@dataclass
class Counters:
    """Message and frame counts (totals since start, or a window's increments).

    Attributes (all counts):
        images, camera_info, imu, speed: messages received per input role.
        imu_invalid: IMU messages that could not be read (one per message).
        imu_non_finite, imu_duplicate, imu_out_of_order: IMU samples dropped for that
            reason (a stamp not after the newest, within ``max_frame_gap_s``).
        imu_gaps: IMU gaps longer than ``imu_max_gap_s`` (never interpolated across).
        speed_invalid, speed_stale, speed_too_low: speed messages unreadable / speeds not
            used for a frame (too old, below ``min_speed``).
        dropped_queue_full: frames dropped from the full queue (newest wins).
        images_missing: images missing between the received ones' stamps, lost before
            the node (``owl_ros.scheduler.StampGaps``).
        backlog_dropped: IMU, camera_info and speed messages dropped from the node's full
            input backlog (its worker stalled for longer than the backlog holds).
        skipped_no_camera_info, skipped_bad_image, skipped_duplicate_stamp,
            skipped_out_of_order, skipped_engine_error: frames taken from the queue but
            not processed (an out-of-order stamp: before the last processed frame's by
            at most ``max_frame_gap_s``).
        processed, frames_with_points, frames_metric, headings: frames the engine
            processed; of those, with points, with metric points, with a heading.
        frames_imu_not_covered: processed frames whose interval the IMU did not cover.
        frames_imu_late: of those, frames the IMU reached after they were processed (it
            arrives later than the queue kept the frame waiting: ``queue_size`` or
            ``imu_wait_s`` too small for this IMU's latency).
        time_jumps: backwards time jumps (engine reset).
        reconfigured, camera_changed, bad_camera_info: engine rebuilds for new options or
            a new calibration; camera_info messages rejected.
        qos_events: QoS incompatibilities reported.
        worker_errors: exceptions the node's worker thread survived outside the engine
            (handing over an input, publishing a frame's outputs, the debug image, the dense
            hand-off, the diagnostics): that frame's outputs may be incomplete.
    """

    images: int = 0
    camera_info: int = 0
    imu: int = 0
    speed: int = 0
    imu_invalid: int = 0
    imu_non_finite: int = 0
    imu_duplicate: int = 0
    imu_out_of_order: int = 0
    imu_gaps: int = 0
    speed_invalid: int = 0
    speed_stale: int = 0
    speed_too_low: int = 0
    dropped_queue_full: int = 0
    images_missing: int = 0
    backlog_dropped: int = 0
    skipped_no_camera_info: int = 0
    skipped_bad_image: int = 0
    skipped_duplicate_stamp: int = 0
    skipped_out_of_order: int = 0
    skipped_engine_error: int = 0
    processed: int = 0
    frames_with_points: int = 0
    frames_metric: int = 0
    headings: int = 0
    frames_imu_not_covered: int = 0
    frames_imu_late: int = 0
    time_jumps: int = 0
    reconfigured: int = 0
    camera_changed: int = 0
    bad_camera_info: int = 0
    qos_events: int = 0
    worker_errors: int = 0

    def count_skip(self, skip: Skip) -> None:
        """One frame skipped for ``skip``."""
        setattr(self, skip.value, getattr(self, skip.value) + 1)

    def received(self, role: Role) -> int:
        """Messages received on the input of ``role``."""
        return {
            Role.IMAGE: self.images,
            Role.CAMERA_INFO: self.camera_info,
            Role.IMU: self.imu,
            Role.SPEED: self.speed,
        }[role]

    def copy(self) -> Counters:
        """An independent copy."""
        return replace(self)

    def since(self, start: Counters) -> Counters:
        """The increments since ``start`` (an earlier copy of these totals)."""
        return Counters(
            **{f.name: getattr(self, f.name) - getattr(start, f.name) for f in fields(self)}
        )

    def as_dict(self) -> dict[str, int]:
        """Every count by its published key."""
        return asdict(self)
