"""Issue 7 rows not covered by test_pipeline.py, on the same rendered feed (its ``feed``
fixture and helpers): infinite gyro rates, and bad images of every kind in one stream."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from msg_adapters.image import array_to_image
from msg_adapters.stamps import header_to_ns

_spec = importlib.util.spec_from_file_location(
    "owl_test_pipeline_helpers", Path(__file__).with_name("test_pipeline.py")
)
assert _spec is not None and _spec.loader is not None
tp: Any = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = tp  # its dataclasses look their module up
_spec.loader.exec_module(tp)

feed = tp.feed  # the rendered 320x240 street feed (module fixture of test_pipeline)


@pytest.mark.parametrize("value", [math.inf, -math.inf])
def test_infinite_gyro_rates_dropped_and_counted(feed: Any, value: float) -> None:
    imus = list(feed.imus)
    for idx, axis in ((40, "x"), (80, "y"), (120, "z")):
        bad = tp.modified(imus[idx])
        setattr(bad.angular_velocity, axis, value)
        imus[idx] = bad
    pipe = tp.make(tp.options(feed))
    outs = tp.run(pipe, tp.events(feed, imus=imus))
    msg, values, level = tp.diag(pipe, "input")
    assert values["imu_non_finite_total"] == "3"
    assert "not finite" in values["last_imu_problem"] and "inf" in values["last_imu_problem"]
    assert level == 1 and "bad IMU samples dropped" in msg
    # one missing sample in 400 Hz is no gap: every frame as without the bad samples
    reference = tp.run(tp.make(tp.options(feed)), tp.events(feed))
    assert [o.result.num_points > 0 for o in outs] == [o.result.num_points > 0 for o in reference]
    for got, ref in zip(outs, reference, strict=True):
        if ref.result.heading is not None:
            assert got.result.heading is not None
            cos = float(np.clip(got.result.heading @ ref.result.heading, -1, 1))
            assert math.degrees(math.acos(cos)) < 3 * math.degrees(ref.result.heading_sigma_rad)


def test_every_kind_of_bad_image_in_one_stream(feed: Any) -> None:
    """Unknown encoding, short step, short data, a size differing from camera_info and an
    unsupported but valid encoding, each replacing one frame: each skipped with its
    reason, counted, every other frame processed."""
    images = list(feed.images)
    w, h = images[0].width, images[0].height
    bad = {
        4: tp.modified(images[4], encoding="yuv422"),
        7: tp.modified(images[7], step=w - 1),
        10: tp.modified(images[10], data=bytes(images[10].data)[: w * h // 2]),
        13: array_to_image(np.zeros((h // 2, w // 2), np.uint8), "mono8", images[13].header),
        16: tp.modified(images[16], encoding="32FC1", step=4 * w, data=bytes(4 * w * h)),
    }
    for k, msg in bad.items():
        images[k] = msg
    pipe = tp.make(tp.options(feed))
    outs = tp.run(pipe, tp.events(feed, images=images))
    done = {header_to_ns(o.header) for o in outs}
    assert len(outs) == len(images) - len(bad)
    assert not done & {header_to_ns(images[k].header) for k in bad}
    _, values, level = tp.diag(pipe, "input")
    assert values["bad_images_total"] == str(len(bad)) and level == 1
    assert "32FC1" in values["last_bad_image"]  # the last one, named
    assert tp.with_points(outs)[-1].header == images[-1].header  # kept running
