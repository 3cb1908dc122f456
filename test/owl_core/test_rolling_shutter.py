"""owl_core.rolling_shutter and the engine's rolling-shutter compensation.

The end-to-end tests render the ``brisk`` scenario (walking at 1.5 m/s, turning at up to
1 rad/s) at 320x240, 30 Hz, 1.5 s, once with a global shutter and once with a 30 ms
readout, and score the engine against the truth with owl_eval's functions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pytest

from bags.sim import scenarios
from bags.sim.scenarios import SimOptions, Simulation
from owl_core import heading as hd
from owl_core import rolling_shutter as rs
from owl_core.engine import EngineOptions, OwlEngine, fit_tracks
from owl_core.errors import InvalidInputError
from owl_core.gyro import GyroBuffer
from owl_core.motion import cross
from owl_core.types import FrameResult, GyroSamples, ImageFrame
from owl_ros.tools.bench import owl_estimate
from owl_ros.tools.evaluate import Truth, score_frame, summarize

READOUT = 0.03  # s
SMALL = SimOptions(seconds=1.5, width=320, height=240)


def _accelerating_gyro(rate_hz: float = 400.0) -> tuple[GyroBuffer, np.ndarray]:
    """A gyro turning at about 1 rad/s with 3 rad/s^2 of angular acceleration on two axes."""
    t = np.arange(0.0, 1.0, 1.0 / rate_hz)
    w = np.stack([0.8 * np.sin(3.0 * t), 0.6 * np.cos(5.0 * t), 0.2 + 0.1 * t], axis=1)
    stamps = (t * 1e9).astype(np.int64)
    buf = GyroBuffer()
    buf.add(GyroSamples(stamps, w))
    return buf, stamps


def test_readout_rotations_match_the_exact_gyro_rotation_at_every_row() -> None:
    gyro, _ = _accelerating_gyro()
    frames = np.array([400_000_000, 366_666_667, 333_333_333], dtype=np.int64)
    stamp = int(frames[0])
    readout_ns = 30_000_000
    grid = rs.readout_rotations(gyro, frames, stamp, readout_ns, (0.01, 0.0, -0.02))
    rng = np.random.default_rng(1)
    fraction = rng.uniform(0.0, 1.0, 50)
    frame = rng.integers(0, 3, 50)
    b = rng.normal(size=(50, 3))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    got = grid.to_stamp(frame, fraction, b)
    for i in range(50):
        t_row = int(frames[frame[i]]) + round(fraction[i] * readout_ns)
        exact = gyro.relative_rotation(t_row, stamp, (0.01, 0.0, -0.02))
        # a constant rate over readout/8 = 3.75 ms: |dw/dt| (T/M)^2 / 8 ~ 1e-5 rad at most
        assert np.linalg.norm(got[i] - exact @ b[i]) < 2e-5
    back = grid.from_stamp(frame, fraction, got)
    np.testing.assert_allclose(back, b, atol=1e-12)
    # row 0 of the current frame is the stamp itself
    np.testing.assert_allclose(grid.to_stamp(0, np.zeros(1), b[:1]), b[:1], atol=1e-12)
    with pytest.raises(InvalidInputError, match="readout_ns"):
        rs.readout_rotations(gyro, frames, stamp, 0, (0, 0, 0))


def _tracks(n: int, w: int, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """Bearings moving at constant rates (N, W, 3), with per-entry times."""
    e0 = rng.normal(size=(n, 3)) + np.array([0.0, 0.0, 3.0])
    e0 /= np.linalg.norm(e0, axis=1, keepdims=True)
    rate = cross(rng.normal(scale=0.3, size=(n, 3)), e0)
    frame_tau = -np.arange(w) / 30.0
    row_tau = frame_tau[None, :] + rng.uniform(0, READOUT, (n, w))
    return e0, rate, frame_tau, row_tau


def test_fit_timed_recovers_linear_motion_and_equals_the_global_fit_without_readout() -> None:
    rng = np.random.default_rng(7)
    n, w = 40, 5
    e0, rate, frame_tau, row_tau = _tracks(n, w, rng)
    mask = np.ones((n, w), dtype=bool)
    mask[:5, 3:] = False  # shorter tracks
    # without a readout the timed fit is the global-shutter fit
    bearings = e0[:, None, :] + rate[:, None, :] * frame_tau[None, :, None]
    for order in (1, 2):
        glob = fit_tracks(bearings, frame_tau, mask, order)
        timed = rs.fit_timed(bearings, np.broadcast_to(frame_tau, (n, w)), mask, order, frame_tau)
        for a, b in zip(
            (glob.bearing, glob.rate, glob.tau_ref, glob.gain), timed[:4], strict=True
        ):
            np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(timed[4], glob.valid)
        np.testing.assert_allclose(timed[5], glob.tau_ref, atol=1e-12)
    # each entry at its own time: the line through them is the motion, its bearing referred
    # to the frame-stamp centroid (a global-shutter fit would be off by rate x row time)
    bearings = e0[:, None, :] + rate[:, None, :] * row_tau[..., None]
    bearing, fitted_rate, tau_ref, _, valid, tau_rate = rs.fit_timed(
        bearings, row_tau, mask, 1, frame_tau
    )
    assert valid.all()
    centroid = (mask @ frame_tau) / mask.sum(axis=1)
    np.testing.assert_allclose(tau_ref, centroid, atol=1e-15)
    expected = e0 + rate * centroid[:, None]
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(bearing, expected, atol=1e-12)
    tangent = rate - np.einsum("ni,ni->n", rate, bearing)[:, None] * bearing
    np.testing.assert_allclose(fitted_rate, tangent, atol=1e-12)
    # the rate's time: the entry times' centroid, moved by m3 / (2 m2) of their spread
    # (where a least-squares slope on uneven times is exact for a quadratic)
    own = np.sum(np.where(mask, row_tau, 0.0), axis=1) / mask.sum(axis=1)
    dev = np.where(mask, row_tau - own[:, None], 0.0)
    skew = 0.5 * np.sum(dev**3, axis=1) / np.sum(dev**2, axis=1)
    np.testing.assert_allclose(tau_rate, own + skew, atol=1e-15)
    glob = fit_tracks(bearings, frame_tau, mask, 1)
    assert np.median(np.linalg.norm(glob.bearing - bearing, axis=1)) > 1e-3
    # back to the stamp from a row time
    now = rs.bearings_at_stamp(bearings[:, 0], fitted_rate, row_tau[:, 0])
    np.testing.assert_allclose(now, e0 / np.linalg.norm(e0, axis=1, keepdims=True), atol=2e-4)


def test_engine_options_check_the_readout_and_the_gyro_must_reach_the_last_row() -> None:
    for bad in (-0.01, math.nan, 1.5):
        with pytest.raises(InvalidInputError, match="rolling_shutter_readout_s"):
            EngineOptions(rolling_shutter_readout_s=bad)
    sim = scenarios.get("brisk").simulate(replace(SMALL, seconds=0.2))
    camera = sim.camera
    stamps = sim.frame_stamps_ns
    offset = sim.imu_time_offset_ns
    for readout, covered in ((0.0, True), (READOUT, False)):
        engine = OwlEngine(camera, EngineOptions(rolling_shutter_readout_s=readout))
        imu = sim.gyro_samples()
        keep = imu.stamp_ns <= stamps[1] + offset + 5_000_000  # IMU to 5 ms past frame 1
        engine.add_gyro(GyroSamples(imu.stamp_ns[keep], imu.angular_velocity[keep]))
        assert engine.covers(int(stamps[1])) is covered


def test_tracker_prediction_follows_each_row_under_pure_rotation() -> None:
    """Turning on the spot (no parallax), a feature seen at row v of frame k-1 is predicted
    where frame k's rows see its direction: exactly with the row times, off by the change of
    the readout's rotation without them."""
    sim = scenarios.get("rotation_only").simulate(
        replace(SMALL, seconds=0.5, rolling_shutter_readout_s=READOUT)
    )
    camera, stamps = sim.camera, sim.frame_stamps_ns
    errors: dict[float, float] = {}
    for readout in (READOUT, 0.0):
        engine = OwlEngine(
            camera,
            EngineOptions(
                camera_to_imu_rotation_xyzw=sim.camera_to_imu_xyzw,
                rolling_shutter_readout_s=readout,
            ),
        )
        engine.add_gyro(sim.gyro_samples())
        prev, stamp = int(stamps[5]), int(stamps[6])
        px = np.stack(np.meshgrid(np.arange(20.0, 300, 40), np.arange(10.0, 235, 25)), -1)
        px = px.reshape(-1, 2)
        engine._state.last_stamp = prev
        if readout:
            predicted = engine._row_time_predictor(prev, stamp, np.zeros(3))(px)
        else:
            r_rel = engine.gyro.relative_rotation(prev, stamp)
            predicted = camera.bearing_to_pixel(camera.pixel_to_bearing(px) @ r_rel.T)
        truth = _rolling_reprojection(sim, px, prev, stamp, READOUT)
        errors[readout] = float(np.median(np.linalg.norm(predicted - truth, axis=1)))
    assert errors[READOUT] < 0.02  # px: the gyro noise (0.001 rad/s per sample)
    assert errors[0.0] > 5 * errors[READOUT]


def _rolling_reprojection(
    sim: Simulation, px: np.ndarray, prev: int, stamp: int, readout: float
) -> np.ndarray:
    """Where a rolling-shutter camera that only rotates sees, in frame ``stamp``, the
    directions it saw at pixels ``px`` of frame ``prev`` (fixed point over the row time)."""
    cam, h = sim.camera, sim.camera.height

    def pose(ns: int, v: np.ndarray) -> np.ndarray:
        times = sim.time_of(ns) + v / h * readout
        st = sim.trajectory.state(times)
        out: np.ndarray = st.R_wb @ sim.R_bc
        return out

    world = np.einsum("nij,nj->ni", pose(prev, px[:, 1]), cam.pixel_to_bearing(px))
    out = px.copy()
    for _ in range(6):
        out = cam.bearing_to_pixel(np.einsum("nji,nj->ni", pose(stamp, out[:, 1]), world))
    return out


# --- end to end: the 1.2x test and the uncompensated engine --------------------------------

SEEDS = (0, 1)  # two renders (image noise, IMU noise) of each shutter, pooled


@dataclass(frozen=True)
class Run:
    """Engine passes over the seeds' renders: results, truths and the pooled owl_eval
    summary."""

    results: list[FrameResult]
    truths: list[Truth]
    sims: list[Simulation]
    summary: dict[str, Any]


def _run(renders: list[tuple[Simulation, list[Any]]], readout: float, **options: Any) -> Run:
    results, truths, sims, scores = [], [], [], []
    for sim, frames in renders:
        engine = OwlEngine(
            sim.camera,
            EngineOptions(
                camera_to_imu_rotation_xyzw=sim.camera_to_imu_xyzw,
                max_features=300,
                rolling_shutter_readout_s=readout,
                **options,
            ),
        )
        engine.add_gyro(sim.gyro_samples())
        for f in frames:
            res = engine.process(ImageFrame(f.stamp_ns, f.image))
            truth = Truth(f.stamp_ns, f.velocity, f.range_m, None)
            results.append(res)
            truths.append(truth)
            sims.append(sim)
            scores.append(score_frame(owl_estimate(res), truth))
    return Run(results, truths, sims, summarize(scores, False))


@pytest.fixture(scope="module")
def brisk() -> dict[str, Run]:
    scenario = scenarios.get("brisk")
    glob, rolling = [], []
    for seed in SEEDS:
        for out, readout in ((glob, 0.0), (rolling, READOUT)):
            sim = scenario.simulate(replace(SMALL, seed=seed, rolling_shutter_readout_s=readout))
            out.append((sim, list(sim.frames())))
    return {
        "global": _run(glob, 0.0),
        "compensated": _run(rolling, READOUT),
        "uncompensated": _run(rolling, 0.0),
        "global, bias known": _run(glob, 0.0, estimate_bias=False),
        "compensated, bias known": _run(rolling, READOUT, estimate_bias=False),
    }


def _ratio(brisk: dict[str, Run], key: str, known_bias: bool = False) -> float:
    suffix = ", bias known" if known_bias else ""
    glob = brisk["global" + suffix].summary[key]
    comp = brisk["compensated" + suffix].summary[key]
    print(f"{key}{suffix}: global {glob:.4f}, compensated {comp:.4f}, ratio {comp / glob:.3f}")
    return float(comp / glob)


def test_compensated_rolling_shutter_is_within_1_2x_of_the_global_shutter(
    brisk: dict[str, Run],
) -> None:
    """r/|t| with the default engine, and the heading with the gyro bias known (it is zero
    here): the compensation itself. Measured: r/|t| 1.05-1.11x per seed (1.085x over five),
    heading 0.61-1.2x per seed (0.91x over five); on this test's two seeds, since the
    heading fit's gradient carries the normaliser's derivative, 1.15x and 0.80x."""
    assert _ratio(brisk, "range_rel_median") <= 1.2
    assert _ratio(brisk, "heading_deg_median", known_bias=True) <= 1.2
    assert _ratio(brisk, "range_rel_median", known_bias=True) <= 1.2
    glob, comp = brisk["global"].summary, brisk["compensated"].summary
    assert comp["heading_availability"] >= glob["heading_availability"] - 0.05
    assert comp["points_per_frame"] >= 0.9 * glob["points_per_frame"]


def test_compensated_heading_with_the_bias_estimated_is_within_1_2x(
    brisk: dict[str, Run],
) -> None:
    """With the bias estimated too. This was 1.21x (0.128 against 0.106 deg) while the
    heading fit's Gauss-Newton left the normaliser's derivative out of its gradient: the
    bias filter then settled on a pitch bias a few 0.1 mrad/s off (exact tracks with the
    same noise: 1.1-1.3x); with it, as with the bias known."""
    assert _ratio(brisk, "heading_deg_median") <= 1.2


def _predicted_heading_errors(run: Run, readout: float) -> np.ndarray:
    """First-order heading error of an engine that ignores the readout (deg per frame).

    Treating a position seen at row fraction u as seen at its frame's stamp derotates it
    with the rotation of the wrong instant: its bearing is off by ``-(Omega u T) x e``. The
    track fit's slope turns that into a rate error ``-T (u Omega' + u' Omega) x e`` (the
    u' term is 1/20 of it here, and the time shift of the translation smaller still):
    checked against the engine's own rates, the ratio is 0.99. Put through the heading
    estimator on the true flow of the same pixels (leftover rotation fixed, as it is once
    the bias has settled), with Omega' at the fits' time centroid (2 frames back).
    """
    out = []
    for res, truth, sim in zip(run.results, run.truths, run.sims, strict=True):
        if res.heading is None or res.pixels.shape[0] < 20:
            continue
        cam = sim.camera
        iu, iv = np.rint(res.pixels).astype(int).T
        r = truth.range_m[iv, iu].astype(np.float64)
        ok = np.isfinite(r)
        e = cam.pixel_to_bearing(res.pixels[ok])
        v = truth.velocity
        flow = -(v - e * (e @ v)[:, None]) / r[ok, None]
        t = sim.time_of(truth.stamp_ns) - 2.0 / sim.options.rate_hz
        accel = (sim.twist(t + 1e-3)[1] - sim.twist(t - 1e-3)[1]) / 2e-3
        u = res.pixels[ok, 1] / cam.height
        error = -readout * cross(u[:, None] * accel[None, :], e)
        est = hd.estimate_motion(e, flow + error, 1e-3, np.eye(3), estimate_rotation=False)
        if est.heading is not None:
            cos = float(est.heading @ v) / float(np.linalg.norm(v))
            out.append(math.degrees(math.acos(min(1.0, max(-1.0, cos)))))
    return np.asarray(out)


def test_ignoring_the_readout_costs_what_the_first_order_error_predicts(
    brisk: dict[str, Run],
) -> None:
    glob, unc = brisk["global"].summary, brisk["uncompensated"].summary
    predicted = float(np.median(_predicted_heading_errors(brisk["uncompensated"], READOUT)))
    measured = unc["heading_deg_median"]
    print(
        f"heading median: global {glob['heading_deg_median']:.3f}, uncompensated "
        f"{measured:.3f}, first-order prediction {predicted:.3f} deg"
    )
    # the prediction leaves out the bias and heading filters: the measured error is within
    # a factor 2 of it, and both are far above the global shutter's
    assert 0.5 * predicted <= measured <= 2.0 * predicted
    assert predicted > 10 * glob["heading_deg_median"]
