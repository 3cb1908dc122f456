"""owl_batch on a local Ray (one instance, 2 CPUs): three small bags and a broken one."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from bags.cli.make_bag import write_bag
from bags.sim import scenarios
from bags.sim.scenarios import SimOptions
from owl_ros.tools.batch import PROG, find_bags, main
from owl_ros.tools.evaluate import evaluate, summarize
from owl_ros.tools.latency import proc_tree


def _descendants(pid: int) -> set[int]:
    """Pids of every live process below ``pid`` (from /proc)."""
    return set(proc_tree(pid)[1:])


@pytest.mark.slow
def test_batch_table_equals_per_bag_eval_and_a_broken_bag_is_reported(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "bags"
    folder.mkdir()
    opts = SimOptions(seconds=0.6, rate_hz=30.0, width=320, height=240)
    for name in ("cube", "street", "receding"):
        write_bag(scenarios.get(name).simulate(opts), folder / name)
    (folder / "broken").mkdir()
    (folder / "broken" / "metadata.yaml").write_text("rosbag2_bagfile_information: [\n")
    assert [b.name for b in find_bags([str(folder)])] == ["broken", "cube", "receding", "street"]
    before = _descendants(os.getpid())
    out = tmp_path / "results"
    report_path = tmp_path / "report.json"
    rc = main([str(folder), "-o", str(out), "--num-cpus", "2", "--json", str(report_path), "-q"])
    assert rc == 1  # one bag failed
    # Ray stopped everything it started
    assert _descendants(os.getpid()) - before == set()
    table = capsys.readouterr().out
    report = json.loads(report_path.read_text())
    rows = {Path(r["bag"]).name: r for r in report["bags"]}
    broken = rows.pop("broken")
    assert not broken["ok"] and broken["attempts"] == 2
    assert "broken" in broken["error"] and "\n" not in broken["error"]
    assert "broken                   FAILED  " in table
    scores = []
    for name, row in rows.items():
        assert row["ok"] and row["scored"], row
        ev = evaluate(out / name, folder / name)  # what owl_eval --json prints
        expected = json.loads(json.dumps(ev.as_dict()))["summary"]
        assert row["summary"] == expected  # the table's numbers are owl_eval's
        s = expected
        line = next(t for t in table.splitlines() if t.startswith(name))
        assert f"{s['heading_deg_median']:.2f}/{s['heading_deg_p90']:.2f}" in line
        assert row["frames"] == s["frames"] == 19
        scores += ev.frames
    pooled = summarize(scores, False)
    for key, value in pooled.items():
        assert report["pooled"][key] == pytest.approx(value, nan_ok=True), key
    assert report["pooled"]["bags"] == 3
    assert report["ray"]["cpus"] == 2


def test_outputs_are_refused_before_ray_and_nothing_is_touched(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every output path is checked before Ray starts (each case returns in well under a
    second: a run would take tens): --json into an input bag used to replace its
    metadata.yaml after the whole run, and -o naming a file was a FileExistsError traceback."""
    folder = tmp_path / "bags"
    folder.mkdir()
    opts = SimOptions(seconds=0.2, rate_hz=10.0, width=64, height=48)
    write_bag(scenarios.get("cube").simulate(opts), folder / "cube")
    bag = folder / "cube"
    files = {p: p.read_bytes() for p in bag.iterdir()}
    report = tmp_path / "report.json"
    report.write_text("a previous report\n")
    a_file = tmp_path / "notes.txt"
    a_file.write_text("notes\n")
    out = tmp_path / "results"
    cases = [
        (["--json", str(bag / "metadata.yaml")], "the output is inside the input"),
        (["--json", str(bag)], "the output is the input"),
        (["--json", str(report)], "exists"),
        (["--json", str(out / "cube")], "the result bags are written there"),
        (["--json", str(tmp_path / "missing" / "r.json")], "does not exist"),
        (["-o", str(a_file)], "is not a directory"),
        (["-o", str(bag)], "inside the input"),  # the result bag cube/cube
    ]
    for extra, what in cases:
        argv = [str(folder), "-o", str(out), "-q", *extra]  # a later -o wins
        assert main(argv) == 2, extra
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"{PROG}: error:"), lines
        assert what in lines[0] and extra[1] in lines[0], lines
        assert captured.out == ""
    assert {p: p.read_bytes() for p in bag.iterdir()} == files
    assert report.read_text() == "a previous report\n" and a_file.read_text() == "notes\n"
    assert not out.exists() and not (tmp_path / "missing").exists()
