"""Issue 7, bad bags: every CLI that reads a bag (owl_process, owl_replay, owl_eval) against
the same damaged inputs: a directory that is no bag, an empty directory, a file with the
MCAP magic and garbage after it, a bag cut at 2/3 (a killed recorder), a bag whose last
third is overwritten with garbage, and a bag without the image topic.

Each must exit non-zero with exactly one line on stderr naming the problem and the path,
no traceback; owl_process keeps the frames before the damage, owl_eval scores the readable
part of a damaged result bag. The CLIs run in this process (their ``main``): an exception
escaping ``main`` fails the test as a traceback would.
"""

from __future__ import annotations

import json
import random
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from bags.cli import make_bag, replay
from bags.io import BagReader, BagWriter
from owl_ros import process
from owl_ros.tools import evaluate

IMAGE = "/camera/image_raw"
MAGIC = b"\x89MCAP0\r\n"


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A mover truth bag (160x120, 1 s), its owl_process result with the inputs copied
    (several MCAP chunks, so a cut leaves whole chunks), and damaged copies."""
    root = tmp_path_factory.mktemp("robust_bags")
    truth = root / "truth"
    args = ["mover", str(truth), "--seconds", "1", "--width", "160", "--height", "120"]
    assert make_bag.main([*args, "--quiet", "--seed", "3"]) == 0
    result = root / "result"
    assert process.main([str(truth), "-o", str(result), "--copy-inputs", "-q"]) == 0
    out = {"truth": truth, "result": result}
    for name in ("truth", "result"):
        out[f"{name}_cut"] = _damaged(out[name], root / f"{name}_cut", _cut)
        out[f"{name}_tail"] = _damaged(out[name], root / f"{name}_tail", _garbage_tail)
        out[f"{name}_flip"] = _damaged(out[name], root / f"{name}_flip", _flipped_bit)
    nobag = root / "photos"
    nobag.mkdir()
    (nobag / "notes.txt").write_text("not a bag\n")
    out["nobag"] = nobag
    (root / "empty").mkdir()
    out["empty"] = root / "empty"
    junk = root / "junk.mcap"
    junk.write_bytes(MAGIC + random.Random(0).randbytes(4000))
    out["junk"] = junk
    out["no_image"] = _without(truth, root / "no_image", IMAGE)
    return out


def _cut(data: bytes) -> bytes:
    return data[: len(data) * 2 // 3]


def _garbage_tail(data: bytes) -> bytes:
    k = len(data) * 2 // 3
    return data[:k] + random.Random(1).randbytes(len(data) - k)


def _flipped_bit(data: bytes) -> bytes:
    """One bit changed at two thirds of the file, inside a message: the structure (record
    lengths, indexes, summary) stays intact, only the chunk checksum tells."""
    k = len(data) * 2 // 3
    return data[:k] + bytes([data[k] ^ 0x10]) + data[k + 1 :]


def _damaged(src: Path, dst: Path, how: Callable[[bytes], bytes]) -> Path:
    shutil.copytree(src, dst)
    (mcap,) = dst.glob("*.mcap")
    mcap.write_bytes(how(mcap.read_bytes()))
    return dst


def _without(src: Path, dst: Path, topic: str) -> Path:
    """A copy of ``src`` without ``topic`` (every other message byte for byte)."""
    with BagReader(src) as reader, BagWriter(dst) as writer:
        for name, info in reader.topics.items():
            if name != topic:
                writer.add_topic(name, info.msgtype, qos=info.qos_kind)
        for raw in reader.messages([t for t in reader.topics if t != topic]):
            writer.write_raw(raw.topic, raw.log_time_ns, raw.data)
    return dst


def one_line(capsys: pytest.CaptureFixture[str], prog: str, *needles: str) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{prog}: error: ") and "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


NOT_A_BAG = [
    ("nobag", "not a bag"),
    ("empty", "not a bag"),
    ("junk", "junk.mcap"),
    ("truth_cut", "truncated or corrupt"),
    ("truth_tail", "truncated or corrupt"),
    ("truth_flip", "checksum"),
]


@pytest.mark.parametrize(("name", "needle"), NOT_A_BAG)
def test_replay_damaged_bag_one_line(bags, capsys, name, needle):
    assert replay.main([str(bags[name]), "-q"]) == 1
    one_line(capsys, "owl_replay", needle, bags[name].name)


def test_replay_bag_without_the_image_topic_one_line(bags, capsys):
    topics = ["--topics", IMAGE, "/imu/data", "/camera/camera_info"]
    assert replay.main([str(bags["no_image"]), *topics, "-q"]) == 1
    one_line(capsys, "owl_replay", f"topic {IMAGE} is not in bag", "no_image")


@pytest.mark.parametrize(("name", "needle"), NOT_A_BAG[:3])
def test_process_not_a_bag_one_line_no_output(bags, capsys, tmp_path, name, needle):
    assert process.main([str(bags[name]), "-o", str(tmp_path / "out"), "-q"]) == 1
    one_line(capsys, "owl_process", needle)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name", ["truth_cut", "truth_tail", "truth_flip"])
def test_process_damaged_bag_keeps_the_frames_before_the_damage(bags, capsys, tmp_path, name):
    out = tmp_path / "out"
    assert process.main([str(bags[name]), "-o", str(out), "-q"]) == 1
    line = one_line(capsys, "owl_process", "truncated or corrupt", name)
    assert "frames before the damage" in line
    with BagReader(bags["result"]) as full, BagReader(out) as kept:
        n_full = full.topics["/owl/points"].count
        n_kept = kept.topics["/owl/points"].count
    assert 0 < n_kept < n_full


def test_process_bag_without_the_image_topic_one_line(bags, capsys, tmp_path):
    assert process.main([str(bags["no_image"]), "-o", str(tmp_path / "out"), "-q"]) == 1
    one_line(capsys, "owl_process", IMAGE, "no_image")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("name", "needle"), NOT_A_BAG)
def test_eval_damaged_truth_bag_one_line(bags, capsys, name, needle):
    assert evaluate.main([str(bags["result"]), "--truth", str(bags[name])]) == 2
    one_line(capsys, "owl_eval", needle, bags[name].name)


@pytest.mark.parametrize(("name", "needle"), NOT_A_BAG[:3])
def test_eval_result_that_is_no_bag_one_line(bags, capsys, name, needle):
    assert evaluate.main([str(bags[name]), "--truth", str(bags["truth"])]) == 2
    one_line(capsys, "owl_eval", needle, bags[name].name)


@pytest.mark.parametrize("name", ["result_cut", "result_tail", "result_flip"])
def test_eval_damaged_result_scores_the_readable_part(bags, capsys, name):
    assert evaluate.main([str(bags["result"]), "--truth", str(bags["truth"]), "--json"]) == 0
    full = json.loads(capsys.readouterr().out)
    assert evaluate.main([str(bags[name]), "--truth", str(bags["truth"]), "--json"]) == 0
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    part = json.loads(captured.out)
    assert any("damaged" in note for note in part["notes"]), part["notes"]
    s, f = part["summary"], full["summary"]
    assert s["frames"] == f["frames"]  # every truth frame is scored ...
    assert 0 < s["heading_frames"] < f["heading_frames"]  # ... with fewer estimates
    # the frames that were read are scored exactly as in the full bag
    by_stamp = {fr["stamp_ns"]: fr for fr in full["frames"]}
    read = [fr for fr in part["frames"] if fr["has_heading"]]
    assert read and all(fr == by_stamp[fr["stamp_ns"]] for fr in read)


def test_eval_result_without_points_or_heading_one_line(bags, capsys):
    # the truth bag as a result bag: no /owl/points, no /owl/heading
    assert evaluate.main([str(bags["no_image"]), "--truth", str(bags["truth"])]) == 2
    one_line(capsys, "owl_eval", "/owl/points", "no_image")
