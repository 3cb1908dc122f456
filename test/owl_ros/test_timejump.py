"""owl_ros.timejump: the one detector of backwards time, for IMU batches and image stamps."""

from __future__ import annotations

import numpy as np

from owl_ros.timejump import ImageStamp, TimeJumps

MS = 1_000_000


def runs(jumps: TimeJumps, stamps_ms: list[int], finite: list[bool] | None = None) -> list:
    """[start, stop, jump stamp in ms or None] per run; resets at jumps as the pipeline
    does."""
    stamps = np.array(stamps_ms, dtype=np.int64) * MS
    ok = np.ones(stamps.size, bool) if finite is None else np.array(finite)
    out = []
    for run in jumps.imu_runs(stamps, ok):
        if run.jump is not None:
            jumps.reset()
        out.append([run.start, run.stop, run.jump and run.jump.stamp_ns // MS])
    return out


def test_out_of_order_within_tolerance_is_not_a_jump() -> None:
    jumps = TimeJumps(100 * MS)
    got = runs(jumps, [1000, 1010, 950, 1020])
    assert got == [[0, 4, None]]
    assert jumps.newest_imu_ns == 1020 * MS


def test_a_batch_is_cut_at_each_jump() -> None:
    jumps = TimeJumps(100 * MS)
    jumps.newest_imu_ns = 500 * MS
    got = runs(jumps, [510, 520, 100, 110, 120, 5, 6])
    assert got == [[0, 2, None], [2, 5, 100], [5, 7, 5]]
    assert jumps.newest_imu_ns == 6 * MS


def test_jump_at_the_first_sample_and_its_text() -> None:
    jumps = TimeJumps(100 * MS)
    jumps.newest_imu_ns = 2000 * MS
    stamps = np.array([500, 510], dtype=np.int64) * MS
    (run,) = list(jumps.imu_runs(stamps, np.ones(2, bool)))
    assert (run.start, run.stop) == (0, 2)
    assert run.jump is not None and run.jump.before_ns == 600 * MS
    assert run.jump.what == (
        f"IMU stamp went back 1.500 s ({500 * MS} ns after {2000 * MS} ns): engine reset"
    )


def test_non_finite_samples_never_count() -> None:
    jumps = TimeJumps(100 * MS)
    jumps.newest_imu_ns = 1000 * MS
    # a NaN sample far back is not a jump, and a NaN sample far ahead does not raise the
    # newest stamp (so what follows is no jump either)
    got = runs(jumps, [10, 5000, 1010], finite=[False, False, True])
    assert got == [[0, 3, None]]
    assert jumps.newest_imu_ns == 1010 * MS


def test_newest_advances_after_each_run_is_handled() -> None:
    jumps = TimeJumps(100 * MS)
    seen = []
    stamps = np.array([1000, 1100, 10, 20], dtype=np.int64) * MS
    for run in jumps.imu_runs(stamps, np.ones(4, bool)):
        seen.append(jumps.newest_imu_ns)  # what the pipeline sees while handling the run
        if run.jump is not None:
            jumps.reset()
    assert seen == [None, 1100 * MS]
    assert jumps.newest_imu_ns == 20 * MS


def test_image_stamps() -> None:
    jumps = TimeJumps(100 * MS)
    assert jumps.check_image(5) is ImageStamp.NEXT  # nothing processed yet
    jumps.image_processed(1000 * MS)
    assert jumps.check_image(1001 * MS) is ImageStamp.NEXT
    assert jumps.check_image(1000 * MS) is ImageStamp.DUPLICATE
    # back by up to the tolerance: out of order (skipped); further: a jump
    assert jumps.check_image(999 * MS) is ImageStamp.OUT_OF_ORDER
    assert jumps.check_image(900 * MS) is ImageStamp.OUT_OF_ORDER
    assert jumps.check_image(900 * MS - 1) is ImageStamp.BACKWARDS
    jump = jumps.image_jump(400 * MS)
    assert jump.what == (
        f"image stamp went back 0.600 s ({400 * MS} ns after {1000 * MS} ns): engine reset"
    )
    jumps.forget_image()
    assert jumps.check_image(1 * MS) is ImageStamp.NEXT
