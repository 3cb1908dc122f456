"""owl_ros.scheduler: the one bounded frame queue and the readiness rule, on a manual clock."""

from __future__ import annotations

import threading

from sensor_msgs.msg import Image

from msg_adapters.stamps import make_header
from owl_ros.scheduler import Frame, FrameQueue, Probe, Scheduler

MS = 1_000_000
WAIT_S = 0.05


class Clock:
    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        return self.now


def image(stamp_ns: int) -> Image:
    return Image(header=make_header(stamp_ns, "cam"))


def make(capacity: int = 3) -> tuple[Scheduler, Clock]:
    clock = Clock()
    return Scheduler(capacity, WAIT_S, clock), clock


COVERED = Probe(engine=True, covered=True, imu_live=True)
WAITING = Probe(engine=True, imu_live=True)  # not covered, IMU live and not past the stamp


def test_newest_wins_and_drops_are_counted_once() -> None:
    queue = FrameQueue(2)
    for k in range(5):
        queue.put(Frame.of(image(k * MS), k))
    assert [f.stamp_ns for f in queue.take_where(lambda f: True)] == [3 * MS, 4 * MS]
    assert queue.counts() == (5, 3)
    assert queue.counts() == (0, 0)  # handed over once
    queue.put(Frame.of(image(9), 9))
    queue.put(Frame.of(image(10), 10))
    queue.resize(1)
    assert len(queue) == 1 and queue.head().stamp_ns == 10
    assert queue.counts() == (2, 1)


def test_covered_frame_is_ready_at_once() -> None:
    sched, _ = make()
    sched.put(image(5 * MS), 0)
    frame, probe = sched.take(lambda f: COVERED)
    assert frame.stamp_ns == 5 * MS and probe is COVERED
    assert sched.take(lambda f: COVERED) is None  # empty


def test_uncovered_frame_waits_imu_wait_s_by_the_clock() -> None:
    sched, clock = make()
    clock.now = 100 * MS
    sched.put(image(5 * MS), clock.now)
    assert sched.deadline_ns() == 150 * MS
    clock.now = 149 * MS
    assert sched.take(lambda f: WAITING) is None
    assert len(sched.queue) == 1
    clock.now = 150 * MS  # the wait is over: taken with what exists
    got = sched.take(lambda f: WAITING)
    assert got is not None and got[1] is WAITING
    assert sched.deadline_ns() is None


def test_what_ends_the_wait_early() -> None:
    for probe in (
        Probe(engine=True, passed=True, imu_live=True),  # the IMU is already past the stamp
        Probe(engine=True, imu_live=False),  # the IMU is silent
    ):
        sched, _ = make()
        sched.put(image(5 * MS), 0)
        assert sched.take(lambda f, p=probe: p) is not None
    sched, _ = make(capacity=2)  # a full queue: the next frame is already there
    sched.put(image(5 * MS), 0)
    assert sched.take(lambda f: WAITING) is None
    sched.put(image(6 * MS), 0)
    assert sched.take(lambda f: WAITING)[0].stamp_ns == 5 * MS
    sched, _ = make(capacity=1)  # ... but not with a queue of one
    sched.put(image(5 * MS), 0)
    assert sched.take(lambda f: WAITING) is None
    assert sched.take(lambda f: WAITING, flush=True) is not None  # flush: always


def test_without_engine_waits_for_camera_info_unless_the_last_one_was_bad() -> None:
    sched, clock = make()
    sched.put(image(5 * MS), 0)
    assert sched.take(lambda f: Probe(engine=False)) is None
    assert sched.take(lambda f: Probe(engine=False, camera_failed=True)) is not None
    sched.put(image(6 * MS), 0)
    clock.now = 50 * MS
    assert sched.take(lambda f: Probe(engine=False)) is not None  # waited long enough


def test_unreadable_stamp_is_ready_at_once() -> None:
    sched, _ = make()
    bad = image(0)
    bad.header.stamp.nanosec = 2_000_000_000  # out of range
    sched.put(bad, 0)
    frame, _ = sched.take(lambda f: WAITING)
    assert frame.stamp_ns is None and "nanosec" in frame.stamp_error


def test_a_put_that_drops_the_head_while_it_is_probed() -> None:
    """The callback thread may drop the head between the probe and the take: the frame
    taken is then the one probed next, never one that was not probed."""
    sched, _ = make(capacity=1)
    sched.put(image(1 * MS), 0)
    probed = []

    def probe(frame: Frame) -> Probe:
        probed.append(frame.stamp_ns)
        if len(probed) == 1:  # a newer frame arrives meanwhile and drops this one
            sched.put(image(2 * MS), 0)
        return COVERED

    frame, _ = sched.take(probe)
    assert frame.stamp_ns == 2 * MS and probed == [1 * MS, 2 * MS]


def test_put_is_thread_safe() -> None:
    queue = FrameQueue(5)

    def producer(base: int) -> None:
        for k in range(2000):
            queue.put(Frame(None, base + k, base + k))

    threads = [threading.Thread(target=producer, args=(b,)) for b in (0, 10_000, 20_000)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    received, dropped = queue.counts()
    assert (received, dropped, len(queue)) == (6000, 5995, 5)


def test_stamp_gaps_count_the_images_missing_between_received_stamps() -> None:
    from owl_ros.scheduler import StampGaps

    gaps = StampGaps()
    period = 33 * MS
    stamps = [k * period for k in range(6)]  # 0..5: regular
    stamps += [8 * period, 9 * period]  # 6 and 7 missing
    stamps += [9 * period + 50 * MS]  # 1.5 periods: counts as one (rounded, at least 1)
    stamps += [9 * period + 60 * MS]  # a short interval (jitter) counts nothing
    assert [gaps.see(s) for s in stamps] == [0, 0, 0, 0, 0, 0, 2, 0, 1, 0]
    # too few intervals to judge: nothing counted after a restart
    fresh = StampGaps()
    assert [fresh.see(s) for s in (0, period, 5 * period)] == [0, 0, 0]
    # a stamp going back (replay loop) or a pause beyond max_gap_ns starts over
    assert gaps.see(0) == 0 and gaps.see(period) == 0 and gaps.see(10**12) == 0
    assert gaps.see(None) == 0
    # a camera switching from 30 to 15 Hz: counted until the median follows
    switch = StampGaps(window=7)
    t = [k * period for k in range(8)]
    t += [t[-1] + 2 * period * (k + 1) for k in range(8)]
    counted = [switch.see(s) for s in t]
    assert sum(counted) == 4 and counted[-4:] == [0, 0, 0, 0]


def test_queue_reports_missing_images_once() -> None:
    queue = FrameQueue(2)
    for k in (0, 1, 2, 3, 4, 6, 7):
        queue.put(Frame.of(image(k * 40 * MS), k))
    assert queue.missing() == 1
    assert queue.missing() == 0
    assert queue.counts() == (7, 5)  # unchanged: missing images were never received


def test_live_scheduler_processes_the_newest_covered_frame() -> None:
    # Two frames wait while the worker was busy; both are covered by the IMU. Live, the
    # older is dropped (counted) and the newest processed; offline both are, in order.
    for skip_stale, expect in ((True, [20 * MS]), (False, [10 * MS, 20 * MS])):
        clock = Clock()
        sched = Scheduler(2, WAIT_S, clock, skip_stale=skip_stale)
        sched.put(image(10 * MS), 0)
        sched.put(image(20 * MS), 1)
        taken = []
        while (got := sched.take(lambda f: COVERED)) is not None:
            taken.append(got[0].stamp_ns)
        assert taken == expect
        assert sched.queue.counts() == (2, 2 - len(expect))
    # the newest not yet covered: the ready older frame is processed
    sched = Scheduler(2, WAIT_S, Clock(), skip_stale=True)
    sched.put(image(10 * MS), 0)
    sched.put(image(20 * MS), 1)
    probes = {10 * MS: COVERED, 20 * MS: WAITING}
    got = sched.take(lambda f: probes[f.stamp_ns])
    assert got is not None and got[0].stamp_ns == 10 * MS
    # flush keeps every frame
    sched = Scheduler(2, WAIT_S, Clock(), skip_stale=True)
    sched.put(image(10 * MS), 0)
    sched.put(image(20 * MS), 1)
    assert sched.take(lambda f: COVERED, flush=True)[0].stamp_ns == 10 * MS
