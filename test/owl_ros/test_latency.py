"""owl_latency's standard cases and their target checks (no DDS: the arithmetic only), its
command line, and the help of every tool's options."""

from __future__ import annotations

import argparse
from dataclasses import replace

import pytest

from bags.cli import make_bag
from owl_ros import process
from owl_ros.tools import bench, demo, latency, soak
from owl_ros.tools import evaluate as ev
from owl_ros.tools.latency import CASES, Measurement, median_measurement, meets


def _m(**kw: float) -> Measurement:
    base = Measurement(
        input_rate_hz=30.0,
        width=640,
        height=480,
        max_features=1000,
        images_sent=300,
        clouds=300,
        kept_up=1.0,
        latency_ms_p50=20.0,
        latency_ms_p95=30.0,
        latency_ms_max=40.0,
        cpu_percent=50.0,
        rss_mb=130.0,
        points_per_cloud=800.0,
    )
    return replace(base, **kw)


def test_cases_are_the_issue_inputs() -> None:
    assert (CASES["vga30"].width, CASES["vga30"].height, CASES["vga30"].rate_hz) == (640, 480, 30)
    assert (CASES["vga60"].width, CASES["vga60"].rate_hz) == (640, 60)
    assert (CASES["hd30"].width, CASES["hd30"].height) == (1280, 720)


def test_each_target_can_fail() -> None:
    vga30 = CASES["vga30"]
    assert meets(vga30, _m()) == {"kept_up": True, "latency_p95": True, "cpu": True}
    assert meets(vga30, _m(kept_up=0.99))["kept_up"] is False
    assert meets(vga30, _m(latency_ms_p95=33.5))["latency_p95"] is False
    assert meets(vga30, _m(cpu_percent=61.0))["cpu"] is False
    # hd30 has only the kept-up target
    assert meets(CASES["hd30"], _m(latency_ms_p95=500.0, cpu_percent=190.0)) == {"kept_up": True}


def test_median_over_runs() -> None:
    runs = [_m(latency_ms_p95=p, kept_up=k) for p, k in ((30.0, 1.0), (50.0, 0.9), (40.0, 0.95))]
    med = median_measurement(runs)
    assert med["latency_ms_p95"] == 40.0
    assert med["kept_up"] == 0.95
    dense = [_m(images_per_frame={"/owl/looming": f}) for f in (0.2, 0.5, 0.4)]
    assert median_measurement(dense)["images_per_frame /owl/looming"] == 0.4


def test_runs_must_be_positive(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as err:
        latency.main(["--case", "vga30", "--runs", "0"])
    assert err.value.code == 2
    assert "--runs must be >= 1, got 0" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["-p", "max_features:=250"], "-p max_features:=250: give the feature count as"),
        (["--case", "vga30", "-p", "max_features := 250"], "give the feature count as"),
        (["--case", "vga30", "--max-features", "0"], "--max-features must be >= 1, got 0"),
    ],
)
def test_the_feature_count_is_an_option_of_the_tool(
    argv: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """The tool sets max_features and records it in each measurement: a -p for it would
    win in the node and leave the record wrong, so it is refused (before anything runs)."""
    with pytest.raises(SystemExit) as err:
        latency.main(argv)
    assert err.value.code == 2
    out = capsys.readouterr().err
    assert says in out and out.count("\n") == 1


@pytest.mark.parametrize("module", [latency, process, ev, bench, demo, soak, make_bag])
def test_every_option_has_help(module) -> None:
    parser = module.build_parser()
    missing = [
        a.option_strings or a.dest
        for a in parser._actions
        if not isinstance(a, argparse._HelpAction) and not a.help
    ]
    assert missing == [], f"{parser.prog}: options without help: {missing}"


def test_latency_one_line_errors(capsys) -> None:
    with pytest.raises(SystemExit) as done:
        latency.build_parser().parse_args(["--rate", "x"])
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("owl_latency: error:")


def test_node_counts_cover_the_span_of_the_nodes_own_diagnostics() -> None:
    # Diagnostics at 1 Hz (times in ns); the window opens at 1.5 s. The span is from the
    # first snapshot inside the window (2 s) to the last (5 s); images published in it
    # are compared with what the node counted over the same span.
    def snap(t: float, images: int, dropped: int, processed: int, engine: float):
        return (
            round(t * 1e9),
            {
                "images_total": float(images),
                "dropped_queue_full_total": float(dropped),
                "frames_processed_total": float(processed),
                "processing_ms_mean": engine,
            },
        )

    snapshots = [
        snap(1.0, 30, 0, 30, 99.0),  # before the window: not used
        snap(2.0, 60, 5, 55, 40.0),
        snap(3.0, 90, 10, 80, 42.0),
        snap(4.0, 100, 12, 88, float("nan")),  # a window without frames
        snap(5.0, 120, 20, 100, 44.0),
    ]
    published = [round((1.9 + k / 30) * 1e9) for k in range(90)]  # 1.9 s .. 4.87 s
    got = latency._node_counts(snapshots, round(1.5e9), published)
    assert got == {
        "counted_sent": sum(1 for t in published if 2e9 < t <= 5e9),
        "node_images": 60,
        "node_dropped_queue": 15,
        "node_processed": 45,
        "node_engine_ms": 43.0,  # median of 42 and 44 (the first in-window one opens it)
    }
    assert latency._node_counts(snapshots[:2], round(1.5e9), published) == {}


def test_the_clip_covers_the_window_unless_asked_to_loop() -> None:
    # a looped clip jumps back to its first image inside the window: a scene cut a camera
    # never makes, so by default the clip lasts the warm-up and the window at the top speed
    parse = latency.build_parser().parse_args
    assert latency.clip_seconds(parse([])) == latency.WARMUP_S + 10.0 + 0.5
    assert latency.clip_seconds(parse(["--seconds", "4", "--speed", "1", "2"])) == 2 * (
        latency.WARMUP_S + 4.5
    )
    assert latency.clip_seconds(parse(["--speed", "3"]), 1.0) == latency.WARMUP_S + 10.5
    assert latency.clip_seconds(parse(["--clip-seconds", "2"])) == 2.0
