"""owl_bench on a tiny profile: schema, and the pooled numbers are owl_eval's numbers."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from owl_core.geometry import so3_exp
from owl_ros.tools import bench
from owl_ros.tools.evaluate import heading_error_deg, score_frame, summarize

TINY = bench.Profile(
    "tiny", 160, 120, 0.4, 120, (bench.Case("street"), bench.Case("street", bench.BIAS))
)

REQUIRED = {
    "owl_fps": float,
    "baseline_fps": float,
    "estimation_speedup": float,
    "owl_heading_deg_median": float,
    "baseline_heading_deg_median": float,
    "owl_range_rel_median": float,
    "baseline_range_rel_median": float,
    "features_per_frame": float,
    "image_size": str,
}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    return bench.run_bench(TINY, cache), cache


def test_json_schema(tiny):
    doc, cache = tiny
    for key, kind in REQUIRED.items():
        assert isinstance(doc[key], kind), key
    assert doc["image_size"] == "160x120"
    assert doc["owl_fps"] > 0 and doc["baseline_fps"] > 0 and doc["estimation_speedup"] > 0
    assert 0 < doc["features_per_frame"] <= TINY.features
    assert [c["case"] for c in doc["cases"]] == ["street", "street+bias"]
    for c in doc["cases"]:
        assert set(c["methods"]) == set(bench.METHODS)
        assert {"cv-5pt@1", "cv-5pt@2", "cv-5pt@4", "cv-gyro@1", "cv-gyro@4"} <= set(c["methods"])
        assert c["best"]["cv-5pt"].startswith("cv-5pt@")
        assert c["best"]["heading"] in c["methods"]
        assert c["frames"] == 13
        assert {"track", "total"} <= set(c["owl_stage_ms_per_frame"])
    # biased rows are reported separately
    assert "owl_heading_deg_median_bias" in doc and "baseline_gyro_heading_deg_median_bias" in doc
    assert json.loads(json.dumps(doc)) == doc  # plain JSON
    # frames were cached once per scenario (the biased row reuses the images)
    assert len(list(cache.glob("street_160x120_*.npz"))) == 1


def test_baselines_are_given_the_known_gyro_bias(tiny):
    """On a "+bias" case the gyro-aided baselines derotate, and the filtered ones (the
    5-point ones too) predict, with the case's true bias: their headings are those of the
    unbiased case within the noise of the two runs. With the raw gyro they were not
    (cv-gyro@1 0.82 deg against 0.34, its filtered variant 0.78 against 0.21)."""
    doc, _ = tiny
    rows = {c["case"]: c["methods"] for c in doc["cases"]}
    for name in ("cv-gyro@1", "cv-gyro@4", "cv-gyro@1+kf0.5", "cv-5pt@1+kf0.5"):
        plain = rows["street"][name]["heading_deg_median"]
        biased = rows["street+bias"][name]["heading_deg_median"]
        assert biased <= 1.1 * plain, (name, plain, biased)


def test_cached_frames_are_reused_and_equal(tiny):
    _, cache = tiny
    sim = bench._sim(bench.Case("street"), TINY)
    again = bench.load_frames(sim, cache)
    fresh = bench.load_frames(sim, None)
    np.testing.assert_array_equal(again.images, fresh.images)
    finite = np.isfinite(fresh.range_m)
    np.testing.assert_array_equal(np.isfinite(again.range_m), finite)
    # the cache stores float16 ranges: relative rounding <= 2^-11
    np.testing.assert_allclose(again.range_m[finite], fresh.range_m[finite], rtol=2**-11)


def test_bench_scores_are_owl_eval_scores_and_a_wrong_heading_shows_exactly():
    case = bench.Case("street")
    sim = bench._sim(case, TINY)
    frames = bench.load_frames(sim, None)
    run = bench.run_case(case, TINY, frames, sim, keep_results=True)
    row = bench.case_report(run)["methods"]
    # recompute the OWL summary from the kept results with owl_eval's functions
    scores = [
        score_frame(bench.owl_estimate(r), frames.truth(k), np.zeros(3))
        for k, r in enumerate(run.owl_results)
    ]
    assert summarize(scores, False)["heading_deg_median"] == row["owl"]["heading_deg_median"]
    # a heading rotated by 7 degrees about an axis perpendicular to the truth scores 7 degrees
    for k, r in enumerate(run.baseline_results["cv-5pt@4"]):
        v = frames.velocity[k]
        axis = np.cross(v, [1.0, 0.0, 0.0])
        wrong = so3_exp(axis / np.linalg.norm(axis) * math.radians(7.0)) @ v
        est = bench.baseline_estimate(r)
        est = type(est)(est.stamp_ns, wrong, est.pixels, est.range_over_speed, est.flags)
        s = score_frame(est, frames.truth(k))
        assert s.heading_deg == pytest.approx(7.0, abs=1e-9)
    assert float(heading_error_deg(wrong, v)) == pytest.approx(7.0, abs=1e-9)


def test_seeds_score_every_method_over_the_frames_of_all_seeds(tmp_path):
    """--seeds K renders each case with K noise seeds: a case's figures are owl_eval's
    summary over the frames of all seeds, each seed's own figures are kept beside."""
    profile = bench.Profile("tiny", 160, 120, 0.4, 120, (bench.Case("street"),), seeds=(0, 1))
    doc = bench.run_bench(profile, tmp_path)
    (case,) = doc["cases"]
    assert doc["seeds"] == [0, 1] and case["frames"] == 26
    assert set(case["per_seed"]) == {"0", "1"}
    assert len(list(tmp_path.glob("street_160x120_*seed1_*.npz"))) == 1
    scores = []
    for seed in (0, 1):
        sim = bench._sim(bench.Case("street"), profile, seed)
        frames = bench.load_frames(sim, tmp_path)
        run = bench.run_case(bench.Case("street"), profile, frames, sim, keep_results=True)
        scores += [
            score_frame(bench.owl_estimate(r), frames.truth(k), np.zeros(3))
            for k, r in enumerate(run.owl_results)
        ]
        own = bench.case_report(run)["methods"]["owl"]["heading_deg_median"]
        assert case["per_seed"][str(seed)]["owl"]["heading_deg_median"] == own
    merged = summarize(scores, False)
    assert case["methods"]["owl"]["heading_deg_median"] == merged["heading_deg_median"]
    assert case["methods"]["owl"]["heading_deg_p90"] == merged["heading_deg_p90"]
    seeds = [case["per_seed"][k]["owl"]["heading_deg_median"] for k in ("0", "1")]
    assert seeds[0] != seeds[1]  # the noise differs


def test_cli_json_and_errors(capsys, tmp_path):
    argv = ["--quick", "--json", "--cases", "cube", "--seconds", "0.2", "--quiet"]
    assert bench.main([*argv, "--features", "120", "--cache-dir", str(tmp_path)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["image_size"] == "320x240" and doc["profile"] == "quick"
    assert doc["features"] == 120 and 0 < doc["features_per_frame"] <= 120
    assert bench.main(["--cases", "nowhere", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nowhere" in err
    assert bench.main(["--quick", "--seconds", "-1", "--quiet"]) == 2
    assert "--seconds" in capsys.readouterr().err
    assert bench.main(["--quick", "--features", "0", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--features" in err and "0" in err
    assert bench.main(["--quick", "--seeds", "0", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--seeds" in err


def test_an_engine_setting_runs_owl_and_its_tracks_with_it(capsys, tmp_path):
    """-p NAME:=VALUE: what a setting of the node costs, measured on the bench's cases."""
    argv = ["--quick", "--json", "--cases", "cube", "--seconds", "0.3", "--quiet"]
    argv += ["--features", "120", "--cache-dir", str(tmp_path)]
    assert bench.main(argv) == 0
    default = json.loads(capsys.readouterr().out)
    off = ["-p", "tracker_lk_deformation_correction:=false"]
    assert bench.main([*argv, *off]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert default["engine_params"] == {}
    assert doc["engine_params"] == {"tracker_lk_deformation_correction": False}
    # the same frames, other tracks: every method's figures move (the baselines share them)
    for name in ("owl", "cv-5pt@1"):
        a = default["cases"][0]["methods"][name]["heading_deg_median"]
        b = doc["cases"][0]["methods"][name]["heading_deg_median"]
        assert a != b, name
    for item, says in (
        ("max_features:=500", "the bench sets max_features (give it as --features)"),
        ("imu_time_offset:=0.01", "the bench sets imu_time_offset (each case has its own)"),
        ("queue_size:=3", "queue_size is a node setting, not one of the engine"),
        ("tracker_lk_deformation_corection:=false", "did you mean"),
        ("pixel_noise_px:=-1", "pixel_noise_px"),
        ("pixel_noise_px", "-p expects NAME:=VALUE"),
    ):
        assert bench.main(["--quick", "--quiet", "-p", item]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("owl_bench: error: ") and says in err, err


def test_a_fast_camera_adds_the_gap_spanning_what_4_frames_span_at_30_hz():
    assert bench.case_gaps(30.0, 10) == bench.GAPS == (1, 2, 4)
    assert bench.case_gaps(10.0, 10) == (1, 2, 4)  # a slow camera's gaps are longer already
    assert bench.case_gaps(60.0, 10) == (1, 2, 4, 8)
    assert bench.case_gaps(60.0, 8) == (1, 2, 4, 7)  # as far as the tracks' history reaches
    assert bench.case_gaps(45.0, 10) == (1, 2, 4, 6)
    names, filtered = bench._methods((1, 2, 4, 8))
    assert names[0] == "owl" and "cv-gyro@8" in names and "cv-5pt@8+kf0.2" in names
    assert len(filtered) == 2 * 4 * len(bench.FILTER_SIGMAS_DEG)


def test_best_baseline_is_the_lowest_heading_median_and_owl_is_judged_against_every_gap():
    def row(h50, h90, r50, r90, paired=None):
        return {
            "translating_frames": 10,
            "false_heading_frames": 0,
            "heading_availability": 1.0,
            "heading_deg_median": h50,
            "heading_deg_p90": h90,
            "range_rel_median": r50,
            "range_rel_p90": r90,
            "range_paired": paired,
        }

    def pair(owl50, owl90, base50, base90):
        return {"points": 100, "owl_median": owl50, "owl_p90": owl90, "median": base50,
                "p90": base90}  # fmt: skip

    methods = {m: row(1.0, 2.0, 0.05, 0.2, pair(0.02, 0.1, 0.05, 0.2)) for m in bench.METHODS}
    methods["cv-5pt@2"] = row(0.3, 0.9, 0.04, 0.3, pair(0.02, 0.1, 0.04, 0.3))
    methods["cv-gyro@1"] = row(0.4, 0.5, 0.03, 0.1, pair(0.02, 0.1, 0.03, 0.12))
    methods["owl"] = row(0.35, 0.6, 0.02, 0.1)
    best = bench.best_baselines(methods)
    assert best["cv-5pt"] == "cv-5pt@2" and best["cv-gyro"] == "cv-gyro@1"
    assert best["heading"] == "cv-5pt@2" and best["range"] == "cv-gyro@1"
    assert best["range_paired"] == "cv-gyro@1"  # the lowest p90 on the common tracks
    # OWL's median beats cv-gyro@1's but not cv-5pt@2's; its p90 beats both: not ok.
    # r/|t| is judged on each baseline's common tracks: at or below every one of them
    assert best["owl_heading_ok"] is False
    assert best["owl_range_ok"] is True
    methods["owl"] = row(0.3, 0.5, 0.03, 0.11)
    methods["cv-gyro@1"]["range_paired"] = pair(0.02, 0.13, 0.03, 0.12)  # OWL's p90 higher
    best = bench.best_baselines(methods)
    assert best["owl_heading_ok"] is True and best["owl_range_ok"] is False
    for m in bench.METHODS:
        methods[m]["range_paired"] = None
    assert bench.best_baselines(methods)["owl_range_ok"] is None
    # the heading on common frames: each median over the frames both gave a heading for
    assert best["owl_heading_paired_ok"] is None  # no baseline shares a frame with OWL
    for m in bench.METHODS:
        methods[m]["heading_paired"] = {
            "frames": 50, "owl_median": 0.3, "owl_p90": 0.5, "median": 0.4, "p90": 0.6
        }  # fmt: skip
    methods["owl"].pop("heading_paired")
    best = bench.best_baselines(methods)
    assert best["owl_heading_paired_ok"] is True and best["owl_heading_paired_ok_filtered"]
    # on its own frames cv-5pt@1 looks no better than OWL, on the common ones it is
    methods["cv-5pt@1"]["heading_paired"]["median"] = 0.25
    best = bench.best_baselines(methods)
    assert best["owl_heading_paired_ok"] is False
    assert best["owl_heading_paired_ok_filtered"] is True  # the unfiltered one lost it
    methods["cv-5pt@1+kf0.2"]["heading_paired"]["p90"] = 0.45
    assert bench.best_baselines(methods)["owl_heading_paired_ok_filtered"] is False


def test_bag_source_scores_exactly_as_the_in_memory_frames(tmp_path):
    from bags.cli.make_bag import main as make_bag

    bag = tmp_path / "street"
    argv = ["street", str(bag), "--seconds", "0.4", "--width", "160", "--height", "120"]
    assert make_bag([*argv, "--quiet"]) == 0
    case = bench.Case("street")
    sim = bench._sim(case, TINY)
    mem = bench.case_report(bench.run_case(case, TINY, bench.load_frames(sim, None), sim))
    src = bench.bag_source(bag)
    assert src.num_frames == 13
    from_bag = bench.case_report(bench.run_source(bench.Case("bag", 0.0, str(bag)), TINY, src))
    for m in bench.METHODS:
        a, b = mem["methods"][m], from_bag["methods"][m]
        for key in ("heading_deg_median", "heading_deg_p90", "range_rel_median", "frames"):
            assert a[key] == b[key], (m, key)
    assert bench.main(["--bag", str(tmp_path / "nothing"), "--quiet"]) == 2


def test_case_labels_parse_back_and_unknown_suffixes_are_refused():
    for case in bench.FULL.cases + bench.QUICK.cases:
        assert bench.parse_case(case.label) == case
    c = bench.parse_case("street@20hz+adis16448+jitter+bias")
    assert (c.rate_hz, c.imu, c.effects, c.bias) == (20.0, "adis16448", ("jitter",), bench.BIAS)
    with pytest.raises(bench.BenchError, match="unknown suffix 'fog'"):
        bench.parse_case("street+fog")
    with pytest.raises(bench.BenchError, match="rate"):
        bench.parse_case("street@fasthz")


def test_effect_times_are_uneven_and_drop_frames_deterministically():
    case = bench.parse_case("street+jitter+drop")
    sim = bench._sim(case, TINY)
    t = bench.effect_times(case, sim)
    again = bench.effect_times(case, sim)
    np.testing.assert_array_equal(t, again)
    n = sim.options.num_frames
    assert t.size < n and t[0] == 0.0 and np.all(np.diff(t) > 0)
    gaps = np.diff(t) * sim.options.rate_hz  # in frame periods
    assert gaps.max() > 1.5 or np.ptp(gaps) > 0.3  # uneven / a drop


def test_cache_goes_to_the_user_cache_dir_and_is_named(tmp_path, monkeypatch, capsys):
    run = tmp_path / "somewhere"
    run.mkdir()
    monkeypatch.chdir(run)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    args = ["--quick", "--cases", "still", "--seconds", "0.2", "--features", "40", "--json"]
    assert bench.main(args) == 0
    cache = tmp_path / "xdg" / "owl_ros" / "frames"
    assert f"owl_bench: frame cache: {cache}\n" in capsys.readouterr().err
    assert list(cache.glob("still_320x240_*.npz")) and list(run.iterdir()) == []


def test_rolling_shutter_case_runs_owl_compensating_and_ignoring_the_readout(tmp_path):
    case = bench.parse_case("brisk+rs30")
    assert case.readout_s == 0.03 and case.label == "brisk+rs30"
    profile = bench.Profile("tiny", 160, 120, 0.4, 120, (case,))
    sim = bench._sim(case, profile)
    assert sim.options.rolling_shutter_readout_s == 0.03
    frames = bench.load_frames(sim, tmp_path, case=case)
    np.testing.assert_array_equal(frames.images[2], sim.frame(2).image)  # rows at their times
    report = bench.case_report(bench.run_case(case, profile, frames, sim))
    assert set(report["methods"]) == {*bench.METHODS, bench.UNCOMPENSATED}
    assert not report["best"]["heading"].startswith("owl")  # a baseline, not OWL's variant
    assert report["methods"][bench.UNCOMPENSATED]["frames"] == frames.stamps_ns.size
    glob = bench._sim(bench.Case("brisk"), profile)
    plain = bench.case_report(
        bench.run_case(bench.Case("brisk"), profile, bench.load_frames(glob, None), glob)
    )
    assert set(plain["methods"]) == set(bench.METHODS)  # a global-shutter case: OWL once


def test_concurrent_renders_of_one_case_share_the_cache(tiny, tmp_path):
    """Two processes (two benches, a Ray batch) storing the same case at once each write a
    file of their own and rename it into place: no error, one file, nothing left over."""
    from concurrent.futures import ThreadPoolExecutor

    sim = bench._sim(bench.Case("street"), TINY)
    frames = bench.load_frames(sim, None)
    path = tmp_path / "street.npz"
    with ThreadPoolExecutor(8) as pool:
        for f in [pool.submit(bench._store, path, frames) for _ in range(16)]:
            f.result()
    assert [p.name for p in tmp_path.iterdir()] == ["street.npz"]
    again = np.load(path)
    np.testing.assert_array_equal(again["images"], frames.images)
