"""make demo end to end on a tiny scenario: bag, owl_process, eval, baseline, figures, report."""

from __future__ import annotations

import json

import pytest

from owl_ros.tools import demo


@pytest.mark.slow
def test_demo_end_to_end(tmp_path, capsys):
    argv = [
        "--width",
        "160",
        "--height",
        "120",
        "--seconds",
        "0.5",
        "--out",
        str(tmp_path),
        "--quiet",
    ]
    assert demo.main(argv) == 0
    out = capsys.readouterr().out
    assert str(tmp_path / "report.md") in out
    report = (tmp_path / "report.md").read_text()
    assert "| heading error median (deg) |" in report
    assert "OWL (owl_process)" in report and "OpenCV 5-point" in report
    figures = [
        "shape_constancy",
        "complex_domain",
        "heading_error",
        "range_scatter",
        "scaled_cloud",
        "fields",
        "dense",
    ]
    for name in figures:
        png = tmp_path / "figures" / f"{name}.png"
        assert f"figures/{name}.png" in report
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    metrics = json.loads((tmp_path / "demo_metrics.json").read_text())
    owl = metrics["owl"]
    assert owl["frames"] == 16 and owl["heading_frames"] > 0
    # a 160x120 street with a 0.01 rad/s gyro bias: OWL's heading is still within a few deg
    assert owl["heading_deg_median"] < 5.0
    assert (tmp_path / "demo" / "owl" / "metadata.yaml").is_file()


def test_demo_bad_scenario_is_one_line(tmp_path, capsys):
    assert demo.main(["--scenario", "nowhere", "--out", str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nowhere" in err


def test_demo_refuses_a_result_folder_holding_other_files(tmp_path, capsys):
    """demo/owl and demo/input are replaced only when they hold a previous demo's bag: a
    folder with the user's files is refused in one line before any work (demo/owl used to
    be deleted with everything in it)."""
    for name in ("owl", "input"):
        folder = tmp_path / "demo" / name
        folder.mkdir(parents=True)
        (folder / "notes.txt").write_text("my notes\n")
        argv = ["--width", "64", "--height", "48", "--seconds", "0.2", "--no-cube"]
        assert demo.main([*argv, "--out", str(tmp_path), "--quiet"]) == 2
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert len(lines) == 1 and str(folder) in lines[0], lines
        assert "not a rosbag2 directory" in lines[0] and captured.out == ""
        assert (folder / "notes.txt").read_text() == "my notes\n"
        assert sorted(p.name for p in folder.iterdir()) == ["notes.txt"]
        (folder / "notes.txt").unlink()
        folder.rmdir()
    # refused before step 1: no input bag was rendered
    assert sorted(p.name for p in (tmp_path / "demo").iterdir()) == []


@pytest.mark.slow
@pytest.mark.dds
def test_demo_live_over_dds(tmp_path, capsys, ros_domain_env):
    """--live: owl_replay -> owl_node -> owl_record over DDS, then the same evaluation."""
    argv = [
        "--live",
        "--width",
        "160",
        "--height",
        "120",
        "--seconds",
        "0.5",
        "--no-cube",
        "--out",
        str(tmp_path),
        "--quiet",
    ]
    assert demo.main(argv) == 0
    metrics = json.loads((tmp_path / "demo_metrics.json").read_text())
    assert "owl_node over DDS" in metrics["how"]
    owl = metrics["owl"]
    # the node processed the replayed frames: headings for most of them, close to the truth
    assert owl["heading_frames"] >= 8
    assert owl["heading_deg_median"] < 5.0
    assert "owl_node over DDS" in (tmp_path / "report.md").read_text()


def test_demo_log_is_never_silent_for_long(capsys) -> None:
    import time

    log = demo._Log(2, quiet=False, heartbeat_s=0.2)
    log.start_heartbeat()
    log.step("a slow step")
    time.sleep(0.75)
    log.stop()
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].endswith("[1/2] a slow step")
    beats = [ln for ln in lines[1:] if ln.endswith("[1/2] still working")]
    assert 2 <= len(beats) == len(lines) - 1, lines
