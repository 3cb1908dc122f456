"""owl_eval: metric functions, and deliberately wrong results scored with exactly their error."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bags.cli.make_bag import write_bag
from bags.sim import scenarios
from bags.sim.scenarios import SimOptions
from bags.sim.sensors import ImuOptions
from owl_core.geometry import so3_exp
from owl_core.types import FrameResult, PointFlag
from owl_ros.tools import evaluate

BIAS = (0.004, -0.002, 0.003)
BIAS_ERROR = np.array([0.0006, 0.0, -0.0008])  # |.| = 0.001 rad/s
HEADING_OFFSET_DEG = 10.0
RANGE_FACTOR = 1.1


def test_heading_error_is_the_angle_between_directions():
    v = np.array([0.3, -0.2, 2.0])
    axis = np.cross(v, [1.0, 0.0, 0.0])
    for deg in (0.01, 1.0, 10.0, 90.0, 179.0):
        rot = so3_exp(axis / np.linalg.norm(axis) * math.radians(deg))
        got = evaluate.heading_error_deg(5.0 * rot @ v, v)  # the length does not matter
        assert got == pytest.approx(deg, abs=1e-9)
    assert np.isnan(evaluate.heading_error_deg(np.zeros(3), v))
    with pytest.raises(evaluate.EvalError, match=r"\(2,\)"):
        evaluate.heading_error_deg(np.zeros(2), v)


def test_sampling_coverage_and_relative_error():
    img = np.arange(12, dtype=np.float32).reshape(3, 4)
    px = np.array([[0.4, 0.4], [2.6, 1.2], [3.49, 2.49], [-0.6, 0.0], [np.nan, 1.0]])
    np.testing.assert_array_equal(evaluate.sample_nearest(img, px)[:3], [0, 7, 11])
    assert np.isnan(evaluate.sample_nearest(img, px)[3:]).all()
    # 2 of the 4 cells of a 2x2 grid over a 100 x 50 image
    cells = evaluate.coverage([[10, 10], [20, 5], [90, 40]], 100, 50, grid=(2, 2))
    assert cells == pytest.approx(0.5)
    np.testing.assert_allclose(
        evaluate.relative_error([1.1, 0.9, np.nan], [1.0, 1.0, 1.0])[:2], [0.1, -0.1]
    )


@pytest.fixture(scope="module")
def truth_bag(tmp_path_factory):
    """A small mover bag (320 x 240, 10 frames) with a known gyro bias, and its simulation
    (the car is wide enough for points farther than MASK_MARGIN_PX inside its outline)."""
    sim = scenarios.get("mover").simulate(
        SimOptions(seconds=0.3, width=320, height=240, imu=ImuOptions(gyro_bias=BIAS))
    )
    path = tmp_path_factory.mktemp("eval") / "truth"
    custom = {"owl_make_bag": json.dumps({"scenario": "mover", "gyro_bias": list(BIAS)})}
    write_bag(sim, path, custom=custom)
    return path, sim, list(sim.frames())


def wrong_result(frame, rng, n_random=60):
    """A FrameResult wrong by known amounts: heading rotated 10 deg, r/|t| x 1.1, bias off."""
    v = frame.velocity
    axis = np.cross(v, [0.0, 1.0, 0.0])
    heading = so3_exp(axis / np.linalg.norm(axis) * math.radians(HEADING_OFFSET_DEG)) @ v
    h, w = frame.range_m.shape
    px = np.c_[rng.integers(0, w, n_random), rng.integers(0, h, n_random)].astype(np.float64)
    moving = np.argwhere(frame.mask)[:, ::-1].astype(np.float64)  # (u, v) on the car
    px = np.concatenate([px, moving[:: max(1, moving.shape[0] // 40)]])
    iu, iv = px[:, 0].astype(int), px[:, 1].astype(int)
    ros = frame.range_m[iv, iu].astype(np.float64) / np.linalg.norm(v) * RANGE_FACTOR
    on_car = frame.mask[iv, iu]
    flags = np.where(on_car, PointFlag.MOVING, 0).astype(np.uint8)
    car = np.flatnonzero(on_car)
    flags[rng.choice(car, car.size // 2, replace=False)] = 0  # half missed: recall known
    keep = np.isfinite(ros)
    n = int(keep.sum())
    z3, z4 = np.zeros((n, 3)), np.zeros((n, 4))
    return (
        FrameResult(
            stamp_ns=frame.stamp_ns,
            pixels=px[keep],
            bearings=z3,
            looming=np.zeros(n),
            omega=z3,
            rot=z4,
            range_over_speed=ros[keep],
            points=z3,
            quality=np.ones(n),
            ids=np.arange(n, dtype=np.uint32),
            flags=flags[keep],
            heading=heading / np.linalg.norm(heading),
            heading_sigma_rad=0.01,
            gyro_bias=np.asarray(BIAS) + BIAS_ERROR,
        ),
        on_car[keep],
        flags[keep],
    )


def test_wrong_result_is_scored_with_exactly_its_error(truth_bag, tmp_path):
    path, _, frames = truth_bag
    rng = np.random.default_rng(0)
    results, tp, fn, near, static = [], 0, 0, 0, 0
    for f in frames:
        res, on_car, flags = wrong_result(f, rng)
        results.append(res)
        # points within MASK_MARGIN_PX of the car's outline are not scored (brute force:
        # the distance from each point's pixel to the nearest pixel of the other label)
        iu, iv = np.rint(res.pixels).astype(int).T
        other = [np.argwhere(f.mask != f.mask[v, u]) for u, v in zip(iu, iv, strict=True)]
        dist = np.array(
            [np.hypot(*(o - (v, u)).T).min() for o, u, v in zip(other, iu, iv, strict=True)]
        )
        clear = dist > evaluate.MASK_MARGIN_PX
        near += int(np.count_nonzero(~clear))
        static += int(np.count_nonzero(clear & ~on_car))
        tp += int(np.count_nonzero(on_car & (flags > 0) & clear))
        fn += int(np.count_nonzero(on_car & (flags == 0) & clear))
    assert tp > 0 and fn > 0 and near > 0  # the car is in view, some points near its edge
    result = tmp_path / "result"
    assert evaluate.write_result_bag(result, results) == len(frames)
    out = evaluate.evaluate(result, path)
    s = out.summary
    assert s["frames"] == s["translating_frames"] == s["heading_frames"] == len(frames)
    # Vector3 is float64: the angle is exact to rounding
    assert s["heading_deg_median"] == pytest.approx(HEADING_OFFSET_DEG, abs=1e-9)
    assert s["heading_deg_max"] == pytest.approx(HEADING_OFFSET_DEG, abs=1e-9)
    # r/|t| travels as float32: relative rounding 2^-24 on est and on the range image
    assert s["range_rel_median"] == pytest.approx(RANGE_FACTOR - 1, abs=1e-6)
    assert s["range_rel_p90"] == pytest.approx(RANGE_FACTOR - 1, abs=1e-6)
    # only static points away from the car's outline are scored
    assert s["range_points"] == static
    assert s["moving_precision"] == pytest.approx(1.0)
    assert s["moving_recall"] == pytest.approx(tp / (tp + fn))
    assert s["bias_error_final_rad_s"] == pytest.approx(0.001, abs=1e-12)
    assert s["points_per_frame"] == pytest.approx(np.mean([r.num_points for r in results]))


def test_cli_json_schema_and_text(truth_bag, tmp_path, capsys):
    path, _, frames = truth_bag
    rng = np.random.default_rng(1)
    result = tmp_path / "result"
    evaluate.write_result_bag(result, [wrong_result(f, rng)[0] for f in frames[:-2]])
    assert evaluate.main([str(result), "--truth", str(path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) == {"summary", "notes", "frames"}
    keys = {
        "frames",
        "heading_deg_median",
        "heading_deg_p90",
        "range_rel_median",
        "range_rel_p90",
        "points_per_frame",
        "coverage_mean",
        "moving_precision",
        "moving_recall",
        "bias_error_final_rad_s",
        "heading_availability",
        "truth_gyro_bias_rad_s",
    }
    assert keys <= set(doc["summary"])
    assert len(doc["frames"]) == len(frames)
    # the two frames without output count as frames without heading
    assert doc["summary"]["heading_availability"] == pytest.approx((len(frames) - 2) / len(frames))
    assert doc["frames"][-1]["has_heading"] is False
    assert doc["frames"][0]["heading_deg"] == pytest.approx(HEADING_OFFSET_DEG, abs=1e-9)
    assert evaluate.main([str(result), "--truth", str(path), "--per-frame"]) == 0
    text = capsys.readouterr().out
    assert "heading error median / p90" in text and "10 deg" in text


def test_cli_errors_are_one_line(truth_bag, tmp_path, capsys):
    path, _, _ = truth_bag
    assert evaluate.main([str(tmp_path / "missing"), "--truth", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing" in err and "Traceback" not in err
    # the truth bag has no /owl/points: named in the error
    assert evaluate.main([str(path), "--truth", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "/owl/points" in err
    # a result bag is no truth bag
    result = tmp_path / "result"
    evaluate.write_result_bag(result, [])
    assert evaluate.main([str(result), "--truth", str(result)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "/ground_truth/twist" in err
    assert "no ground truth to score against (owl_make_bag renders it; owl_import" in err
    with pytest.raises(SystemExit) as exc:
        evaluate.main(["--help"])
    assert exc.value.code == 0


def test_truncated_result_bag_is_scored_up_to_the_damage(truth_bag, tmp_path):
    path, _, frames = truth_bag
    rng = np.random.default_rng(2)
    result = tmp_path / "result"
    # enough points for several MCAP chunks: a cut leaves the first ones readable
    evaluate.write_result_bag(result, [wrong_result(f, rng, 8000)[0] for f in frames])
    (mcap,) = result.glob("*.mcap")
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) * 2 // 3])  # a recorder killed mid-write
    (result / "metadata.yaml").unlink()
    out = evaluate.evaluate(result, path)
    assert any("damaged" in n for n in out.notes)
    assert 0 < out.summary["heading_frames"] < len(frames)
    assert out.summary["heading_deg_median"] == pytest.approx(HEADING_OFFSET_DEG, abs=1e-9)


def _one_line(capsys, expect):
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith("owl_eval: error: ") and expect in err, err


def test_refuses_what_it_cannot_score_honestly(truth_bag, tmp_path, capsys):
    from dataclasses import replace

    path, _, frames = truth_bag
    rng = np.random.default_rng(3)
    good = [wrong_result(f, rng)[0] for f in frames]
    result = tmp_path / "result"
    evaluate.write_result_bag(result, good)
    for opt in ("--points-topic", "--heading-topic"):
        assert evaluate.main([str(result), "--truth", str(path), opt, "/nope"]) == 2
        _one_line(capsys, "topic /nope is not in result bag")
    empty = tmp_path / "empty"
    evaluate.write_result_bag(empty, [replace(r, **_no_points()) for r in good])
    named = ["--points-topic", "/owl/points"]
    assert evaluate.main([str(empty), "--truth", str(path), *named]) == 2
    _one_line(capsys, f"has 0 points on every frame ({len(frames)} frames)")
    notes = evaluate.evaluate(empty, path).notes  # the default topic: scored, with a note
    assert any("0 points on every frame" in n for n in notes), notes
    shifted = tmp_path / "shifted"  # another bag: no stamp in common
    evaluate.write_result_bag(shifted, [replace(r, stamp_ns=r.stamp_ns + 1) for r in good])
    assert evaluate.main([str(shifted), "--truth", str(path)]) == 2
    _one_line(capsys, "a result of another bag")
    wide = tmp_path / "wide"  # another image size: pixels beyond the 320x240 truth
    evaluate.write_result_bag(wide, [replace(r, pixels=r.pixels * 2.0 + 1.0) for r in good])
    assert evaluate.main([str(wide), "--truth", str(path)]) == 2
    _one_line(capsys, "outside the 320x240 images")
    # the truth given as the bag's bare .mcap file: its bias is read all the same
    (mcap,) = path.glob("*.mcap")
    out = evaluate.evaluate(result, mcap)
    assert out.summary["truth_gyro_bias_rad_s"] == pytest.approx(list(BIAS))
    assert out.summary["bias_error_final_rad_s"] == pytest.approx(0.001, abs=1e-12)


def _no_points():
    z = np.zeros((0, 3))
    return {
        "pixels": np.zeros((0, 2)), "bearings": z, "looming": np.zeros(0), "omega": z,
        "rot": np.zeros((0, 4)), "range_over_speed": np.zeros(0), "points": z,
        "quality": np.zeros(0), "ids": np.zeros(0, dtype=np.uint32),
        "flags": np.zeros(0, dtype=np.uint8),
    }  # fmt: skip


def test_run_without_imu_has_no_bias_error(truth_bag, tmp_path):
    from owl_ros.params import build_options
    from owl_ros.process import ProcessOptions, process_bag

    path, _, _ = truth_bag
    opts = ProcessOptions(node=build_options({"require_gyro": False}), imu_topic="")
    process_bag(path, tmp_path / "owl", opts)
    out = evaluate.evaluate(tmp_path / "owl", path)
    assert out.summary["bias_error_final_rad_s"] is None
    assert "result had no IMU samples: gyro-bias error not scored" in out.notes


def test_paired_range_errors_score_two_estimators_on_their_common_tracks(truth_bag):
    """A gives ranges 10 % long on tracks 0..9, B 20 % short on tracks 5..14: only tracks
    5..9 are scored, A's error 0.1 and B's 0.2 on each; a point on the car or within
    MASK_MARGIN_PX of its outline is left out."""
    _, _, frames = truth_bag
    f = frames[5]
    truth = evaluate.Truth(f.stamp_ns, f.velocity, f.range_m, f.mask)
    speed = float(np.linalg.norm(f.velocity))
    far = np.argwhere(evaluate.mask_edge_distance(f.mask) > 20)[:, ::-1].astype(float)
    px = far[np.linspace(0, far.shape[0] - 1, 15).astype(int)]
    px = px[np.isfinite(evaluate.true_range_over_speed(px, f.range_m, speed))][:15]
    car = np.argwhere(f.mask)[:, ::-1].astype(float)[:1]
    px[9] = car[0]  # track 9 sits on the car
    true = evaluate.true_range_over_speed(px, f.range_m, speed)
    ids = np.arange(px.shape[0], dtype=np.uint32)
    a, b = evaluate.paired_range_errors(
        ids[:10], px[:10], true[:10] * 1.1, ids[5:], np.nan_to_num(true[5:]) * 0.8, truth
    )
    np.testing.assert_allclose(a, 0.1, rtol=1e-6)
    np.testing.assert_allclose(b, 0.2, rtol=1e-6)
    assert a.size == 4  # tracks 5, 6, 7, 8 (9 is on the car)
