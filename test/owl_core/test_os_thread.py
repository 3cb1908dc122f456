"""owl_core.os_thread: the product's threads carry their names into the kernel's view."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from owl_core.os_thread import NAME_BYTES, name_os_thread
from owl_core.tracker import FeatureTracker, TrackerOptions

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl, /proc")


def _comm(tid: int) -> str:
    return Path(f"/proc/self/task/{tid}/comm").read_text().strip()


@linux
def test_a_thread_takes_its_python_name_or_the_one_given() -> None:
    seen: dict[str, object] = {}

    def run() -> None:
        seen["set"] = name_os_thread()
        seen["own"] = _comm(threading.get_native_id())
        name_os_thread("a-name-longer-than-fifteen-bytes")
        seen["cut"] = _comm(threading.get_native_id())

    t = threading.Thread(target=run, name="owl-test")
    t.start()
    t.join()
    assert seen == {"set": True, "own": "owl-test", "cut": "a-name-longer-than"[:NAME_BYTES]}
    assert _comm(threading.get_native_id()) != "owl-test"  # the caller's own name untouched


@linux
def test_the_tracker_s_detection_thread_is_named() -> None:
    rng = np.random.default_rng(0)
    img = (rng.random((120, 160)) * 255).astype(np.uint8)
    tracker = FeatureTracker(TrackerOptions(max_features=50, background_detection=True))
    for k in range(3):  # the first frame detects in place, later ones in the background
        tracker.track(img, k * 33_000_000)
    names = {p.read_text().strip() for p in Path("/proc/self/task").glob("*/comm")}
    assert "owl-detect_0" in names, names
