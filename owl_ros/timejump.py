"""The one place that detects backwards time (bag loops, a restarted sim clock).

:class:`TimeJumps` watches both streams of stamps the pipeline sees:

- IMU: a sample stamped more than ``tolerance_ns`` (``max_frame_gap_s``) before the newest
  finite one is a jump; one less far back is only out of order (the gyro buffer drops
  it). :meth:`TimeJumps.split_imu` cuts a batch of samples into runs at the jumps,
  vectorised over the samples (a loop only over the jumps, which are rare).
- images: a stamp more than ``tolerance_ns`` before the last processed frame's is a jump;
  one less far back is only out of order (the frame is skipped, the tracks kept); an
  equal one a duplicate.

What to do about a jump (process the frames queued before it, reset the engine) is the
pipeline's business; this class only finds them and says what happened.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from enum import Enum

import numpy as np
import numpy.typing as npt

__all__ = ["ImageStamp", "ImuRun", "Jump", "TimeJumps"]

_FLOOR = int(np.iinfo(np.int64).min)


@dataclass(frozen=True)
class Jump:
    """A backwards jump: ``stamp_ns`` arrived after ``newest_ns``; frames stamped after
    ``before_ns`` are from before the jump.

    Attributes:
        stamp_ns: the stamp that went back, ns.
        newest_ns: the newest stamp before it, ns.
        before_ns: frames stamped later than this belong to the old timeline, ns.
        what: one line for diagnostics.
    """

    stamp_ns: int
    newest_ns: int
    before_ns: int
    what: str


@dataclass(frozen=True)
class ImuRun:
    """Samples ``[start, stop)`` of a batch, all on one timeline; ``jump`` is the jump
    between the previous run and this one (None for the first run)."""

    start: int
    stop: int
    jump: Jump | None = None


class ImageStamp(Enum):
    """How a frame's stamp relates to the last processed frame's."""

    NEXT = "next"  # later (or nothing processed yet)
    DUPLICATE = "duplicate"  # equal
    OUT_OF_ORDER = "out_of_order"  # earlier, by at most the tolerance: skip the frame
    BACKWARDS = "backwards"  # earlier by more: a time jump


class TimeJumps:
    """Backwards-time detector for the IMU and image streams (see the module docstring).

    Args:
        tolerance_ns: how far an IMU or image stamp may go back before it is a jump, ns.
    """

    def __init__(self, tolerance_ns: int) -> None:
        self.tolerance_ns = int(tolerance_ns)
        #: newest finite IMU stamp since the last jump, ns (IMU clock), or None.
        self.newest_imu_ns: int | None = None
        #: stamp of the last processed frame, ns, or None.
        self.last_image_ns: int | None = None

    def reset(self) -> None:
        """Forget both timelines (after a jump)."""
        self.newest_imu_ns = None
        self.last_image_ns = None

    def imu_runs(
        self, stamps_ns: npt.NDArray[np.int64], finite: npt.NDArray[np.bool_]
    ) -> Iterator[ImuRun]:
        """Cut a batch of IMU samples at its backwards jumps.

        Yields the non-empty runs in order; every run after the first starts at a jump.
        After the caller has handled a run (fed its samples, or first reset everything for
        its jump), :attr:`newest_imu_ns` advances to the run's newest stamp.

        Args:
            stamps_ns: (N,) int64 sample stamps in arrival order, ns.
            finite: (N,) bool, the sample's rate is finite (others never count).
        """
        n = int(stamps_ns.shape[0])
        start, jump = 0, None
        newest = self.newest_imu_ns
        while True:
            t = stamps_ns[start:]
            valid = np.where(finite[start:], t, _FLOOR)
            base = _FLOOR if newest is None else newest
            prior = np.maximum.accumulate(np.concatenate([[base], valid]))
            back = finite[start:] & (prior[:-1] != _FLOOR) & (t < prior[:-1] - self.tolerance_ns)
            k = int(np.flatnonzero(back)[0]) if back.any() else n - start
            if k > 0 or jump is not None:
                yield ImuRun(start, start + k, jump)
                top = int(prior[k])
                self.newest_imu_ns = None if top == _FLOOR else top
            if start + k == n:
                return
            stamp, before = int(t[k]), int(prior[k])
            jump = Jump(
                stamp,
                before,
                stamp + self.tolerance_ns,
                f"IMU stamp went back {(before - stamp) * 1e-9:.3f} s ({stamp} ns after "
                f"{before} ns): engine reset",
            )
            start, newest = start + k, None

    def check_image(self, stamp_ns: int) -> ImageStamp:
        """Whether a frame's stamp comes after the last processed one's."""
        last = self.last_image_ns
        if last is None or stamp_ns > last:
            return ImageStamp.NEXT
        if stamp_ns == last:
            return ImageStamp.DUPLICATE
        if last - stamp_ns <= self.tolerance_ns:
            return ImageStamp.OUT_OF_ORDER
        return ImageStamp.BACKWARDS

    def image_jump(self, stamp_ns: int) -> Jump:
        """The jump of a frame stamped before the last processed one."""
        last = self.last_image_ns if self.last_image_ns is not None else stamp_ns
        return Jump(
            stamp_ns,
            last,
            last,
            f"image stamp went back {(last - stamp_ns) * 1e-9:.3f} s ({stamp_ns} ns after "
            f"{last} ns): engine reset",
        )

    def image_processed(self, stamp_ns: int) -> None:
        """A frame with this stamp was processed: later frames must come after it."""
        self.last_image_ns = int(stamp_ns)

    def forget_image(self) -> None:
        """No previous frame any more (a new engine, or one reset after an error)."""
        self.last_image_ns = None
