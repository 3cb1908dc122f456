"""OwlEngine: options, input checks, gyro handling, time handling, and the track fit.

Uses a short rendered street scenario (bags.sim.scenarios, 320x240, 0.5 s at 30 Hz), rendered
once per module.
"""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import numpy as np
import pytest

from bags.sim import scenarios
from owl_core.camera import CameraModel
from owl_core.engine import EngineOptions, OwlEngine, fit_tracks
from owl_core.errors import InvalidInputError
from owl_core.heading import HeadingOptions
from owl_core.types import GyroSamples, ImageFrame, PointFlag

SIM_OPTS = scenarios.SimOptions(seconds=0.5, width=320, height=240)


@pytest.fixture(scope="module")
def street() -> tuple[scenarios.Simulation, list[scenarios.Frame]]:
    sim = scenarios.get("street").simulate(SIM_OPTS)
    return sim, list(sim.frames())


def make_engine(sim: scenarios.Simulation, **overrides: object) -> OwlEngine:
    opts = EngineOptions(
        camera_to_imu_rotation_xyzw=sim.camera_to_imu_xyzw,
        imu_time_offset_s=sim.imu_time_offset_ns * 1e-9,
        max_features=400,
    )
    return OwlEngine(sim.camera, replace(opts, **overrides))  # type: ignore[arg-type]


def test_options_validation_names_the_value() -> None:
    with pytest.raises(InvalidInputError, match="fit_frames"):
        EngineOptions(fit_frames=1)
    with pytest.raises(InvalidInputError, match="min_track_frames"):
        EngineOptions(fit_frames=3, min_track_frames=4)
    with pytest.raises(InvalidInputError, match=r"pixel_noise_px.*-1"):
        EngineOptions(pixel_noise_px=-1.0)
    with pytest.raises(InvalidInputError, match="fit_order"):
        EngineOptions(fit_order=3)
    with pytest.raises(InvalidInputError, match="camera_to_imu_rotation_xyzw"):
        EngineOptions(camera_to_imu_rotation_xyzw=(0.0, 0.0, float("nan"), 1.0))
    with pytest.raises(InvalidInputError, match="bias_inflation"):
        EngineOptions(bias_inflation=0.5)
    with pytest.raises(InvalidInputError, match=r"confirm_below_turning.*-0.1"):
        EngineOptions(confirm_below_turning=-0.1)
    with pytest.raises(InvalidInputError, match=r"fit_turning_weight.*-0.5"):
        EngineOptions(fit_turning_weight=-0.5)
    with pytest.raises(InvalidInputError, match=r"fit_turning_window_s.*0.0"):
        EngineOptions(fit_turning_window_s=0.0)


def test_bad_image_raises(street: tuple[scenarios.Simulation, list[scenarios.Frame]]) -> None:
    sim, _ = street
    engine = make_engine(sim)
    with pytest.raises(InvalidInputError, match=r"\(10, 10\)"):
        engine.process(ImageFrame(0, np.zeros((10, 10), dtype=np.uint8)))
    with pytest.raises(InvalidInputError, match="uint8"):
        engine.process(ImageFrame(0, np.zeros((240, 320), dtype=np.float32)))  # type: ignore[arg-type]


def test_fit_tracks_exact_for_linear_motion() -> None:
    """A bearing moving linearly in time: the line fit returns it at the time centroid."""
    tau = np.array([0.0, -0.1, -0.2, -0.3, -0.4])
    v = np.array([0.1, -0.05, 0.0])
    b0 = np.array([0.0, 0.0, 1.0])
    bearings = (b0 + tau[:, None] * v)[None]
    mask = np.array([[True, True, True, True, False]])
    fit = fit_tracks(bearings, tau, mask, order=1)
    assert fit.valid[0]
    np.testing.assert_allclose(fit.tau_ref[0], -0.15)
    centre = b0 - 0.15 * v
    np.testing.assert_allclose(fit.bearing[0], centre / np.linalg.norm(centre))
    expected = v - (v @ fit.bearing[0]) * fit.bearing[0]
    np.testing.assert_allclose(fit.rate[0], expected, atol=1e-12)
    # slope sigma per unit noise = 1/sqrt(sum (tau - mean)^2)
    np.testing.assert_allclose(fit.gain[0], 1.0 / np.sqrt(0.05))
    quad = fit_tracks(bearings, tau, mask, order=2)
    np.testing.assert_allclose(quad.tau_ref[0], 0.0)
    one = fit_tracks(bearings, tau, np.array([[True, False, False, False, False]]), order=1)
    assert not one.valid[0] and np.isnan(one.rate[0]).all()


def test_fit_tracks_refers_the_rate_to_its_time_on_uneven_frames() -> None:
    """An approaching point seen at 30 Hz with one frame dropped: the line's slope is the
    bearing's derivative at centroid + m3 / (2 m2) of the frame times (exact for a
    quadratic), not at their centroid. There the rate is within 0.05 % of the analytic
    one (what a regular grid leaves: the bearing's cubic term); at the centroid it is
    0.8 % off, which is how a dropped frame used to make r/|t| read about 1 % short."""
    x0, vel = np.array([1.0, 0.5, 4.0]), np.array([0.2, 0.1, 1.5])

    def bearing(t: float) -> np.ndarray:
        x = x0 - vel * t
        return x / np.linalg.norm(x)

    def rate_at(t: float, b: np.ndarray) -> np.ndarray:
        d = (bearing(t + 1e-6) - bearing(t - 1e-6)) / 2e-6
        return d - (d @ b) * b

    for tau, shifted in ((np.array([0.0, -2.0, -3.0, -4.0]) / 30, True),
                         (np.array([0.0, -1.0, -2.0, -3.0, -4.0]) / 30, False)):  # fmt: skip
        track = np.stack([bearing(t) for t in tau])[None]
        fit = fit_tracks(track, tau, np.ones((1, tau.size), bool), 1)
        d = tau - tau.mean()
        skew = 0.5 * np.sum(d**3) / np.sum(d**2)
        np.testing.assert_allclose(fit.tau_ref[0], tau.mean() + skew, atol=1e-15)
        assert (abs(fit.tau_ref[0] - tau.mean()) > 0.01) == shifted
        expected = rate_at(fit.tau_ref[0], fit.bearing[0])
        assert np.linalg.norm(fit.rate[0] - expected) < 6e-4 * np.linalg.norm(expected)
        assert np.linalg.norm(fit.bearing[0] - bearing(fit.tau_ref[0])) < 5e-5
        at_centroid = rate_at(tau.mean(), fit.bearing[0])
        off = np.linalg.norm(fit.rate[0] - at_centroid) / np.linalg.norm(at_centroid)
        assert (off > 5e-3) == shifted


def test_first_frames_give_reasons_then_points(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]],
) -> None:
    sim, frames = street
    engine = make_engine(sim)
    engine.add_gyro(sim.gyro_samples())
    results = [engine.process(ImageFrame(f.stamp_ns, f.image)) for f in frames]
    first = results[0]
    assert first.num_points == 0 and any("frames yet" in r for r in first.reasons)
    assert first.dropped.get("young_track", 0) > 0
    later = results[-1]
    assert later.num_points > 100
    tracks = engine.last_tracks
    assert tracks is not None and tracks.stamp_ns == frames[-1].stamp_ns
    assert set(later.ids.tolist()) <= set(tracks.ids.tolist())
    assert later.heading is not None and np.isfinite(later.heading_sigma_rad)
    n = later.num_points
    for name in ("pixels", "bearings", "omega", "points"):
        assert getattr(later, name).shape[0] == n
    assert later.rot.shape == (n, 4) and later.ids.dtype == np.uint32
    assert later.flags.dtype == np.uint8
    assert np.all((later.quality >= 0) & (later.quality <= 1))
    # every point says which route(s) gave L
    routes = later.flags & (PointFlag.L_LOCAL | PointFlag.L_HEADING)
    assert np.all(routes > 0)
    # RoT is the quaternion inverse of ToR = (L, omega)
    tor = np.column_stack([later.looming, later.omega])
    prod_w = later.rot[:, 0] * tor[:, 0] - np.sum(later.rot[:, 1:] * tor[:, 1:], axis=1)
    np.testing.assert_allclose(prod_w, 1.0, atol=1e-9)
    np.testing.assert_allclose(
        np.linalg.norm(later.points, axis=1), later.range_over_speed, rtol=1e-12
    )
    for key in ("track", "integrate", "heading", "looming", "total"):
        assert later.timings[key] >= 0
    assert later.timings["total"] >= later.timings["track"]


def test_require_gyro_without_samples_gives_no_points(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]],
) -> None:
    sim, frames = street
    engine = make_engine(sim)
    results = [engine.process(ImageFrame(f.stamp_ns, f.image)) for f in frames[:7]]
    assert all(r.num_points == 0 for r in results)
    assert any("no gyro samples (require_gyro)" in r for r in results[-1].reasons)
    assert results[-1].dropped["no_gyro"] > 0


def test_without_gyro_points_are_flagged_and_rotation_comes_from_the_flow(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]],
) -> None:
    sim, frames = street
    engine = make_engine(sim, require_gyro=False)
    results = [engine.process(ImageFrame(f.stamp_ns, f.image)) for f in frames]
    last = results[-1]
    assert last.num_points > 50
    assert np.all(last.flags & PointFlag.NO_GYRO)
    assert not np.any(last.flags & PointFlag.IMU_GAP)
    assert any("without gyro" in r for r in last.reasons)
    # the camera yaws at up to 0.4 rad/s; the flow alone still gives the heading
    assert last.heading is not None
    truth = frames[-1].velocity / np.linalg.norm(frames[-1].velocity)
    assert np.degrees(np.arccos(last.heading @ truth)) < 3.0


def test_imu_gap(street: tuple[scenarios.Simulation, list[scenarios.Frame]]) -> None:
    sim, frames = street
    gyro = sim.gyro_samples()
    # IMU samples stop 0.2 s into the run (camera clock = IMU clock here)
    cut = frames[6].stamp_ns + sim.imu_time_offset_ns
    keep = gyro.stamp_ns <= cut
    partial = GyroSamples(gyro.stamp_ns[keep], gyro.angular_velocity[keep])
    strict = make_engine(sim)
    strict.add_gyro(partial)
    assert strict.covers(frames[0].stamp_ns)
    res = [strict.process(ImageFrame(f.stamp_ns, f.image)) for f in frames[:10]]
    assert not strict.covers(frames[10].stamp_ns)
    assert res[-1].num_points == 0
    assert any("IMU does not cover" in r for r in res[-1].reasons)
    lenient = make_engine(sim, require_gyro=False)
    lenient.add_gyro(partial)
    res = [lenient.process(ImageFrame(f.stamp_ns, f.image)) for f in frames[:12]]
    assert res[-1].num_points > 0
    assert np.all(res[-1].flags & PointFlag.IMU_GAP)
    assert np.all(res[-1].flags & PointFlag.NO_GYRO)


def test_time_going_backwards_resets_tracks(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]],
) -> None:
    sim, frames = street
    engine = make_engine(sim)
    engine.add_gyro(sim.gyro_samples())
    for f in frames[:8]:
        engine.process(ImageFrame(f.stamp_ns, f.image))
    back = engine.process(ImageFrame(frames[2].stamp_ns, frames[2].image))
    assert back.num_points == 0
    assert any("backwards" in r for r in back.reasons)
    # it carries on normally afterwards
    for f in frames[3:12]:
        res = engine.process(ImageFrame(f.stamp_ns, f.image))
    assert res.num_points > 0
    # a gyro run from before the newest sample clears the gyro buffer instead of being dropped
    gyro = sim.gyro_samples()
    assert engine.add_gyro(gyro) == gyro.stamp_ns.shape[0]


def test_large_frame_gap_resets(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]],
) -> None:
    sim, frames = street
    engine = make_engine(sim, max_frame_gap_s=0.05)
    engine.add_gyro(sim.gyro_samples())
    engine.process(ImageFrame(frames[0].stamp_ns, frames[0].image))
    res = engine.process(ImageFrame(frames[3].stamp_ns, frames[3].image))  # 0.1 s later
    assert any("frame gap" in r for r in res.reasons)


def test_reset_forgets_everything(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]],
) -> None:
    sim, frames = street
    engine = make_engine(sim, initial_bias_imu=(0.001, 0.0, 0.0))
    engine.add_gyro(sim.gyro_samples())
    for f in frames[:8]:
        engine.process(ImageFrame(f.stamp_ns, f.image))
    engine.reset()
    assert engine.last_tracks is None
    np.testing.assert_array_equal(engine.gyro_bias, [0.001, 0.0, 0.0])
    assert len(engine.gyro) == 0
    res = engine.process(ImageFrame(frames[8].stamp_ns, frames[8].image))
    assert res.num_points == 0


def test_deterministic(street: tuple[scenarios.Simulation, list[scenarios.Frame]]) -> None:
    sim, frames = street
    outs = []
    for _ in range(2):
        engine = make_engine(sim)
        engine.add_gyro(sim.gyro_samples())
        for f in frames[:9]:
            res = engine.process(ImageFrame(f.stamp_ns, f.image))
        outs.append(res)
    np.testing.assert_array_equal(outs[0].looming, outs[1].looming)
    np.testing.assert_array_equal(outs[0].ids, outs[1].ids)


def _street_headings(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]], **overrides: object
) -> np.ndarray:
    """(K, 3) the headings of the street's first 12 frames that have one, with engine
    option overrides."""
    sim, frames = street
    engine = make_engine(sim, **overrides)
    engine.add_gyro(sim.gyro_samples())
    out = [engine.process(ImageFrame(f.stamp_ns, f.image)).heading for f in frames[:12]]
    return np.array([h for h in out if h is not None])


def test_confirmed_warm_start_follows_the_turning_weight(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]],
) -> None:
    """``confirm_below_turning`` 0 (the turning model always weighs at least that) keeps the
    second start on every frame, exactly as ``confirmed_warm_start=False``. Above 1 a warm
    start that RANSAC confirms is refined alone whatever the filter says, which changes the
    street's headings."""
    headings = partial(_street_headings, street)
    never = headings(confirm_below_turning=0.0)
    assert never.shape[0] >= 5
    np.testing.assert_array_equal(
        never, headings(heading=HeadingOptions(confirmed_warm_start=False))
    )
    always = headings(confirm_below_turning=2.0)
    assert not np.array_equal(always, never)  # the street's frames confirm their warm starts


def test_turning_fit_window_follows_the_turning_weight(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]],
) -> None:
    """The shorter track-fit window applies only while the turning model weighs at least
    ``fit_turning_weight``: above 1 it never does, exactly as without a turning window; at 0
    it does on every frame with a heading, and the street's 0.13 s window (4 frames at 30 Hz
    against 0.15 s's 5) changes its headings."""
    headings = partial(_street_headings, street)
    never = headings(fit_turning_weight=2.0)
    assert never.shape[0] >= 5
    np.testing.assert_array_equal(never, headings(fit_turning_window_s=None))
    always = headings(fit_turning_weight=0.0)
    assert always.shape == never.shape
    assert not np.array_equal(always, never)


def test_gyro_starting_late_shortens_fits_and_says_so(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]],
) -> None:
    sim, frames = street
    gyro = sim.gyro_samples()
    start = frames[3].stamp_ns + sim.imu_time_offset_ns - 1_000_000
    keep = gyro.stamp_ns >= start
    engine = make_engine(sim)
    engine.add_gyro(GyroSamples(gyro.stamp_ns[keep], gyro.angular_velocity[keep]))
    results = [engine.process(ImageFrame(f.stamp_ns, f.image)) for f in frames[:8]]
    # frame 4 still sees its history stamps 0..2 uncovered
    assert any("does not reach back" in r for r in results[4].reasons)
    assert all(r.num_points == 0 for r in results[:7])  # 5-frame fits need 4 covered intervals
    assert results[7].num_points > 0


def test_history_bearings_reused_equal_fresh_undistortion(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]],
) -> None:
    # Each position is undistorted once and reused while it stays in the fit window; an
    # engine whose cache is cleared before every frame converts the whole history anew.
    sim, frames = street
    cam = sim.camera
    lens = CameraModel(
        cam.width, cam.height, cam.K, np.array([-0.05, 0.01, 1e-4, -1e-4, 0.0]), "plumb_bob"
    )
    opts = EngineOptions(camera_to_imu_rotation_xyzw=sim.camera_to_imu_xyzw, max_features=400)
    cached, fresh = OwlEngine(lens, opts), OwlEngine(lens, opts)
    for engine in (cached, fresh):
        engine.add_gyro(sim.gyro_samples())
    points = 0
    for frame in frames:
        fresh._state.bearing_cache = None
        a = cached.process(ImageFrame(frame.stamp_ns, frame.image))
        b = fresh.process(ImageFrame(frame.stamp_ns, frame.image))
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_allclose(a.points, b.points, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(a.bearings, b.bearings, rtol=0, atol=1e-15)
        points += a.num_points
    assert points > 1000


def test_residual_memory_is_a_running_mean_per_track(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]],
) -> None:
    """Each track's running mean coplanarity residual moves towards the frame's residual
    with the time constant residual_memory_s; a new track starts at its own residual, an
    unused one (NaN) decays towards 0; None keeps no memory."""
    sim, _ = street
    eng = make_engine(sim, residual_memory_s=0.1, residual_memory_sigma=0.5)
    ids = np.array([7, 3, 9], dtype=np.uint32)
    np.testing.assert_array_equal(eng._residual_memory(ids), 0.0)
    eng._remember_residuals(ids, 0, np.array([2.0, -1.0, np.nan]), eng._residual_memory(ids))
    np.testing.assert_allclose(eng._residual_memory(ids), [2.0, -1.0, 0.0])
    later = np.array([3, 11, 7], dtype=np.uint32)  # 9 gone, 11 new, order changed
    old = eng._residual_memory(later)
    np.testing.assert_allclose(old, [-1.0, 0.0, 2.0])
    eng._remember_residuals(later, 100_000_000, np.array([np.nan, 4.0, 0.0]), old)
    gain = 1.0 - np.exp(-1.0)  # 0.1 s at a 0.1 s time constant
    np.testing.assert_allclose(
        eng._residual_memory(later), [-1.0 * (1 - gain), 4.0, 2.0 * (1 - gain)]
    )
    off = make_engine(sim, residual_memory_s=None)
    off._remember_residuals(ids, 0, np.array([2.0, -1.0, 1.0]), off._residual_memory(ids))
    np.testing.assert_array_equal(off._residual_memory(ids), 0.0)
    with pytest.raises(InvalidInputError, match="residual_memory_s"):
        EngineOptions(residual_memory_s=0.0)


def _range_frame(points_now: np.ndarray, ids: np.ndarray, stamps: np.ndarray, rot: np.ndarray):
    """An integrate record holding only what the range filter reads: stamps, the rotation
    from the previous frame (column 1), bearings now and ids."""
    from owl_core import engine as eng

    n = points_now.shape[0]
    e_now = points_now / np.linalg.norm(points_now, axis=1, keepdims=True)
    z = np.zeros((n, 3))
    return eng._Integrated(
        stamps, np.stack([np.eye(3), rot]), True, np.uint8(0), 0.1, e_now, e_now, z,
        np.ones(n), np.zeros(n), np.zeros((n, 2)), ids, (), (), (),
    )  # fmt: skip


def test_range_filter_fuses_the_moved_previous_point_with_the_measurement(
    street: tuple[scenarios.Simulation, list[scenarios.Frame]],
) -> None:
    """Static points, the camera moving along its heading h at constant speed and turning
    by R between frames: the previous scaled point moved on by -h dt and rotated by R is
    exactly this frame's. With an exact previous state (relative sigma s_p, grown by the
    process noise) and a measurement off by a factor (1 + d) with relative sigma s_m, the
    fused inverse range is their inverse-variance mean; a measurement beyond the gate
    restarts the track at the measurement."""
    from owl_core import engine as eng
    from owl_core.geometry import so3_exp

    sim, _ = street
    e = make_engine(sim, range_process_rel=0.0, range_gate=4.0)
    h = np.array([0.1, 0.0, 1.0]) / np.linalg.norm([0.1, 0.0, 1.0])
    pts0 = np.array([[1.0, 0.5, 6.0], [-2.0, 0.3, 9.0], [0.4, -0.2, 4.0]])  # s (r/|t|)
    ids = np.array([4, 5, 6], dtype=np.uint32)
    dt, rot = 0.05, so3_exp(np.array([0.0, 0.02, 0.0]))
    stamps = np.array([int(dt * 1e9), 0], dtype=np.int64)
    headed = eng._Headed(None, h, h, 0.0, np.zeros((3, 3)), ())  # type: ignore[arg-type]
    first = _range_frame(pts0, ids, np.array([0, -1], dtype=np.int64), np.eye(3))
    r0 = np.linalg.norm(pts0, axis=1)
    out, rel = e._filter_ranges(first, headed, 0, r0, np.full(3, 0.02), np.ones(3, bool))
    np.testing.assert_allclose(out, r0)  # nothing to fuse yet
    pts1 = (pts0 - h * dt) @ rot.T  # the truth now (h is a direction fixed in the scene)
    h1 = rot @ h
    headed1 = eng._Headed(None, h1, h1, 0.0, np.zeros((3, 3)), ())  # type: ignore[arg-type]
    second = _range_frame(pts1, ids, stamps, rot)
    r1 = np.linalg.norm(pts1, axis=1)
    d = np.array([0.03, -0.03, 0.5])  # the last one is 25 sigma off: restarted
    s_m = np.array([0.02, 0.04, 0.02])
    out, rel = e._filter_ranges(
        second, headed1, int(dt * 1e9), r1 * (1 + d), s_m, np.ones(3, bool)
    )
    inv_p, inv_m = 1.0 / r1, 1.0 / (r1 * (1 + d))
    var_p, var_m = (0.02 * inv_p) ** 2, (s_m * inv_m) ** 2
    fused = (inv_p / var_p + inv_m / var_m) / (1.0 / var_p + 1.0 / var_m)
    np.testing.assert_allclose(out[:2], 1.0 / fused[:2], rtol=1e-9)
    np.testing.assert_allclose(out[2], r1[2] * 1.5, rtol=1e-12)
    np.testing.assert_allclose(rel[2], s_m[2])
    assert np.all(rel[:2] < s_m[:2])
