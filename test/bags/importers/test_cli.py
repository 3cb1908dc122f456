"""owl_import on malformed folders (one line, nothing written) and on the shared recordings."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bags.cli.importers.cli import main
from bags.io import BagReader
from owl_core.geometry import quat_xyzw_to_matrix


@pytest.fixture(scope="module")
def small_asl(tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest) -> Path:
    writer = request.getfixturevalue("asl_writer")
    return Path(writer(tmp_path_factory.mktemp("small") / "asl", rate=10.0, seconds=0.5).root)


@pytest.fixture(scope="module")
def small_kitti(tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest) -> Path:
    writer = request.getfixturevalue("kitti_writer")
    return Path(writer(tmp_path_factory.mktemp("small") / "00", rate=10.0, seconds=0.5).root)


def _first_data_line(path: Path) -> int:
    lines = path.read_text().splitlines()
    return next(i for i, t in enumerate(lines) if t and not t.startswith("#"))


def _edit_lines(path: Path, fn: Callable[[list[str]], list[str]]) -> None:
    path.write_text("\n".join(fn(path.read_text().splitlines())) + "\n")


def _swap_two(lines: list[str]) -> list[str]:
    k = next(i for i, t in enumerate(lines) if t and not t.startswith("#"))
    lines[k], lines[k + 1] = lines[k + 1], lines[k]
    return lines


def _drop_column(lines: list[str]) -> list[str]:
    k = next(i for i, t in enumerate(lines) if t and not t.startswith("#")) + 2
    lines[k] = lines[k].rsplit(",", 1)[0]
    return lines


def _break_asl(kind: str, root: Path) -> str:
    """Damage the folder; returns the file name the error line must mention."""
    mav0 = root / "mav0"
    if kind == "missing imu csv":
        (mav0 / "imu0" / "data.csv").unlink()
        return "imu0/data.csv"
    if kind == "missing sensor.yaml":
        (mav0 / "cam0" / "sensor.yaml").unlink()
        return "cam0/sensor.yaml"
    if kind == "missing image":
        victim = sorted((mav0 / "cam0" / "data").iterdir())[3]
        victim.unlink()
        return victim.name
    if kind == "unreadable image":  # found while writing: the bag being built is discarded
        victim = sorted((mav0 / "cam0" / "data").iterdir())[-1]
        victim.write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
        return victim.name
    if kind == "imu column count":
        _edit_lines(mav0 / "imu0" / "data.csv", _drop_column)
        return "imu0/data.csv"
    if kind == "ground-truth column count":
        _edit_lines(mav0 / "state_groundtruth_estimate0" / "data.csv", _drop_column)
        return "state_groundtruth_estimate0/data.csv"
    if kind == "image stamps out of order":
        _edit_lines(mav0 / "cam0" / "data.csv", _swap_two)
        return "cam0/data.csv"
    if kind == "imu stamps out of order":
        _edit_lines(mav0 / "imu0" / "data.csv", _swap_two)
        return "imu0/data.csv"
    if kind == "not a number":
        _edit_lines(
            mav0 / "imu0" / "data.csv",
            lambda ls: [*ls[:5], ls[5].replace(",", ",x", 1), *ls[6:]],
        )
        return "imu0/data.csv"
    raise AssertionError(kind)


def _break_kitti(kind: str, root: Path) -> str:
    if kind == "missing calib":
        (root / "calib.txt").unlink()
        return "calib.txt"
    if kind == "pose column count":
        _edit_lines(root / "poses.txt", lambda ls: [*ls[:2], ls[2].rsplit(" ", 1)[0], *ls[3:]])
        return "poses.txt"
    if kind == "times out of order":
        _edit_lines(root / "times.txt", _swap_two)
        return "times.txt"
    if kind == "fewer poses than images":
        _edit_lines(root / "poses.txt", lambda ls: ls[:-1])
        return "poses.txt"
    if kind == "unreadable image":
        (root / "image_0" / "000004.png").write_bytes(b"garbage")
        return "000004.png"
    if kind == "imu column count":
        _edit_lines(root / "imu.csv", _drop_column)
        return "imu.csv"
    raise AssertionError(kind)


def _one_line_and_nothing_written(
    capsys: pytest.CaptureFixture[str], rc: int, out: Path, names: str
) -> None:
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert rc == 1
    assert len(lines) == 1, cap.err
    assert lines[0].startswith("owl_import: error: ") and names in lines[0], lines[0]
    assert "Traceback" not in cap.err and cap.out == ""
    assert not out.exists()
    assert sorted(p.name for p in out.parent.iterdir()) == []  # no hidden temporary bag


ASL_CASES = [
    "missing imu csv",
    "missing sensor.yaml",
    "missing image",
    "unreadable image",
    "imu column count",
    "ground-truth column count",
    "image stamps out of order",
    "imu stamps out of order",
    "not a number",
]
KITTI_CASES = [
    "missing calib",
    "pose column count",
    "times out of order",
    "fewer poses than images",
    "unreadable image",
    "imu column count",
]


@pytest.mark.parametrize("kind", ASL_CASES)
def test_malformed_asl_folder(
    kind: str, small_asl: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "asl"
    shutil.copytree(small_asl, root)
    name = _break_asl(kind, root)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    rc = main([str(root), str(out_dir / "bag")])
    _one_line_and_nothing_written(capsys, rc, out_dir / "bag", name)


@pytest.mark.parametrize("kind", KITTI_CASES)
def test_malformed_kitti_folder(
    kind: str, small_kitti: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "00"
    shutil.copytree(small_kitti, root)
    name = _break_kitti(kind, root)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    rc = main([str(root), str(out_dir / "bag"), "-q"])
    _one_line_and_nothing_written(capsys, rc, out_dir / "bag", name)


def test_output_inside_or_equal_to_the_input_is_refused(
    small_asl: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "asl"
    shutil.copytree(small_asl, root)
    before = sorted(str(p) for p in root.rglob("*"))
    for out, how in ((root, "is"), (root / "mav0" / "bag", "is inside"), (tmp_path, "contains")):
        assert main([str(root), str(out), "--overwrite"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"refusing to write {out}: the output {how} the input" in err[0]
    assert sorted(str(p) for p in root.rglob("*")) == before


def test_bad_options_and_existing_output(
    small_asl: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    existing = tmp_path / "exists"
    existing.mkdir()
    (existing / "keep.txt").write_text("x")
    cases = [
        ([str(existing)], "exists"),
        ([str(tmp_path / "b"), "--every", "0"], "--every"),
        ([str(tmp_path / "b"), "--scale", "-1"], "--scale"),
        ([str(tmp_path / "b"), "--start", "100"], "keeps 0"),
    ]
    for extra, text in cases:
        assert main([str(small_asl), *extra]) in (1, 2)
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and text in err[0], err
    assert (existing / "keep.txt").read_text() == "x"
    assert not (tmp_path / "b").exists()


# ------------------------------------------------------------------ shared recordings


def _process(bag: Path, out: Path) -> Any:
    from owl_ros.process import ProcessOptions, process_bag

    return process_bag(bag, out, ProcessOptions())


def _mean_gyro_over_images(bag: Path) -> np.ndarray:
    with BagReader(bag) as reader:
        stamps = [r.log_time_ns for r in reader.messages(["/camera/image_raw"])]
        gyro = []
        for r in reader.messages(["/imu/data"]):
            if stamps[0] <= r.log_time_ns <= stamps[-1]:
                w = reader.deserialize(r).angular_velocity
                gyro.append((w.x, w.y, w.z))
    return np.mean(np.asarray(gyro), axis=0)


@pytest.mark.slow
def test_euroc_still_no_heading_and_bias_settles_on_the_mean_gyro(
    shared: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from owl_ros.tools.evaluate import read_estimates

    root = shared("euroc_v101_still")
    bag = tmp_path / "euroc"
    assert main([str(root), str(bag), "--seconds", "3", "-q"]) == 0
    summary = _process(bag, tmp_path / "out")
    frames = summary.frames_processed
    assert frames == 61
    assert len(summary.headings) <= 0.05 * frames
    # the engine's warm-up frames (no track long enough yet) have their own reason; after
    # it, the reason for every empty frame must be "no translation"
    warm = summary.reasons.get("no track spans 5 frames yet", 0)
    assert warm <= 5
    assert summary.reasons.get("no translation", 0) >= 0.95 * (frames - warm)
    est = read_estimates(tmp_path / "out")
    bias = est[max(est)].gyro_bias
    mean = _mean_gyro_over_images(bag)
    assert bias is not None
    assert np.all(np.abs(bias - mean) <= 0.003), (bias, mean)


@pytest.mark.slow
def test_realsense_walk_extrinsic_and_points(
    shared: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from bags.cli.importers.common import read_yaml, transform

    root = shared("realsense_walk")
    bag = tmp_path / "walk"
    # the whole 10 s recording: on its first 5 s alone, 71 of 83 frames after warm-up have
    # points (86 %): while the bias filter still doubts the gyro (the frames' measured
    # scatter is about 0.03 rad/s here), 11 frames of the walk's first 0.8 s are judged "no
    # translation"; over the recording 154 of 166 (93 %)
    assert main([str(root), str(bag), "-q"]) == 0
    printed = capsys.readouterr().out.strip()
    r_bs, _ = transform(read_yaml(root / "mav0" / "cam0" / "sensor.yaml")["T_BS"], root)
    with BagReader(bag) as reader:
        (tf,) = reader.deserialize(next(iter(reader.messages(["/tf_static"])))).transforms
    q = tf.transform.rotation
    # the IMU's T_BS is the identity: camera -> IMU is the camera's T_BS rotation
    assert quat_xyzw_to_matrix([q.x, q.y, q.z, q.w]) == pytest.approx(r_bs, abs=1e-9)
    line_q = [float(v) for v in printed.split("[")[1].rstrip("]").split(",")]
    assert quat_xyzw_to_matrix(line_q) == pytest.approx(r_bs, abs=1e-8)
    summary = _process(bag, tmp_path / "out")
    assert summary.extrinsic_source == "tf_static"
    warm = summary.reasons.get("no track spans 5 frames yet", 0)
    after = summary.frames_processed - warm
    assert summary.frames_with_points >= 0.9 * after, (summary.frames_with_points, after)
