"""When a frame is processed: one bounded frame queue and the readiness rule.

Frames wait in ONE queue of ``capacity`` frames; when it is full the oldest gives way
(the newest frame wins) and the drop is counted. :meth:`FrameQueue.put` is thread-safe:
the node's image callback puts frames straight in, while its worker takes them out.

The readiness rule (:meth:`Scheduler.take`) for the oldest queued frame, with ``now`` from
the injected clock (the node: monotonic time; ``owl_process``: the bag's log time) and
``waited = now - arrival >= imu_wait_s``:

- no engine yet (no valid camera_info): wait while the camera_info may be just behind
  its image (``not waited``), unless the last camera_info was invalid;
- a frame whose header stamp cannot be read: ready (it is skipped at once);
- otherwise ready when the IMU covers the interval since the previous frame, or the wait
  is over, or the IMU already passed its stamp (it will never be covered), or the IMU is
  silent, or the queue is full (the next frame is already there; capacity > 1).

``flush`` (end of a bag, shutdown) makes every frame ready.

Live (``skip_stale``, the node): when the oldest frame is ready and the newest queued
frame is already covered by the IMU, the older frames are dropped (counted with the full
queue's drops) and the newest is processed: a node that fell behind processes the newest
image instead of one that waited a whole engine time in the queue (``owl_latency``
vga30: latency p50 101 -> 63 ms). ``owl_process`` keeps every frame.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from msg_adapters.stamps import header_to_ns

__all__ = ["Frame", "FrameQueue", "Probe", "Scheduler", "StampGaps"]


@dataclass(frozen=True)
class Frame:
    """A queued image.

    Attributes:
        msg: sensor_msgs/Image or CompressedImage.
        arrival_ns: when it arrived, on the scheduler's clock, ns.
        stamp_ns: its header stamp, ns, or None when the header cannot be read.
        stamp_error: why the stamp cannot be read ("" when it can).
    """

    msg: Any
    arrival_ns: int
    stamp_ns: int | None
    stamp_error: str = ""

    @staticmethod
    def of(msg: Any, arrival_ns: int) -> Frame:
        """The queued form of an image message."""
        try:
            return Frame(msg, arrival_ns, header_to_ns(msg.header))
        except ValueError as err:
            return Frame(msg, arrival_ns, None, str(err))


@dataclass(frozen=True)
class Probe:
    """What the rest of the pipeline knows about the inputs of the oldest queued frame.

    Attributes:
        engine: an engine exists (a valid camera_info arrived).
        camera_failed: the last camera_info was invalid (no use waiting for one).
        covered: the IMU covers the interval from the previous frame to this one.
        passed: the IMU already passed the frame's stamp (it cannot become covered).
        imu_live: an IMU message arrived recently (the IMU is not silent).
    """

    engine: bool
    camera_failed: bool = False
    covered: bool = False
    passed: bool = False
    imu_live: bool = False


class StampGaps:
    """Images missing between the received ones, from their header stamps.

    A stamp more than ``factor`` times the median of the last ``window`` intervals after
    the previous one implies ``round(gap / median) - 1`` missing images: lost before the
    node (the camera driver, or the transport: see ``bags.dds`` for images over 512 KiB on
    Fast DDS). The median follows a camera whose rate changes within about half the
    window. A stamp not after the previous one (a replay loop, a time jump) or more than
    ``max_gap_ns`` after it starts over without counting.

    Args:
        window: intervals in the median (>= 3).
        factor: a gap counts when it exceeds this many median intervals (> 1).
        max_gap_ns: longer gaps are pauses, not losses, ns.
    """

    def __init__(self, window: int = 31, factor: float = 1.5, max_gap_ns: int = 2_000_000_000):
        self._intervals: collections.deque[int] = collections.deque(maxlen=window)
        self._factor = float(factor)
        self._max_gap_ns = int(max_gap_ns)
        self._last: int | None = None

    def see(self, stamp_ns: int | None) -> int:
        """The images missing just before this stamp (0 while too few intervals are
        known to judge)."""
        if stamp_ns is None:
            return 0
        last, self._last = self._last, stamp_ns
        if last is None or stamp_ns <= last or stamp_ns - last > self._max_gap_ns:
            self._intervals.clear()
            return 0
        gap = stamp_ns - last
        missing = 0
        if len(self._intervals) >= 3:
            median = sorted(self._intervals)[len(self._intervals) // 2]
            if gap > self._factor * median:
                missing = max(round(gap / median) - 1, 1)
        self._intervals.append(gap)
        return missing


class FrameQueue:
    """The bounded frame queue (thread-safe; the newest frame wins when it is full).

    Args:
        capacity: most frames held (>= 1).
    """

    def __init__(self, capacity: int) -> None:
        self._lock = threading.Lock()
        self._frames: collections.deque[Frame] = collections.deque()
        self._capacity = int(capacity)
        self._received = 0
        self._dropped = 0
        self._gaps = StampGaps()
        self._missing = 0

    def put(self, frame: Frame) -> None:
        """Append a frame; drop the oldest when full."""
        with self._lock:
            self._received += 1
            self._missing += self._gaps.see(frame.stamp_ns)
            self._frames.append(frame)
            self._trim()

    def resize(self, capacity: int) -> None:
        """A new capacity; the oldest frames beyond it are dropped (and counted)."""
        with self._lock:
            self._capacity = int(capacity)
            self._trim()

    def _trim(self) -> None:
        while len(self._frames) > self._capacity:
            self._frames.popleft()
            self._dropped += 1

    @property
    def capacity(self) -> int:
        """Most frames held."""
        return self._capacity

    def head(self) -> Frame | None:
        """The oldest frame, or None."""
        with self._lock:
            return self._frames[0] if self._frames else None

    def tail(self) -> Frame | None:
        """The newest frame, or None."""
        with self._lock:
            return self._frames[-1] if self._frames else None

    def drop_head(self, frame: Frame) -> None:
        """Drop ``frame`` if it is still the oldest, counted as a drop (newest wins)."""
        with self._lock:
            if self._frames and self._frames[0] is frame:
                self._frames.popleft()
                self._dropped += 1

    def remove_head(self, frame: Frame) -> bool:
        """Remove ``frame`` if it is still the oldest (a put may have dropped it meanwhile)."""
        with self._lock:
            if self._frames and self._frames[0] is frame:
                self._frames.popleft()
                return True
            return False

    def take_where(self, keep: Callable[[Frame], bool]) -> list[Frame]:
        """Remove and return, in order, the frames for which ``keep`` is true."""
        with self._lock:
            taken = [f for f in self._frames if keep(f)]
            if taken:
                self._frames = collections.deque(f for f in self._frames if not keep(f))
            return taken

    def counts(self) -> tuple[int, int]:
        """(frames put, frames dropped) since the last call."""
        with self._lock:
            out = (self._received, self._dropped)
            self._received = self._dropped = 0
            return out

    def missing(self) -> int:
        """Images missing between the stamps put (:class:`StampGaps`) since the last call."""
        with self._lock:
            out, self._missing = self._missing, 0
            return out

    def __len__(self) -> int:
        with self._lock:
            return len(self._frames)


class Scheduler:
    """The frame queue and the readiness rule (see the module docstring).

    Args:
        capacity: frames queued at most (``queue_size``).
        imu_wait_s: longest wait of a frame for its IMU (or camera_info), s.
        clock: the current time, ns, on the clock of the frames' arrival times.
        skip_stale: live: process the newest frame the IMU covers, dropping older ones
            (module docstring).
    """

    def __init__(
        self,
        capacity: int,
        imu_wait_s: float,
        clock: Callable[[], int],
        skip_stale: bool = False,
    ) -> None:
        self.queue = FrameQueue(capacity)
        self.clock = clock
        self.skip_stale = skip_stale
        self._wait_ns = round(imu_wait_s * 1e9)

    def configure(self, capacity: int, imu_wait_s: float) -> None:
        """New queue capacity and wait (frames beyond the capacity are dropped)."""
        self._wait_ns = round(imu_wait_s * 1e9)
        self.queue.resize(capacity)

    def put(self, msg: Any, arrival_ns: int) -> None:
        """Queue an image (thread-safe)."""
        self.queue.put(Frame.of(msg, arrival_ns))

    def ready(self, frame: Frame, probe: Probe, now_ns: int) -> bool:
        """The readiness rule for the oldest queued frame (without ``flush``)."""
        waited = now_ns - frame.arrival_ns >= self._wait_ns
        if not probe.engine:
            return probe.camera_failed or waited
        if frame.stamp_ns is None or probe.covered:
            return True
        full = len(self.queue) >= self.queue.capacity > 1
        return waited or probe.passed or full or not probe.imu_live

    def take(
        self, probe: Callable[[Frame], Probe], flush: bool = False
    ) -> tuple[Frame, Probe] | None:
        """Remove and return the oldest frame with its probe if it is ready, else None.

        Args:
            probe: what the pipeline knows about a frame's inputs (asked for the head).
            flush: every frame is ready.
        """
        while True:
            frame = self.queue.head()
            if frame is None:
                return None
            found = probe(frame)
            if not flush and not self.ready(frame, found, self.clock()):
                return None
            if self.skip_stale and not flush and self._newer_is_covered(frame, probe):
                self.queue.drop_head(frame)
                continue
            if self.queue.remove_head(frame):
                return frame, found

    def _newer_is_covered(self, frame: Frame, probe: Callable[[Frame], Probe]) -> bool:
        newest = self.queue.tail()
        if newest is None or newest is frame or newest.stamp_ns is None:
            return False
        return probe(newest).covered

    def deadline_ns(self) -> int | None:
        """When the oldest queued frame stops waiting (clock time, ns), or None."""
        frame = self.queue.head()
        return None if frame is None else frame.arrival_ns + self._wait_ns
