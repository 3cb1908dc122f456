"""The two-view baseline on synthetic correspondences with known motion."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from owl_core.baseline import (
    BaselineFrame,
    BaselineOptions,
    FilteredBaseline,
    TwoViewBaseline,
    essential_two_view,
    gyro_two_view,
)
from owl_core.camera import CameraModel
from owl_core.errors import InvalidInputError
from owl_core.geometry import so3_exp
from owl_core.tracker import Tracks
from owl_core.types import PointFlag

FOCAL = 300.0


def scene(heading, rotvec, n=150, seed=1, speed=4.0, dt=0.1):
    """Points in the current frame, their bearings in both frames, exact r/|t|.

    X1 = R X0 + t with t = -heading * speed * dt (the camera moved along heading).
    """
    rng = np.random.default_rng(seed)
    p1 = np.c_[rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), rng.uniform(5, 25, n)]
    h = np.asarray(heading, dtype=float)
    h = h / np.linalg.norm(h)
    rot = so3_exp(np.asarray(rotvec, dtype=float))
    t = -h * speed * dt
    p0 = (p1 - t) @ rot  # R^T (X1 - t), row-wise
    e0 = p0 / np.linalg.norm(p0, axis=1, keepdims=True)
    e1 = p1 / np.linalg.norm(p1, axis=1, keepdims=True)
    return e0, e1, rot, h, np.linalg.norm(p1, axis=1) / speed, dt


def angle(a, b):
    return float(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


@pytest.mark.parametrize(
    ("heading", "rotvec"),
    [((0.2, -0.1, 1.0), (0.01, -0.02, 0.015)), ((1.0, 0.1, 0.3), (0.0, 0.03, 0.0))],
)
def test_exact_correspondences_give_exact_motion_and_range(heading, rotvec):
    e0, e1, rot, h, ros, dt = scene(heading, rotvec)
    ess = essential_two_view(e0, e1, dt, FOCAL)
    gyr = gyro_two_view(e0, e1, rot, dt, FOCAL)
    # exact data: the gyro variant is exact up to the SVD's conditioning (~eps/parallax);
    # OpenCV's USAC local optimisation stops within ~1e-4 rad (0.006 deg) of the truth
    for est, tol in ((ess, 1e-4), (gyr, 1e-6)):
        assert est.heading is not None
        assert angle(est.heading, h) < tol
        assert est.inliers.all()
        np.testing.assert_allclose(est.range_over_speed, ros, rtol=100 * tol)
    np.testing.assert_allclose(ess.rotation, rot, atol=1e-5)


def test_receding_camera_heading_points_backwards():
    e0, e1, rot, h, ros, dt = scene((0.0, 0.1, -1.0), (0.0, 0.01, 0.0))
    opts = BaselineOptions(min_parallax_deg=0.0)  # keep the points near the FOE too
    for est in (
        essential_two_view(e0, e1, dt, FOCAL, opts),
        gyro_two_view(e0, e1, rot, dt, FOCAL, opts),
    ):
        assert angle(est.heading, h) < 1e-4
        np.testing.assert_allclose(est.range_over_speed, ros, rtol=1e-2)


def test_outliers_are_rejected_and_flagged():
    e0, e1, rot, h, _, dt = scene((0.3, 0.0, 1.0), (0.0, 0.02, 0.0), n=200)
    rng = np.random.default_rng(5)
    bad = rng.choice(200, 40, replace=False)
    # move the outliers' current bearings by 0.03 rad (9 px) off their epipolar plane
    e1 = e1.copy()
    normal = np.cross(e1[bad], h)
    e1[bad] += 0.03 * normal / np.linalg.norm(normal, axis=1, keepdims=True)
    e1[bad] /= np.linalg.norm(e1[bad], axis=1, keepdims=True)
    for est in (essential_two_view(e0, e1, dt, FOCAL), gyro_two_view(e0, e1, rot, dt, FOCAL)):
        assert angle(est.heading, h) < 1e-4
        good = np.setdiff1d(np.arange(200), bad)
        assert est.inliers[good].all()
        assert not est.inliers[bad].any()
        assert np.isnan(est.range_over_speed[bad]).all()


def test_biased_gyro_tilts_the_gyro_variant_only():
    e0, e1, rot, h, _, dt = scene((0.1, 0.0, 1.0), (0.0, 0.02, 0.0), n=300)
    wrong = so3_exp(np.array([0.0, 0.01 * dt, 0.0])) @ rot  # 0.01 rad/s of bias over dt
    gyr = gyro_two_view(e0, e1, wrong, dt, FOCAL, BaselineOptions(threshold_px=50.0))
    ess = essential_two_view(e0, e1, dt, FOCAL)
    assert angle(ess.heading, h) < 1e-6
    # the leftover rotation masquerades as translation: the heading tilts measurably
    assert angle(gyr.heading, h) > np.radians(0.5)


def test_too_few_points_gives_reason():
    e0, e1, _, _, _, dt = scene((0, 0, 1), (0, 0, 0), n=6)
    est = essential_two_view(e0, e1, dt, FOCAL)
    assert est.heading is None
    assert "< 8" in est.reason
    assert np.isnan(est.range_over_speed).all()


def test_bad_input_raises_with_shapes():
    with pytest.raises(InvalidInputError, match=r"\(5, 2\)"):
        essential_two_view(np.zeros((5, 2)), np.zeros((5, 2)), 0.1, FOCAL)
    with pytest.raises(InvalidInputError, match="interval_s"):
        gyro_two_view(np.ones((9, 3)), np.ones((9, 3)), np.eye(3), 0.0, FOCAL)
    with pytest.raises(InvalidInputError, match="method"):
        BaselineOptions(method="eight-point")


def test_on_tracks_uses_the_frame_gap_frames_earlier():
    cam = CameraModel.pinhole(320, 240, FOCAL, FOCAL, 159.5, 119.5)
    rng = np.random.default_rng(3)
    n = 120
    pw = np.c_[rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(6, 20, n)]
    v = np.array([0.3, 0.0, 3.0])  # m/s, camera frame, no rotation
    stamps = 1_000_000_000 + np.arange(6)[::-1] * 33_333_333  # newest first
    t_rel = (stamps - stamps[0]) * 1e-9  # <= 0
    hist = np.stack([cam.bearing_to_pixel(pw - v * tau) for tau in t_rel], axis=1)
    hist[:10, 3:] = np.nan  # ten young tracks do not reach the older view
    tracks = Tracks(
        ids=np.arange(n, dtype=np.uint32),
        pixels=hist[:, 0].copy(),
        ages=np.full(n, 5, dtype=np.int32),
        history=hist,
        stamps_ns=stamps.astype(np.int64),
    )
    calls = []

    def rotation(t0, t1):
        calls.append((t0, t1))
        return np.eye(3)

    for method in ("essential", "gyro"):
        opts = BaselineOptions(method=method, gap_frames=3, min_parallax_deg=0.0)
        base = TwoViewBaseline(cam, opts, rotation)
        out = base.process(tracks)
        assert out.interval_s == pytest.approx(3 * 0.033333333)
        assert angle(out.heading, v) < 1e-4  # pixels carry float rounding only
        assert out.ids.tolist() == list(range(10, n))
        ros_true = np.linalg.norm(pw[10:], axis=1) / np.linalg.norm(v)
        np.testing.assert_allclose(out.range_over_speed, ros_true, rtol=1e-2)
        assert not (out.flags & PointFlag.MOVING).any()
    assert calls == [(int(stamps[3]), int(stamps[0]))]
    with pytest.raises(InvalidInputError, match="rotation provider"):
        TwoViewBaseline(cam, BaselineOptions(method="gyro"))


def test_small_baselines_keep_the_sign_of_the_heading(monkeypatch: pytest.MonkeyPatch) -> None:
    """5 cm between the frames (1.5 m/s at 30 Hz), points 5-25 m away (100-500 baselines),
    0.3 px noise: every point votes in recoverPose's cheirality check, so each of ten
    scenes gets a heading and none is reversed (the 5-point heading itself is noisy this
    close: up to about 50 deg). With OpenCV's default distance threshold (50 baselines) no
    point votes: frames without a heading, or with a reversed one."""
    import owl_core.baseline as bl

    def noisy(e: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        x = e[:, :2] / e[:, 2:] + rng.normal(scale=0.3 / FOCAL, size=(e.shape[0], 2))
        v = np.column_stack([x, np.ones(e.shape[0])])
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def headings() -> list[float | None]:
        """Heading error per scene, degrees (None: no heading)."""
        out: list[float | None] = []
        for seed in range(10):
            e0, e1, _, h, _, dt = scene(
                [0.2, -0.1, 1.0], [0.01, 0.02, 0.0], n=200, seed=seed, speed=1.5, dt=1 / 30
            )
            rng = np.random.default_rng(100 + seed)
            est = bl.essential_two_view(noisy(e0, rng), noisy(e1, rng), dt, FOCAL)
            out.append(None if est.heading is None else np.degrees(angle(est.heading, h)))
        return out

    got = headings()
    assert all(a is not None and a < 90.0 for a in got), got
    monkeypatch.setattr(bl, "POSE_DISTANCE_BASELINES", 50.0)
    default = headings()
    assert any(a is None or a > 90.0 for a in default), default


def test_a_pair_a_rotation_explains_gives_no_heading() -> None:
    """The camera only turned (0.3 px tracking noise): both baselines refuse a heading, as a
    visual-odometry initialiser refuses a pair without parallax (median derotated parallax
    about 0.3 px here, below ``min_heading_parallax_px`` 0.5 px); with the gate off the
    5-point solver returns a direction fitted to the noise."""
    rng = np.random.default_rng(4)
    n = 200
    p = np.c_[rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), rng.uniform(5, 25, n)]
    rot = so3_exp(np.array([0.01, -0.02, 0.005]))
    e0 = p / np.linalg.norm(p, axis=1, keepdims=True)
    e1 = e0 @ rot.T

    def noisy(e: np.ndarray) -> np.ndarray:
        x = e[:, :2] / e[:, 2:] + rng.normal(scale=0.3 / FOCAL, size=(n, 2))
        v = np.column_stack([x, np.ones(n)])
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    a, b = noisy(e0), noisy(e1)
    ess = essential_two_view(a, b, 1 / 30, FOCAL)
    gyro = gyro_two_view(a, b, rot, 1 / 30, FOCAL)
    for est in (ess, gyro):
        assert est.heading is None
        assert est.reason is not None and "too little parallax" in est.reason
    ungated = essential_two_view(a, b, 1 / 30, FOCAL, BaselineOptions(min_heading_parallax_px=0))
    assert ungated.heading is not None
    with pytest.raises(InvalidInputError, match="min_heading_parallax_px"):
        BaselineOptions(min_heading_parallax_px=-1.0)


def _straight_path_frames(noise_deg: float, n: int = 90, seed: int = 4):
    """A camera on a straight line, turning at a constant rate (30 Hz, gap 1): per frame
    the true heading in the current camera frame and a two-view measurement of it with
    isotropic angular noise; the gyro's R_{1<-0} between any two stamps."""
    rate = np.array([0.0, 0.4, 0.05])  # rad/s, camera frame
    world_heading = np.array([0.3, 0.0, 1.0]) / np.linalg.norm([0.3, 0.0, 1.0])
    rng = np.random.default_rng(seed)
    dt_ns = 33_333_333
    frames, truth = [], []
    for k in range(n):
        stamp = (k + 1) * dt_ns
        h = so3_exp(-rate * stamp * 1e-9) @ world_heading  # world direction seen now
        z = h + np.radians(noise_deg) * rng.standard_normal(3)
        pixels = rng.uniform(0, 100, (5, 2))
        frames.append(
            BaselineFrame(
                stamp, z / np.linalg.norm(z), pixels, np.arange(5, dtype=np.uint32),
                np.ones(5), np.zeros(5, np.uint8), dt_ns * 1e-9, {"estimate": 0.001},
            )
        )  # fmt: skip
        truth.append(h)

    def rotation(t0: int, t1: int) -> np.ndarray:
        return so3_exp(-rate * (t1 - t0) * 1e-9)

    return frames, truth, rotation


def test_filtered_baseline_averages_a_straight_path_and_follows_the_turning_camera():
    """The same heading filter as OWL's: exact measurements stay exact while the camera
    turns (the gyro's rotation carries the state between frames), and noisy ones are
    averaged (after a second, the error well below a single frame's)."""
    frames, truth, rotation = _straight_path_frames(0.0)
    flt = FilteredBaseline(np.radians(0.2), rotation)
    for f, h in zip(frames, truth, strict=True):
        out = flt.step(f)
        assert angle(out.heading, h) < 1e-6
        assert out.pixels is f.pixels and out.range_over_speed is f.range_over_speed
        assert out.timings["estimate"] >= f.timings["estimate"]
    frames, truth, rotation = _straight_path_frames(0.5)
    flt = FilteredBaseline(np.radians(0.5), rotation)
    raw = [np.degrees(angle(f.heading, h)) for f, h in zip(frames, truth, strict=True)]
    filtered = [
        np.degrees(angle(flt.step(f).heading, h)) for f, h in zip(frames, truth, strict=True)
    ]
    assert np.median(filtered[30:]) < 0.3 * np.median(raw[30:]), (
        np.median(filtered[30:]),
        np.median(raw[30:]),
    )


def test_filtered_baseline_without_a_measurement_or_a_gyro():
    """No two-view heading: none filtered either (the state is kept). A step the gyro does
    not cover restarts the filter from the measurement."""
    frames, truth, rotation = _straight_path_frames(0.0, n=6)
    flt = FilteredBaseline(np.radians(0.2), rotation)
    flt.step(frames[0])
    empty = replace(frames[1], heading=None)
    assert flt.step(empty).heading is None
    assert angle(flt.step(frames[2]).heading, truth[2]) < 1e-6  # predicted across the gap
    blind = FilteredBaseline(np.radians(0.2), lambda t0, t1: None)
    blind.step(frames[3])
    assert np.allclose(blind.step(frames[4]).heading, frames[4].heading)  # restarted
    with pytest.raises(InvalidInputError, match="sigma_rad"):
        FilteredBaseline(0.0, rotation)


def test_rolling_shutter_gyro_baseline_derotates_each_row() -> None:
    """A camera turning at 0.8 rad/s while walking, 30 ms readout: derotating every point from
    its own row's time makes the gyro-aided heading exact (the camera centres of all rows lie
    on the straight path, so every epipolar plane still holds it); one rotation per frame
    leaves the readout's skew in the pairs."""
    from owl_core import rolling_shutter as rs
    from owl_core.gyro import GyroBuffer
    from owl_core.types import GyroSamples

    cam = CameraModel.pinhole(320, 240, FOCAL, FOCAL, 159.5, 119.5)
    readout_ns = 30_000_000
    w = np.array([0.1, 0.8, -0.2])  # rad/s, camera frame (identity extrinsic)
    v = np.array([0.3, 0.0, 1.5])  # m/s, world frame
    gyro = GyroBuffer()
    t_imu = np.arange(0, 400) * 2_500_000  # 400 Hz over 1 s
    gyro.add(GyroSamples(t_imu.astype(np.int64), np.tile(w, (t_imu.size, 1))))

    def r_wc(t_ns: float) -> np.ndarray:  # camera -> world; body rates w
        return so3_exp(w * (t_ns * 1e-9))

    rng = np.random.default_rng(8)
    n = 150
    z = rng.uniform(2, 8, n)
    pw = np.c_[rng.uniform(-0.4, 0.4, n) * z, rng.uniform(-0.3, 0.3, n) * z, z]
    stamps = np.array([500_000_000, 466_666_667], dtype=np.int64)  # newest first

    def seen(stamp: int) -> np.ndarray:
        """Pixels of every point at the time of the row it lands on (fixed-point)."""
        v_px = np.full(n, 120.0)
        for _ in range(10):  # converges by about 0.03 (rotation x readout) an iteration
            t = stamp + v_px / cam.height * readout_ns
            xc = np.stack(
                [r_wc(t[i]).T @ (pw[i] - v * t[i] * 1e-9) for i in range(n)]
            )  # per-point poses: test geometry, not a hot path
            px = cam.bearing_to_pixel(xc / np.linalg.norm(xc, axis=1, keepdims=True))
            v_px = px[:, 1]
        px[(v_px < 0) | (v_px > cam.height - 1)] = np.nan
        return px

    hist = np.stack([seen(int(s)) for s in stamps], axis=1)
    inside = np.isfinite(hist).all(axis=(1, 2))
    hist = hist[inside]
    tracks = Tracks(
        ids=np.arange(hist.shape[0], dtype=np.uint32),
        pixels=hist[:, 0].copy(),
        ages=np.full(hist.shape[0], 2, dtype=np.int32),
        history=hist,
        stamps_ns=stamps,
    )
    truth = r_wc(float(stamps[0])).T @ v  # heading in the camera frame at the stamp

    def rotation(t0: int, t1: int) -> np.ndarray:
        return gyro.relative_rotation(t0, t1)

    def rows(frames: np.ndarray, stamp: int) -> rs.ReadoutRotations:
        return rs.readout_rotations(gyro, frames, stamp, readout_ns, np.zeros(3))

    opts = BaselineOptions(method="gyro", gap_frames=1, min_parallax_deg=0.0)
    per_row = TwoViewBaseline(cam, opts, rotation, rows).process(tracks)
    per_frame = TwoViewBaseline(cam, opts, rotation).process(tracks)
    assert per_row.heading is not None and per_frame.heading is not None
    err_row, err_frame = angle(per_row.heading, truth), angle(per_frame.heading, truth)
    # exact geometry and an exact (constant-rate) gyro: pixels' float rounding only
    assert err_row < 1e-4, err_row
    # 0.8 rad/s x 30 ms = 1.4 deg of skew across the image, about as much as the
    # translational parallax: one rotation per frame leaves the heading 0.66 deg off here
    assert math.degrees(err_frame) > 0.3, err_frame
    # the 5-point baseline has no gyro: row rotations do not apply to it
    ess = TwoViewBaseline(cam, replace(opts, method="essential"), None, rows)
    assert ess._row_rotations is None
    with pytest.raises(InvalidInputError, match="rotation provider"):
        TwoViewBaseline(cam, BaselineOptions(method="gyro"))
