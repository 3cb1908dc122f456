"""owl_ros.tools.compare: OWL against itself on the same frames, with real rendered frames."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from owl_ros.tools import compare

SMALL = ["--quick", "--cases", "street", "--seconds", "0.5", "--seeds", "2", "--quiet"]


def _run(capsys: pytest.CaptureFixture[str], tmp_path: Path, *args: str) -> dict:
    assert compare.main([*SMALL, "--cache-dir", str(tmp_path), "--json", *args]) == 0
    return json.loads(capsys.readouterr().out)


def test_a_setting_against_itself_gives_ratios_of_one(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # B sets the default value explicitly: the engine is deterministic, so every figure of
    # every seed is the same and every ratio exactly 1
    doc = _run(capsys, tmp_path, "-b", "tracker_lk_window_px:=15", "--size", "160x120")
    assert doc["image_size"] == "160x120"
    (row,) = doc["cases"]
    assert row["case"] == "street" and row["seeds"] == 2
    for name in compare.FIGURES:
        fig = row["figures"][name]
        assert fig["a"] is not None and fig["a"] == fig["b"]
        assert fig["ratio"] == 1.0 and fig["seed_ratios"] == [1.0, 1.0]
        assert fig["verdict"] == "same"
    assert doc["summary"]["same"] == 4 and doc["summary"]["geometric_mean_ratio"] == 1.0
    assert all(v > 0 for v in row["cpu_ms_per_frame"].values())


def test_a_different_setting_reports_b_over_a(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    doc = _run(capsys, tmp_path, "-b", "tracker_lk_deformation_correction:=false")
    (row,) = doc["cases"]
    figs = row["figures"]
    assert any(f["a"] != f["b"] for f in figs.values())  # the correction changes the tracks
    for f in figs.values():
        assert f["ratio"] == pytest.approx(f["b"] / f["a"], rel=1e-12)
        assert len(f["seed_ratios"]) == 2
    assert doc["b"] == {"tracker_lk_deformation_correction": False}
    assert sum(doc["summary"][v] for v in ("worse", "worse?", "better", "better?", "same")) == 4
    text = "\n".join(compare.report_lines(doc))
    assert "B: tracker_lk_deformation_correction:=False" in text and "street |" in text


def test_verdicts_weigh_the_seed_noise() -> None:
    # 10 % worse on every seed: beyond the tolerance and the seed-to-seed noise
    assert compare.verdict(1.10, [1.09, 1.10, 1.11, 1.10], 0.05) == "worse"
    # 10 % worse pooled, but the seeds disagree: within the noise
    assert compare.verdict(1.10, [0.8, 1.5, 0.9, 1.4], 0.05) == "worse?"
    assert compare.verdict(1.10, [1.10], 0.05) == "worse?"  # one seed: no noise estimate
    assert compare.verdict(0.90, [0.89, 0.90, 0.91], 0.05) == "better"
    assert compare.verdict(1.04, [1.04, 1.04], 0.05) == "same"
    assert compare.verdict(None, [None, None], 0.05) == "n/a"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ([], "give B's settings with -b"),
        (["-b", "tracker_lk_window_px:=14"], "tracker_lk_window_px"),
        (["-b", "no_such_setting:=1"], "no_such_setting"),
        (["-b", "tracker_lk_window_px:=13", "--seeds", "0"], "--seeds must be >= 1, got 0"),
        (["-b", "tracker_lk_window_px:=13", "--size", "640"], "size must be WxH"),
    ],
)
def test_bad_input_is_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, args: list[str], message: str
) -> None:
    try:  # a bad value of an option exits inside argparse, the rest returns
        status = compare.main(["--quick", "--cache-dir", str(tmp_path), *args])
    except SystemExit as stop:
        status = stop.code
    assert status == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
