"""The dense stage in a child process: the same arrays as in the node's own thread, bad
input said and survived, the child's life bound to its handle."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bags.cli import make_bag
from owl_ros.dense_outputs import TOPICS, DenseStage
from owl_ros.dense_worker import DenseProcess, DenseProcessError, message_arrays, summarize
from owl_ros.params import build_options

OPTIONS = {"dense": True, "dense_width": 80, "dense_height": 60}


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("dense_worker") / "street"
    args = ["street", str(out), "--seconds", "0.4", "--width", "160", "--height", "120"]
    assert make_bag.main([*args, "--quiet", "--seed", "3"]) == 0
    return out


def _jobs(outs: list[Any], stage: DenseStage) -> list[Any]:
    jobs = [stage.begin(engine, camera, out.image, out.result) for out, engine, camera in outs]
    return [j for j in jobs if j is not None]


def _third_frame(bag: Path, pipeline_outputs: Any) -> tuple[DenseStage, Any]:
    """A dense stage with :data:`OPTIONS` and its job for the bag's third frame (the first
    frame gives none: there is no flow yet)."""
    options = build_options(OPTIONS)
    stage = DenseStage(options)
    return stage, _jobs(pipeline_outputs(bag, options)[:3], stage)[-1]


def test_the_process_gives_the_arrays_and_summary_of_the_thread(
    bag: Path, pipeline_outputs: Any
) -> None:
    options = build_options(OPTIONS)
    stage = DenseStage(options)
    jobs = _jobs(pipeline_outputs(bag, options), stage)
    assert len(jobs) >= 8
    proc = DenseProcess()
    try:
        for job in jobs:
            here = job.measure()
            kind, summary, arrays = proc.measure(stage.request(job, 2.5, frozenset(TOPICS)))
            assert kind == "ok"
            ours = summarize(here)
            # repr: exact floats, and NaN (no time to contact) equal to NaN
            assert repr(replace(summary, total_s=0.0)) == repr(replace(ours, total_s=0.0))
            expected = message_arrays(here, 2.5, options.dense_cloud_stride, TOPICS.__contains__)
            assert set(arrays) == set(expected) == set(TOPICS) - {"owl/depth/camera_info"}
            for topic, want in expected.items():
                assert arrays[topic].dtype == want.dtype, topic
                assert np.array_equal(arrays[topic], want, equal_nan=want.dtype.names is None)
        assert np.count_nonzero(np.isfinite(arrays["owl/range_over_speed"])) > 0
        assert proc.starts == 1
    finally:
        assert proc.close() == 0  # the child ends when its handle closes


def test_only_the_asked_topics_cross(bag: Path, pipeline_outputs: Any) -> None:
    stage, job = _third_frame(bag, pipeline_outputs)
    proc = DenseProcess()
    try:
        kind, _, arrays = proc.measure(stage.request(job, None, frozenset({"owl/looming"})))
    finally:
        proc.close()
    assert kind == "ok" and set(arrays) == {"owl/looming"}
    assert arrays["owl/looming"].shape == (60, 80)


def test_bad_input_is_one_line_and_the_process_goes_on(bag: Path, pipeline_outputs: Any) -> None:
    stage, job = _third_frame(bag, pipeline_outputs)
    proc = DenseProcess()
    try:
        good = stage.request(job, None, frozenset(TOPICS))
        bad = replace(good, inputs=replace(good.inputs, rotation=np.full((3, 3), np.nan)))
        kind, line, arrays = proc.measure(bad)
        assert kind == "error" and arrays is None
        assert line.startswith("dense: rotation must be a finite (3, 3) matrix"), line
        assert "\n" not in line
        kind, _, arrays = proc.measure(good)
        assert kind == "ok" and proc.starts == 1
    finally:
        proc.close()


def test_a_child_that_cannot_start_is_said(bag: Path, pipeline_outputs: Any) -> None:
    stage, job = _third_frame(bag, pipeline_outputs)
    proc = DenseProcess(python="/nonexistent/python3")
    with pytest.raises(DenseProcessError, match="could not start the dense process"):
        proc.measure(stage.request(job, None, frozenset(TOPICS)))
    assert proc.close() is None
