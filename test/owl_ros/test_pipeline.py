"""owl_ros.pipeline: the message -> engine -> message path, fed with rendered frames.

The inputs are real rclpy messages built from an in-memory rendered scenario (bags.sim.scenarios)
with the msg_adapters; arrival times are the stamps (a perfectly punctual sensor), and the
pipeline's clock is a :class:`ManualClock` the test sets to each arrival.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pytest
from geometry_msgs.msg import TwistStamped

from bags.sim import scenarios
from bags.sim.scenarios import CAMERA_FRAME, IMU_FRAME, SimOptions
from msg_adapters.camera_info import camera_model_to_info
from msg_adapters.diagnostics import Level
from msg_adapters.image import array_to_image
from msg_adapters.imu import gyro_to_imus
from msg_adapters.pointcloud import OWL_FIELDS, cloud_speed, cloud_to_array
from msg_adapters.stamps import header_to_ns, make_header
from owl_core.types import PointFlag
from owl_ros.node import Control, Inbox
from owl_ros.node import feed as feed_inbox
from owl_ros.params import NodeOptions, build_options
from owl_ros.pipeline import Output, Pipeline
from owl_ros.roles import Role

WIDTH, HEIGHT = 320, 240
FRAME_NS = 33_333_333


@dataclass(frozen=True)
class Feed:
    """Rendered inputs as rclpy messages."""

    images: list[Any]  # sensor_msgs/Image, mono8
    info: Any  # sensor_msgs/CameraInfo
    imus: list[Any]  # sensor_msgs/Imu
    velocities: list[np.ndarray]  # camera velocity per frame, camera frame, m/s
    rotation: tuple[float, float, float, float]
    camera: Any


@pytest.fixture(scope="module")
def feed() -> Feed:
    sim = scenarios.get("street").simulate(
        SimOptions(seconds=0.6, width=WIDTH, height=HEIGHT, seed=3)
    )
    images, vels = [], []
    for frame in sim.frames():
        header = make_header(frame.stamp_ns, CAMERA_FRAME)
        images.append(array_to_image(frame.image, "mono8", header=header))
        vels.append(np.asarray(frame.velocity, dtype=np.float64))
    info = camera_model_to_info(sim.camera, make_header(int(sim.frame_stamps_ns[0]), CAMERA_FRAME))
    imus = gyro_to_imus(sim.gyro_samples(), IMU_FRAME)
    return Feed(images, info, imus, vels, sim.camera_to_imu_xyzw, sim.camera)


class ManualClock:
    """The pipeline's clock in these tests: the time is what the test last set, ns."""

    def __init__(self, now: int = 0) -> None:
        self.now = now

    def __call__(self) -> int:
        return self.now


def make(opts: NodeOptions) -> Pipeline:
    """A pipeline on a :class:`ManualClock` (``pipe.clock``)."""
    return Pipeline(opts, clock=ManualClock())


def at(pipeline: Pipeline, now: int) -> Pipeline:
    """Set the pipeline's clock to ``now``; returns the pipeline."""
    pipeline.clock.now = now  # type: ignore[attr-defined]
    return pipeline


def options(feed: Feed, **values: Any) -> Any:
    return build_options({"camera_to_imu_rotation_xyzw": list(feed.rotation), **values})


def events(
    feed: Feed,
    images: Iterable[Any] | None = None,
    imus: Iterable[Any] | None = None,
    info: Any | None = "default",
) -> list[tuple[int, Role, Any]]:
    """(arrival ns, role, msg) in time order; camera_info with every image."""
    out = []
    for img in feed.images if images is None else images:
        t = header_to_ns(img.header)
        out.append((t, Role.IMAGE, img))
        if info is not None:
            out.append((t, Role.CAMERA_INFO, feed.info if info == "default" else info))
    for imu in feed.imus if imus is None else imus:
        out.append((header_to_ns(imu.header), Role.IMU, imu))
    order = {Role.IMU: 0, Role.IMAGE: 1, Role.CAMERA_INFO: 2, Role.SPEED: 3}
    return sorted(out, key=lambda e: (e[0], order[e[1]]))


def run(
    pipeline: Pipeline, evs: Iterable[tuple[int, Role, Any]], flush: bool = True
) -> list[Output]:
    """Each message at its arrival time, then what is ready; at the end a flush."""
    outs: list[Output] = []
    for now, role, msg in evs:
        outs += at(pipeline, now).add(role, msg, now)
        outs += pipeline.poll()
    if flush:
        outs += pipeline.poll(flush=True)
    return outs


def diag(pipeline: Pipeline, name: str) -> tuple[str, dict[str, str], int]:
    recs = {r.name: r for r in pipeline.diagnostics(reset_window=False)}
    rec = recs[f"owl: {name}"]
    return rec.message, rec.value_map(), int(rec.level)


def with_points(outs: list[Output]) -> list[Output]:
    return [o for o in outs if o.result.num_points > 0]


def modified(msg: Any, **fields: Any) -> Any:
    """A copy of an Image message with some fields replaced."""
    out = type(msg)()
    for name in msg.get_fields_and_field_types():
        setattr(out, name, getattr(msg, name))
    for name, value in fields.items():
        setattr(out, name, value)
    return out


# ----------------------------------------------------------------------------- nominal


def test_nominal_every_frame_processed_header_kept_heading_right(feed: Feed) -> None:
    pipe = make(options(feed))
    outs = run(pipe, events(feed))
    assert len(outs) == len(feed.images)
    for out, img in zip(outs, feed.images, strict=True):
        assert out.cloud.header == img.header  # stamp and frame_id of the input image
        assert out.cloud.header.frame_id == CAMERA_FRAME
    good = with_points(outs)
    # a young track is fitted over the frames it has: every frame after the first gives points
    assert len(good) == len(feed.images) - 1
    names = [f.name for f in good[0].cloud.fields]
    assert names == [f[0] for f in OWL_FIELDS]
    for out in good:
        assert out.heading is not None and out.heading.header == out.header
        idx = [header_to_ns(i.header) for i in feed.images].index(header_to_ns(out.header))
        truth = feed.velocities[idx] / np.linalg.norm(feed.velocities[idx])
        err = math.acos(np.clip(out.result.heading @ truth, -1, 1))
        # within 5 stated sigmas (+0.3 deg: the truth is instantaneous, the fit spans 5 frames)
        assert err < 5 * out.result.heading_sigma_rad + math.radians(0.3)
        pts = cloud_to_array(out.cloud)
        assert cloud_speed(pts) is None and np.all(np.isnan(pts["speed"]))
    _, values, level = diag(pipe, "processing")
    assert values["frames_processed_total"] == str(len(feed.images))
    assert values["dropped_queue_full_total"] == "0"
    assert level == 0


# ----------------------------------------------------------------------------- bad images


@pytest.mark.parametrize(
    ("change", "expect"),
    [
        ({"encoding": "yuv422"}, "image.encoding 'yuv422'"),
        ({"step": WIDTH - 1}, f"image.step {WIDTH - 1}"),
        ({"height": HEIGHT - 1}, "image.data has"),
    ],
)
def test_bad_image_skipped_with_reason_and_processing_continues(
    feed: Feed, change: dict[str, Any], expect: str
) -> None:
    pipe = make(options(feed))
    images = list(feed.images)
    images[6] = modified(images[6], **change)
    outs = run(pipe, events(feed, images=images))
    assert len(outs) == len(images) - 1
    assert header_to_ns(images[6].header) not in [header_to_ns(o.header) for o in outs]
    msg, values, level = diag(pipe, "input")
    assert expect in values["last_bad_image"]
    assert values["bad_images_total"] == "1"
    assert level == 1 and expect in msg
    assert with_points(outs)[-1].header == images[-1].header  # kept running


def test_image_size_differing_from_camera_info(feed: Feed) -> None:
    pipe = make(options(feed))
    small = array_to_image(np.zeros((120, 160), np.uint8), "mono8", header=feed.images[0].header)
    run(pipe, events(feed, images=[small]))
    _, values, _ = diag(pipe, "input")
    assert "image size 160x120" in values["last_bad_image"]
    assert "camera_info 320x240" in values["last_bad_image"]


def test_images_lost_before_the_node_are_named(feed: Feed) -> None:
    # Every third image never arrives (as Fast DDS loses images over 512 KiB sent by UDP):
    # the pipeline counts them from the stamps and processes what it received.
    last = len(feed.images) - 1  # kept: a loss shows only before a later stamp
    images = [im for k, im in enumerate(feed.images) if k < 6 or k % 3 or k == last]
    lost = len(feed.images) - len(images)
    pipe = make(options(feed))
    outs = run(pipe, events(feed, images=images))
    assert len(outs) == len(images)
    msg, values, level = diag(pipe, "input")
    assert values["images_missing_total"] == str(lost)
    assert level == 1
    assert f"{lost} of {len(feed.images)} images missing between the received stamps" in msg
    assert "Fast DDS" not in msg  # 320x240 mono8 fits the default shared-memory segment
    # the full stream: nothing missing, no warning
    pipe = make(options(feed))
    run(pipe, events(feed))
    msg, values, level = diag(pipe, "input")
    assert values["images_missing_total"] == "0" and level == 0


# ----------------------------------------------------------------------------- camera_info


def test_no_camera_info_then_processing_starts(feed: Feed) -> None:
    pipe = make(options(feed))
    outs = run(pipe, events(feed, images=feed.images[:4], info=None))
    assert outs == []
    msg, _, level = diag(pipe, "input")
    assert level == 2 and "no camera_info received" in msg
    _, proc, _ = diag(pipe, "processing")
    # frames wait imu_wait_s for a camera_info just behind them (queue_size 2), then go
    skipped = int(proc["skipped_no_camera_info_total"])
    assert skipped >= 1 and skipped + int(proc["dropped_queue_full_total"]) == 4
    assert "no camera_info received yet" in proc["last_empty_reason"]
    outs = run(pipe, events(feed, images=feed.images[4:], imus=[]))
    assert len(outs) == len(feed.images) - 4


@pytest.mark.parametrize(
    ("field", "value", "expect"),
    [
        ("k", [0.0] * 9, "camera_info.k is all zero"),
        ("distortion_model", "fisheye_v9", "'fisheye_v9'"),
    ],
)
def test_invalid_camera_info_reported_until_a_valid_one(
    feed: Feed, field: str, value: Any, expect: str
) -> None:
    pipe = make(options(feed))
    bad = modified(feed.info, **{field: value})
    assert run(pipe, events(feed, images=feed.images[:3], info=bad)) == []
    msg, values, level = diag(pipe, "input")
    assert level == 2 and expect in values["camera_info_error"] and expect in msg
    assert pipe.engine is None
    outs = run(pipe, events(feed, images=feed.images[3:], imus=[]))
    # the image just before the valid camera_info finds the invalid one: skipped
    assert len(outs) == len(feed.images) - 4
    assert diag(pipe, "input")[1]["camera_info_error"] == ""


def test_zero_focal_length_rejected(feed: Feed) -> None:
    pipe = make(options(feed))
    k = list(feed.info.k)
    k[0] = 0.0
    run(pipe, events(feed, images=feed.images[:2], info=modified(feed.info, k=k)))
    _, values, _ = diag(pipe, "input")
    assert values["camera_info_error"].startswith("camera_info")
    assert pipe.engine is None


# ----------------------------------------------------------------------------- IMU


def test_no_imu_default_gives_no_points_with_reason(feed: Feed) -> None:
    pipe = make(options(feed))
    outs = run(pipe, events(feed, imus=[]))
    assert len(outs) == len(feed.images)
    assert with_points(outs) == []
    assert any("no gyro samples (require_gyro)" in r for r in outs[-1].result.reasons)
    assert diag(pipe, "gyro")[2] == 1


def test_no_imu_without_require_gyro_flags_every_point(feed: Feed) -> None:
    pipe = make(options(feed, require_gyro=False))
    outs = run(pipe, events(feed, imus=[]))
    good = with_points(outs)
    assert good, [o.result.reasons for o in outs]
    for out in good:
        flags = cloud_to_array(out.cloud)["flags"]
        assert np.all(flags & PointFlag.NO_GYRO)
        assert not np.any(flags & PointFlag.IMU_GAP)  # no samples at all, not a gap


def test_imu_gap_frames_flagged_or_skipped(feed: Feed) -> None:
    stamps = [header_to_ns(i.header) for i in feed.images]
    # no IMU from 5 ms after frame 8 to 5 ms before frame 10 (a 60 ms gap)
    t0, t1 = stamps[8] + 5_000_000, stamps[10] - 5_000_000
    imus = [m for m in feed.imus if not t0 < header_to_ns(m.header) < t1]
    pipe = make(options(feed))
    outs = run(pipe, events(feed, imus=imus))
    by_stamp = {header_to_ns(o.header): o for o in outs}
    assert len(outs) == len(stamps)
    for k in (9, 10):
        res = by_stamp[stamps[k]].result
        assert res.num_points == 0
        assert any("IMU does not cover the frame interval" in r for r in res.reasons)
    assert by_stamp[stamps[8]].result.num_points > 0
    # tracks need fit_frames covered frames again after the gap; then points return
    assert by_stamp[stamps[-1]].result.num_points > 0
    assert diag(pipe, "gyro")[1]["frames_imu_not_covered_total"] == "2"
    assert diag(pipe, "input")[1]["imu_gaps_total"] == "1"
    assert diag(pipe, "processing")[1]["dropped_queue_full_total"] == "0"
    # without require_gyro the gap frames give points flagged NO_GYRO | IMU_GAP
    pipe = make(options(feed, require_gyro=False))
    outs = {header_to_ns(o.header): o for o in run(pipe, events(feed, imus=imus))}
    flags = cloud_to_array(outs[stamps[9]].cloud)["flags"]
    assert flags.size and np.all(flags & PointFlag.IMU_GAP) and np.all(flags & PointFlag.NO_GYRO)
    later = cloud_to_array(outs[stamps[-1]].cloud)["flags"]
    assert later.size and not np.any(later & PointFlag.NO_GYRO)


def test_bad_imu_samples_dropped_and_counted(feed: Feed) -> None:
    imus = list(feed.imus)
    nan = modified(imus[50])
    nan.angular_velocity.x = math.nan
    imus[50] = nan
    evs = events(feed, imus=imus)
    # a duplicate and two stale (out-of-order) samples, delivered right after their originals
    extra = []
    for idx in (100, 150, 151):
        t = header_to_ns(imus[idx].header)
        extra.append((t + 1, Role.IMU, imus[idx] if idx == 100 else imus[idx - 10]))
    evs = sorted(evs + extra, key=lambda e: e[0])
    pipe = make(options(feed))
    outs = run(pipe, evs)
    _, values, level = diag(pipe, "input")
    assert values["imu_non_finite_total"] == "1"
    assert values["imu_duplicate_total"] == "1"
    assert values["imu_out_of_order_total"] == "2"
    assert level == 1
    assert len(with_points(outs)) == len(feed.images) - 1  # nothing else lost


# ----------------------------------------------------------------------------- time


def test_time_going_backwards_resets_engine(feed: Feed) -> None:
    pipe = make(options(feed))
    first = run(pipe, events(feed), flush=True)
    second = run(pipe, events(feed), flush=True)  # a bag loop: same stamps again
    _, values, level = diag(pipe, "processing")
    assert int(values["time_jumps_total"]) >= 1
    assert "engine reset" in values["last_time_jump"]
    assert level == 1
    # no stale tracks: the second pass warms up again like the first one
    assert [o.result.num_points > 0 for o in second] == [o.result.num_points > 0 for o in first]
    assert len(second) == len(feed.images)


def test_duplicate_image_stamp_skipped(feed: Feed) -> None:
    pipe = make(options(feed))
    images = [*feed.images[:6], feed.images[5], *feed.images[6:]]
    outs = run(pipe, events(feed, images=images))
    assert len(outs) == len(feed.images)
    assert diag(pipe, "processing")[1]["skipped_duplicate_stamp_total"] == "1"


def test_out_of_order_image_skipped_without_a_reset(feed: Feed) -> None:
    """A frame arriving after a later one (two drivers on one topic, a reordering bridge)
    by less than max_frame_gap_s is skipped, not a time jump: the tracks are kept and
    every other cloud is the one of the run without the stray frame."""
    clean = run(make(options(feed)), events(feed))
    pipe = make(options(feed))
    evs = events(feed)
    late = header_to_ns(feed.images[6].header)
    k = next(i for i, e in enumerate(evs) if e[0] > late)
    evs.insert(k, (late + 1, Role.IMAGE, feed.images[4]))  # frame 4 again, after frame 6
    outs = run(pipe, evs)
    _, values, _ = diag(pipe, "processing")
    assert values["skipped_out_of_order_total"] == "1"
    assert values["time_jumps_total"] == "0"
    assert [bytes(o.cloud.data) for o in outs] == [bytes(o.cloud.data) for o in clean]


def test_bounded_wait_for_imu(feed: Feed) -> None:
    pipe = make(options(feed, imu_wait_s=0.05))
    stamps = [header_to_ns(i.header) for i in feed.images]
    evs = [e for e in events(feed) if e[0] <= stamps[3]]
    run(pipe, evs, flush=False)
    # frame 4 arrives, but the IMU stops 10 ms before its stamp (IMU still live)
    at(pipe, stamps[4]).add_image(feed.images[4], stamps[4])
    assert pipe.poll() == []
    assert at(pipe, stamps[4] + 49_000_000).poll() == []  # still waiting
    assert pipe.deadline_ns() == stamps[4] + 50_000_000
    outs = at(pipe, stamps[4] + 50_000_000).poll()  # wait over: processed with what exists
    assert len(outs) == 1
    assert any("IMU does not cover" in r for r in outs[0].result.reasons)


def test_rolling_shutter_frame_waits_for_imu_up_to_its_last_row(feed: Feed) -> None:
    stamps = [header_to_ns(i.header) for i in feed.images]
    for readout, waits in ((0.0, False), (0.03, True)):
        pipe = make(options(feed, rolling_shutter_readout_s=readout, imu_wait_s=0.1))
        # the IMU up to 10 ms past frame 4: its rows reach 30 ms past it
        imus = [i for i in feed.imus if header_to_ns(i.header) <= stamps[4] + 10_000_000]
        outs = run(pipe, events(feed, images=feed.images[:5], imus=imus), flush=False)
        assert len(outs) == (4 if waits else 5)
        if waits:
            rest = [i for i in feed.imus if header_to_ns(i.header) > stamps[4] + 10_000_000]
            now = stamps[4] + 31_000_000
            at(pipe, now).add_imus(rest[:12], now)
            outs = pipe.poll()
            assert len(outs) == 1 and outs[0].result.num_points > 0


def test_calibration_check_switch(feed: Feed) -> None:
    pipe = make(options(feed, calibration_check=False))
    run(pipe, events(feed, images=feed.images[:3]), flush=True)
    assert pipe._calibration is None
    assert pipe.engine is not None and pipe.engine.online_calibration is None
    engine = pipe.engine
    # at runtime: the engine is rebuilt with its offset filter observing, for the check
    pipe.reconfigure(replace(pipe.options, calibration_check=True))
    assert pipe._calibration is not None and pipe.engine is not engine
    assert pipe.engine.online_calibration is not None
    assert pipe.engine.imu_time_offset_s == 0.0  # observed, not applied
    pipe.reconfigure(replace(pipe.options, calibration_check=False))
    assert pipe._calibration is None and pipe.calibration_verdict is None
    assert pipe.engine.online_calibration is None
    # with a rolling shutter the check's images refer to their middle row on average
    pipe = make(options(feed, imu_time_offset=0.01, rolling_shutter_readout_s=0.03))
    run(pipe, events(feed, images=feed.images[:2]), flush=True)
    assert pipe._calibration is not None
    assert pipe._calibration._offset == pytest.approx(0.025, abs=1e-12)


def test_newest_frame_wins_when_queue_full(feed: Feed) -> None:
    pipe = make(options(feed, queue_size=2))
    run(pipe, events(feed, images=feed.images[:2]), flush=True)
    imus = [m for m in feed.imus if header_to_ns(m.header) > header_to_ns(feed.images[1].header)]
    for imu in imus:
        pipe.add_imu(imu, 0)
    for img in feed.images[2:7]:  # five frames arrive while the worker is busy
        pipe.add_image(img, header_to_ns(img.header))
    assert pipe.pending == 2
    outs = at(pipe, header_to_ns(feed.images[6].header)).poll()
    assert [o.header for o in outs] == [feed.images[5].header, feed.images[6].header]
    assert diag(pipe, "processing")[1]["dropped_queue_full_total"] == "3"
    assert pipe.totals.images == 7 and pipe.totals.dropped_queue_full == 3


def test_inbox_bounded_in_order() -> None:
    inbox = Inbox(capacity=3)
    inbox.put(Control.OPTIONS, "first", 0)
    for k in range(1, 6):
        inbox.put(Role.IMU, k, k)
    inbox.put(Control.QOS, "text", 9)
    assert inbox.dropped == 2
    # what is kept comes out in the order it was put; a control entry is never dropped
    assert inbox.drain() == [
        (Control.OPTIONS, "first", 0),
        (Role.IMU, 3, 3),
        (Role.IMU, 4, 4),
        (Role.IMU, 5, 5),
        (Control.QOS, "text", 9),
    ]
    assert inbox.drain() == []


def test_feed_isolates_a_failing_entry(feed: Feed, monkeypatch: pytest.MonkeyPatch) -> None:
    """An entry that raises costs only itself: the IMU samples and the option change
    drained with it still reach the pipeline, and the option change reaches the dense
    stage's hook too."""
    pipe = make(options(feed))
    failing = pipe.note_qos_event

    def note(text: str) -> None:
        if text == "bad":
            raise RuntimeError("injected")
        failing(text)

    monkeypatch.setattr(pipe, "note_qos_event", note)
    new_opts = options(feed, queue_size=4)
    entries = [(Control.QOS, "bad", 0)]
    entries += [(Role.IMU, m, header_to_ns(m.header)) for m in feed.imus[:50]]
    entries += [(Control.OPTIONS, new_opts, 1), (Control.QOS, "good", 2)]
    errors: list[tuple[Any, Exception]] = []
    seen: list[NodeOptions] = []
    feed_inbox(pipe, entries, on_error=lambda k, e: errors.append((k, e)), on_options=seen.append)
    assert [(k, str(e)) for k, e in errors] == [(Control.QOS, "injected")]
    assert pipe.totals.imu == 50 and pipe.totals.qos_events == 1
    assert pipe.options is new_opts and seen == [new_opts]
    with pytest.raises(RuntimeError, match="injected"):  # without a handler: raised
        feed_inbox(pipe, [(Control.QOS, "bad", 3)])


def test_bag_loop_seen_late_by_a_busy_worker_resets_once(feed: Feed) -> None:
    """The node's worker drains the end of one loop and the start of the next at once (it
    was busy): the images went straight into the frame queue (8 deep here), the IMU into
    the inbox. The old loop's frames still queued when the new loop's IMU reveals the jump
    are processed first, with the IMU they had (all of it arrived before the jump), and the
    new loop's IMU samples are kept: one reset, every frame covered by the gyro, and the new
    loop warms up like the first pass. (Dropping the queued old frames at the jump would
    lose frames that had all they need.)"""
    pipe = make(options(feed, queue_size=8))
    inbox = Inbox()
    evs = events(feed)
    cut = [i for i, e in enumerate(evs) if e[1] is Role.IMAGE]
    late, resume = cut[-3], len(evs) + cut[3]  # last 3 old frames, first 3 new ones at once
    loop = evs * 2
    outs: list[Output] = []
    i = 0
    while i < len(loop):
        j = resume if i == late else i + 1
        for t, role, msg in loop[i:j]:  # what the callbacks do
            if role is Role.IMAGE:
                pipe.add_image(msg, t)
            else:
                inbox.put(role, msg, t)
        at(pipe, loop[j - 1][0])
        outs += feed_inbox(pipe, inbox.drain())  # what the worker does
        outs += pipe.poll()
        i = j
    outs += pipe.poll(flush=True)
    assert pipe.totals.time_jumps == 1
    assert pipe.totals.frames_imu_not_covered == 0
    assert pipe.totals.dropped_queue_full == 0
    stamps = [header_to_ns(o.header) for o in outs]
    back = next(k for k in range(1, len(outs)) if stamps[k] < stamps[k - 1])
    first, second = outs[:back], outs[back:]
    old = [header_to_ns(img.header) for img in feed.images]
    assert stamps[:back] == old  # the last 3 old frames processed before the reset
    assert stamps[back:] == old
    assert all(o.result.num_points > 0 for o in first[5:])
    # no stale tracks: the new loop warms up like the first, then every frame has points
    warm = [o.result.num_points > 0 for o in first].index(True)
    assert [o.result.num_points > 0 for o in second] == [False] * warm + [True] * (
        len(second) - warm
    )


def test_poll_limit_takes_one_frame_at_a_time(feed: Feed) -> None:
    """The node's worker takes one frame per step (and publishes it before the next): with
    three covered frames queued, poll(limit=1) gives them one by one, in order."""
    pipe = make(options(feed, queue_size=8))
    evs = events(feed)
    fourth = [i for i, e in enumerate(evs) if e[1] is Role.IMAGE][3]
    for t, role, msg in evs[:fourth]:  # 3 frames, their IMU
        pipe.add(role, msg, t)
    assert pipe.pending == 3
    at(pipe, evs[fourth - 1][0])
    got = []
    while pipe.pending:
        outs = pipe.poll(limit=1)
        assert len(outs) == 1
        got += outs
    assert pipe.poll(limit=1) == []
    assert [o.header for o in got] == [img.header for img in feed.images[:3]]
    pipe.record_cycle(0.025)
    assert diag(pipe, "processing")[1]["frame_cycle_ms_max"] == "25"


# ----------------------------------------------------------------------------- speed, debug


def _twist(stamp: int, v: np.ndarray) -> Any:
    msg = TwistStamped(header=make_header(stamp, CAMERA_FRAME))
    msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z = (float(x) for x in v)
    return msg


def test_speed_source_makes_cloud_metric(feed: Feed) -> None:
    pipe = make(options(feed, speed_source="twist"))
    stamps = [header_to_ns(i.header) for i in feed.images]
    speed_evs = [
        (t, Role.SPEED, _twist(t, v)) for t, v in zip(stamps, feed.velocities, strict=True)
    ]
    evs = sorted(events(feed) + speed_evs, key=lambda e: (e[0], e[1] is Role.IMAGE))
    outs = with_points(run(pipe, evs))
    assert outs
    for out in outs:
        speed = float(np.linalg.norm(feed.velocities[stamps.index(header_to_ns(out.header))]))
        pts = cloud_to_array(out.cloud)
        assert out.speed == pytest.approx(speed)
        assert cloud_speed(pts) == pytest.approx(speed, rel=1e-6)
        xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1)
        np.testing.assert_allclose(xyz, (out.result.points * speed).astype(np.float32))
    assert diag(pipe, "processing")[1]["frames_metric_total"] == str(len(outs))


def test_stale_speed_leaves_cloud_in_seconds(feed: Feed) -> None:
    pipe = make(options(feed, speed_source="twist", speed_max_age_s=0.01))
    old = header_to_ns(feed.images[0].header) - 10**9
    pipe.add_speed(_twist(old, np.array([0.0, 0.0, 4.0])))
    outs = with_points(run(pipe, events(feed)))
    assert outs and all(o.speed is None for o in outs)


def test_reconfigure_rebuilds_engine(feed: Feed) -> None:
    pipe = make(options(feed))
    run(pipe, events(feed, images=feed.images[:8]), flush=True)
    engine = pipe.engine
    pipe.reconfigure(replace(pipe.options, imu_wait_s=0.2))
    assert pipe.engine is engine  # node setting only: engine kept
    pipe.reconfigure(options(feed, max_features=200))
    assert pipe.engine is not engine and pipe.engine is not None
    assert pipe.engine.options.max_features == 200
    assert pipe.engine.gyro is engine.gyro is pipe.gyro  # the IMU history is kept, not copied
    assert len(pipe.gyro) > 0
    # a new extrinsic: the same samples, read through the new rotation
    pipe.reconfigure(options(feed, camera_to_imu_rotation_xyzw=[0.0, 0.0, 1.0, 0.0]))
    assert pipe.engine.gyro is pipe.gyro
    np.testing.assert_allclose(
        pipe.gyro.camera_to_imu_rotation, np.diag([-1.0, -1.0, 1.0]), atol=1e-12
    )


def test_draw_debug_marks_points_and_heading(feed: Feed) -> None:
    from msg_adapters.debug_image import draw_debug

    pipe = make(options(feed))
    out = with_points(run(pipe, events(feed)))[-1]
    picture = draw_debug(out.image, out.result, pipe.camera)
    assert picture.shape == (HEIGHT, WIDTH, 3) and picture.dtype == np.uint8
    foe = pipe.camera.bearing_to_pixel(out.result.heading[None])[0]
    u, v = np.rint(foe).astype(int)
    # the heading cross is pure green at the focus of expansion
    assert tuple(picture[v, u]) == (0, 255, 0)
    # points are coloured (grey pixels have equal channels)
    uv = np.rint(out.result.pixels).astype(int)
    coloured = picture[uv[:, 1], uv[:, 0]]
    assert np.mean(np.ptp(coloured, axis=1) > 0) > 0.9


def test_gyro_samples_before_camera_info_are_kept(feed: Feed) -> None:
    pipe = make(options(feed))
    for imu in feed.imus[:40]:
        pipe.add_imu(imu, header_to_ns(imu.header))
    pipe.add_camera_info(feed.info)
    assert pipe.engine is not None and len(pipe.engine.gyro) == 40
    assert pipe.engine.gyro is pipe.gyro


def test_compressed_png_gives_the_same_result_as_raw(feed: Feed) -> None:
    from msg_adapters.image import array_to_compressed, image_to_array

    compressed = [
        array_to_compressed(image_to_array(m), "mono8", "png", header=m.header)
        for m in feed.images[:10]
    ]
    raw = run(make(options(feed)), events(feed, images=feed.images[:10]))
    comp = run(make(options(feed, image_transport="compressed")), events(feed, images=compressed))
    assert len(raw) == len(comp) == 10
    for a, b in zip(raw, comp, strict=True):
        assert a.header == b.header
        assert bytes(a.cloud.data) == bytes(b.cloud.data)  # png is lossless


def test_rotation_only_no_points_reason_and_bias_keeps_updating() -> None:
    sim = scenarios.get("rotation_only").simulate(
        SimOptions(seconds=0.4, width=WIDTH, height=HEIGHT)
    )
    pipe = make(build_options({"camera_to_imu_rotation_xyzw": list(sim.camera_to_imu_xyzw)}))
    pipe.add_camera_info(camera_model_to_info(sim.camera, make_header(0, CAMERA_FRAME)))
    for imu in gyro_to_imus(sim.gyro_samples(), IMU_FRAME):
        pipe.add_imu(imu, 0)
    biases = []
    for frame in sim.frames():
        at(pipe, frame.stamp_ns).add_image(
            array_to_image(frame.image, "mono8", header=make_header(frame.stamp_ns, CAMERA_FRAME)),
            frame.stamp_ns,
        )
        (out,) = pipe.poll()
        assert out.result.num_points == 0 and out.heading is None
        _, values, _ = diag(pipe, "gyro")
        biases.append([float(values[f"bias_{a}_rad_s"]) for a in "xyz"])
    message, _, level = diag(pipe, "processing")
    assert level == 1 and message.startswith("no points: no translation")
    moves = np.abs(np.diff(np.array(biases[5:]), axis=0)).max(axis=1)
    assert np.all(moves > 0)  # the estimate changes every frame once tracks are long enough


def test_imu_publisher_disappears_and_comes_back(feed: Feed) -> None:
    """IMU silent for > 1 s (arrival time): frames are not held back, say why, and points
    return once the IMU is back, without a restart."""
    stamps = [header_to_ns(i.header) for i in feed.images]
    lost_from, back_at = stamps[7] + 1_000_000, stamps[10] + 1_000_000
    imus = [m for m in feed.imus if not lost_from < header_to_ns(m.header) < back_at]
    evs = []
    for t, role, msg in events(feed, imus=imus):
        silent_gap = 2_000_000_000 if t > lost_from else 0  # arrivals 2 s later
        evs.append((t + silent_gap, role, msg))
    pipe = make(options(feed))
    outs = []
    for now, role, msg in evs:
        got = at(pipe, now).add(role, msg, now)
        got += pipe.poll()
        if role is Role.IMAGE and header_to_ns(msg.header) in stamps[8:11]:
            # IMU silent for > 1 s: processed at once, not after imu_wait_s
            assert [o.header for o in got][-1:] == [msg.header]
            assert any("IMU does not cover" in r for r in got[-1].result.reasons)
        outs += got
    outs += pipe.poll(flush=True)
    assert len(outs) == len(stamps)
    assert outs[-1].result.num_points > 0  # recovered
    assert diag(pipe, "input")[1]["imu_gaps_total"] == "1"


def test_imu_batches_equal_single_messages(feed: Feed) -> None:
    """The node hands the IMU over in batches; the result must not depend on batching,
    bad samples inside a batch included."""
    imus = list(feed.imus)
    nan = modified(imus[60])
    nan.angular_velocity.y = math.inf
    imus[60] = nan
    imus.insert(90, imus[89])  # duplicate
    single = make(options(feed))
    outs_single = run(single, events(feed, imus=imus))
    batched = make(options(feed))
    outs_batched: list[Output] = []
    batch: list[tuple[Any, Any, int]] = []
    for now, role, msg in events(feed, imus=imus):
        batch.append((role, msg, now))
        if role is not Role.IMU:  # the worker wakes for each image: what came before
            outs_batched += feed_inbox(at(batched, now), batch)
            batch = []
            outs_batched += batched.poll()
    outs_batched += feed_inbox(batched, batch)
    outs_batched += batched.poll(flush=True)
    assert [bytes(o.cloud.data) for o in outs_batched] == [
        bytes(o.cloud.data) for o in outs_single
    ]
    for key in ("imu", "imu_non_finite", "imu_duplicate"):
        assert getattr(batched.totals, key) == getattr(single.totals, key) > 0


def test_a_worker_error_is_an_error_of_its_window_and_a_total() -> None:
    """An exception the node's worker survived outside the engine (publishing a frame's
    outputs, the dense hand-off) is said in ``owl: processing``: ERROR in the window it
    happened, with the newest text, and counted since start."""
    pipeline = make(build_options({}))
    at(pipeline, 1_000_000_000).start_window()
    pipeline.record_worker_error("worker: ValueError: a broken message")
    pipeline.record_worker_error("worker: KeyError: 'x'")
    at(pipeline, 2_000_000_000)
    recs = {r.name: r for r in pipeline.diagnostics()}
    rec = recs["owl: processing"]
    assert rec.level == Level.ERROR
    assert rec.message.endswith("; 2 worker errors, the last: worker: KeyError: 'x'")
    assert rec.value_map()["worker_errors_total"] == "2"
    at(pipeline, 3_000_000_000)
    rec = {r.name: r for r in pipeline.diagnostics()}["owl: processing"]
    assert rec.level != Level.ERROR and "worker errors" not in rec.message
    assert rec.value_map()["worker_errors_total"] == "2"


def test_an_engine_fault_resets_the_tracks_and_keeps_the_imu(
    feed: Feed, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An unexpected exception in one frame costs that frame and the tracks: the IMU history
    and the bias estimate stay (the next frames have points again at once, with no wait for
    new IMU); a second fault in a row resets the engine whole."""
    pipe = make(options(feed))
    evs = events(feed)
    starts = [i for i, e in enumerate(evs) if e[1] is Role.IMAGE]
    outs = run(pipe, evs[: starts[8]], flush=False)
    engine = pipe._engine
    assert engine is not None and with_points(outs)
    real = engine.process
    faults = iter([True, False, True, True])  # frame 8 fails; 9 ok; 10 and 11 fail

    def process(image: Any) -> Any:
        if next(faults, False):
            raise ZeroDivisionError("injected")
        return real(image)

    monkeypatch.setattr(engine, "process", process)
    samples = len(engine.gyro)
    outs = run(pipe, evs[starts[8] : starts[9]], flush=False)
    assert not outs
    message, values, _ = diag(pipe, "processing")
    assert values["skipped_engine_error_total"] == "1"
    assert "ZeroDivisionError: injected (tracks reset)" in message + str(values)
    assert engine.last_tracks is not None and len(engine.gyro) >= samples  # IMU kept
    # frames 9 (ok), 10 and 11 (two faults in a row): the second resets the IMU history too
    outs = run(pipe, evs[starts[9] : starts[11] + 1], flush=False)
    assert len(outs) == 1 and outs[0].result.num_points == 0  # frame 9 starts tracks anew
    assert len(pipe._engine.gyro) > 0
    outs += run(pipe, evs[starts[11] + 1 : starts[12]], flush=False)
    assert diag(pipe, "processing")[1]["skipped_engine_error_total"] == "3"
    assert len(engine.gyro) < samples  # emptied at frame 11, refilled only since
    outs = run(pipe, evs[starts[12] :], flush=True)
    assert with_points(outs)  # and it recovers
