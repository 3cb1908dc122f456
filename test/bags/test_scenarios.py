"""bags.sim.scenarios / bags.sim.sensors: exact trajectories, REP 145 IMU, gyro vs ground-truth
rotation (through owl_core.gyro.GyroBuffer), range/pose consistency, moving mask, scaling."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest

from bags.errors import ScenarioError
from bags.sim import scenarios
from bags.sim.scenarios import SimOptions
from bags.sim.sensors import GRAVITY_W, ImuOptions
from owl_core.geometry import quat_xyzw_to_matrix, so3_log
from owl_core.gyro import GyroBuffer
from owl_core.types import GyroSamples

SMALL = SimOptions(seconds=0.5, rate_hz=10.0, width=160, height=120, noise_sigma=0.0)


def test_listing_and_unknown_name() -> None:
    expected = {
        "cube",
        "scaled",
        "accel",
        "turn",
        "street",
        "mover",
        "rotation_only",
        "pan_only",
        "handheld",
        "still",
        "receding",
        "car",
        "sideways",
        "slow_start",
        "brisk",
    }
    assert set(scenarios.names()) == expected
    assert all(
        scenarios.DESCRIPTIONS[n] and "\n" not in scenarios.DESCRIPTIONS[n] for n in expected
    )
    with pytest.raises(ScenarioError, match=r"unknown scenario 'nope'.*street"):
        scenarios.get("nope")
    with pytest.raises(ScenarioError, match="rate"):
        SimOptions(rate_hz=-1.0)
    with pytest.raises(ScenarioError, match="width"):
        SimOptions(width=0)
    with pytest.raises(ScenarioError, match="supersample"):
        SimOptions(supersample=5)
    frames = list(scenarios.get("still").render_frames(replace(SMALL, seconds=0.1)))
    assert [f.index for f in frames] == [0, 1]


@pytest.mark.parametrize("name", scenarios.names())
def test_trajectory_derivatives_are_exact(name: str) -> None:
    """Velocity, acceleration and angular velocity match central differences (O(h^2))."""
    sim = scenarios.get(name).simulate(replace(SMALL, scale=1.7))
    traj = sim.trajectory
    t = np.array([0.0, 0.37, 1.1, 2.9])
    h = 1e-4
    s0, sp, sm = traj.state(t), traj.state(t + h), traj.state(t - h)
    np.testing.assert_allclose((sp.position - sm.position) / (2 * h), s0.velocity, atol=1e-6)
    np.testing.assert_allclose((sp.velocity - sm.velocity) / (2 * h), s0.acceleration, atol=1e-6)
    # body rate: R(t+h) = R(t - h) exp(2h [w]x) to second order
    for i in range(t.size):
        rel = sm.R_wb[i].T @ sp.R_wb[i]
        np.testing.assert_allclose(so3_log(rel) / (2 * h), s0.omega_b[i], atol=1e-6)
        np.testing.assert_allclose(s0.R_wb[i] @ s0.R_wb[i].T, np.eye(3), atol=1e-12)


def test_imu_rep145_specific_force_and_frames() -> None:
    quiet = ImuOptions(gyro_noise=0.0, accel_noise=0.0)
    still = scenarios.get("still").simulate(replace(SMALL, imu=quiet))
    n = still.imu.stamp_ns.size
    up = np.broadcast_to([0.0, 0.0, 9.80665], (n, 3))
    np.testing.assert_allclose(still.imu.linear_acceleration, up, atol=1e-12)
    np.testing.assert_allclose(still.imu.angular_velocity, 0.0, atol=1e-15)
    accel = scenarios.get("accel").simulate(replace(SMALL, imu=quiet))
    fwd = np.broadcast_to([2.0, 0.0, 9.80665], accel.imu.linear_acceleration.shape)
    np.testing.assert_allclose(accel.imu.linear_acceleration, fwd, atol=1e-12)
    # the camera looks along the IMU x axis: the contract's quaternion
    assert still.camera_to_imu_xyzw == (-0.5, 0.5, -0.5, 0.5)
    r_bc = quat_xyzw_to_matrix(np.array(still.camera_to_imu_xyzw))
    np.testing.assert_allclose(r_bc @ [0, 0, 1], [1, 0, 0], atol=1e-15)  # optical axis = x
    np.testing.assert_allclose(r_bc @ [0, 1, 0], [0, 0, -1], atol=1e-15)  # image down = -z
    # a yaw to the left (IMU +z) is a rotation about the camera's -y axis
    turn = scenarios.get("turn").simulate(replace(SMALL, imu=quiet))
    st = turn.trajectory.state(1.0)
    _, omega_c = turn.twist(1.0)
    assert st.omega_b[0, 2] > 0.05 and omega_c[1] < -0.05
    np.testing.assert_allclose(r_bc @ omega_c, st.omega_b[0], atol=1e-12)
    # level turn: specific force = centripetal (lateral, +y to the left) + gravity reaction
    f = turn.imu.linear_acceleration
    assert np.all(f[:, 2] > 9.0) and np.all(f[:, 1] > 0.0)
    assert GRAVITY_W[2] < 0


def _gyro_error(sim, offset_ns: int, bias=(0.0, 0.0, 0.0)) -> float:
    buf = GyroBuffer(sim.camera_to_imu_xyzw, offset_ns)
    buf.add(sim.gyro_samples())
    stamps = sim.frame_stamps_ns
    worst = 0.0
    for t0, t1 in itertools.pairwise(stamps):
        got = buf.relative_rotation(int(t0), int(t1), bias_imu=bias)
        truth = sim.relative_rotation(int(t0), int(t1))
        worst = max(worst, float(np.linalg.norm(so3_log(got.T @ truth))))
    return worst


def test_gyro_integration_reproduces_ground_truth_rotation() -> None:
    sigma = 0.002  # rad/s per sample
    bias = (0.004, -0.003, 0.002)
    imu = ImuOptions(rate_hz=400.0, gyro_noise=sigma, gyro_bias=bias, time_offset_s=0.0123)
    sim = scenarios.get("rotation_only").simulate(replace(SMALL, seconds=1.0, imu=imu, seed=3))
    off = sim.imu_time_offset_ns
    assert off == 12_300_000
    # each frame interval (0.1 s) integrates 40 samples: the rotation error from white noise
    # is about sigma * dt * sqrt(40) = 1.3e-5 rad per axis; allow 5 sigma on the norm.
    bound = 5 * sigma * 0.0025 * math.sqrt(40) * math.sqrt(3)
    assert _gyro_error(sim, off, bias) < bound
    # the same gyro without removing the bias, or with the wrong time offset, is wrong
    assert _gyro_error(sim, off) > 0.8 * np.linalg.norm(bias) * 0.1  # |b| dt, less noise
    assert _gyro_error(sim, 0, bias) > 10 * bound
    # noise-free: exact up to the piecewise-linear interpolation of a smooth rate
    quiet = scenarios.get("street").simulate(replace(SMALL, imu=ImuOptions(gyro_noise=0.0)))
    assert _gyro_error(quiet, 0) < 1e-6


def test_imu_covers_frames_with_offset_and_random_walk() -> None:
    imu = ImuOptions(rate_hz=200.0, gyro_noise=0.0, gyro_bias_walk=0.01, time_offset_s=-0.02)
    sim = scenarios.get("still").simulate(replace(SMALL, imu=imu))
    stamps = sim.imu.stamp_ns
    assert np.all(np.diff(stamps) == 5_000_000)
    frames = sim.frame_stamps_ns
    assert stamps[0] <= frames[0] + sim.imu_time_offset_ns - 50_000_000
    assert stamps[-1] >= frames[-1] + sim.imu_time_offset_ns + 50_000_000
    # still camera: the gyro reads exactly the (wandering) bias
    np.testing.assert_allclose(sim.imu.angular_velocity, sim.imu.gyro_bias, atol=1e-15)
    steps = np.diff(sim.imu.gyro_bias, axis=0)
    assert abs(steps.std() / (0.01 * math.sqrt(0.005)) - 1) < 0.1
    samples = sim.gyro_samples()
    assert isinstance(samples, GyroSamples) and samples.stamp_ns.dtype == np.int64
    assert samples.angular_velocity.shape == (stamps.size, 3)


@pytest.mark.parametrize("name", ["street", "mover", "turn"])
def test_ranges_reproject_between_frames(name: str) -> None:
    """World points from frame k's range image appear at frame k+1 where the pose says."""
    sim = scenarios.get(name).simulate(replace(SMALL, seconds=0.2))
    f0, f1 = sim.frame(0), sim.frame(1)
    cam = sim.camera
    uu, vv = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    pix = np.stack([uu, vv], -1).reshape(-1, 2).astype(float)
    r0 = f0.range_m.reshape(-1).astype(float)
    static = np.isfinite(r0) & ~f0.mask.reshape(-1)
    e0 = cam.pixel_to_bearing(pix[static])
    pw = f0.c_w + (e0 * r0[static, None]) @ f0.R_wc.T
    pc1 = (pw - f1.c_w) @ f1.R_wc  # camera frame at k+1
    uv1 = cam.bearing_to_pixel(pc1)
    ok = cam.in_image(uv1, margin_px=1.0)
    iu, iv = np.rint(uv1[ok]).astype(int).T
    same = f1.object_id[iv, iu] == f0.object_id.reshape(-1)[static][ok]
    assert same.mean() > 0.95  # the rest: occlusion changes and object edges
    pred = np.linalg.norm(pc1[ok], axis=1)[same]
    got = f1.range_m[iv, iu][same].astype(float)
    # nearest-pixel lookup: the range changes by at most ~1 pixel's worth of surface
    rel = np.abs(pred - got) / got
    assert np.median(rel) < 0.01


def test_moving_mask_marks_exactly_the_car() -> None:
    sim = scenarios.get("mover").simulate(replace(SMALL, seconds=0.3))
    f = sim.frame(3)
    assert f.mask.sum() > 50
    np.testing.assert_array_equal(f.mask, f.object_id == 50)
    cam = sim.camera
    vv, uu = np.nonzero(f.mask)
    e = cam.pixel_to_bearing(np.stack([uu, vv], -1).astype(float))
    pw = f.c_w + (e * f.range_m[vv, uu, None].astype(float)) @ f.R_wc.T
    car = [r for r in sim.scene_at(f.t) if r.object_id == 50]
    on = np.zeros(len(pw), dtype=bool)
    for r in car:
        on |= r.contains(pw, tol=1e-3)
    assert on.all()
    assert not scenarios.get("street").simulate(SMALL).frame(0).mask.any()


def test_scaled_scenario_gives_identical_images() -> None:
    base = scenarios.get("scaled").simulate(replace(SMALL, scale=1.0, noise_sigma=2.0))
    big = scenarios.get("scaled").simulate(replace(SMALL, noise_sigma=2.0))
    assert big.scale == 3.0
    for k in (0, 4):
        a, b = base.frame(k), big.frame(k)
        diff = np.abs(a.image.astype(int) - b.image.astype(int))
        assert np.mean(diff > 0) < 0.005  # float32 rounding only
        # larger differences only where a sub-pixel ray flips across an object edge
        ids = a.object_id.astype(int)
        pad = np.pad(ids, 1, mode="edge")
        edge = np.zeros_like(ids, dtype=bool)
        for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
            edge |= pad[dy : dy + ids.shape[0], dx : dx + ids.shape[1]] != ids
        assert not np.any((diff > 2) & ~edge)
        fin = np.isfinite(a.range_m)
        np.testing.assert_allclose(b.range_m[fin], 3.0 * a.range_m[fin], rtol=1e-4)
        np.testing.assert_allclose(b.velocity, 3.0 * a.velocity, rtol=1e-12)
        np.testing.assert_allclose(b.omega, a.omega, atol=1e-15)
        assert np.linalg.norm(a.velocity) > 0.5 and np.linalg.norm(a.omega) > 0.01


def test_ground_truth_twist_conventions() -> None:
    recede = scenarios.get("receding").simulate(SMALL)
    v, w = recede.twist(0.2)
    np.testing.assert_allclose(v, [0.0, 0.0, -3.0], atol=1e-12)  # backwards along optical z
    np.testing.assert_allclose(w, 0.0, atol=1e-15)
    cube = scenarios.get("cube").simulate(SMALL)
    v, _ = cube.twist(0.0)
    # world (1, 0.15, 0) = forward and to the left = camera (-0.15, 0, 1)
    np.testing.assert_allclose(v, [-0.15, 0.0, 1.0], atol=1e-12)
    with pytest.raises(ScenarioError, match="frame index"):
        cube.frame(99)


def test_car_camera_ahead_of_the_axle_swings_off_the_car_axis_in_turns() -> None:
    """The camera 1.5 m ahead of the rear axle moves at v_axle + lever * yaw' * left: its
    heading leaves the car's axis by atan(lever yaw' / speed)."""
    sim = scenarios.get("car").simulate(replace(SMALL, seconds=8.0))
    t = np.array([0.0, 1.0, 2.0, 4.0])
    st = sim.trajectory.state(t)
    speed = np.array([1.0, 4.5 - 3.5 * math.cos(math.pi / 4), 4.5, 8.0])
    yaw_rate = 0.6 * np.sin(2 * math.pi * t / 4.0)
    yaw = np.arctan2(st.R_wb[:, 1, 0], st.R_wb[:, 0, 0])
    fwd = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    left = np.stack([-np.sin(yaw), np.cos(yaw)], axis=1)
    np.testing.assert_allclose(np.einsum("ni,ni->n", st.velocity[:, :2], fwd), speed, atol=1e-9)
    np.testing.assert_allclose(
        np.einsum("ni,ni->n", st.velocity[:, :2], left), 1.5 * yaw_rate, atol=1e-9
    )
    np.testing.assert_allclose(st.omega_b[:, 2], yaw_rate, atol=1e-12)
    # the axle (camera minus the lever) moves along the car's axis: no side slip
    axle = st.position[:, :2] - 1.5 * fwd
    h = 1e-4
    sp, sm = sim.trajectory.state(t + h), sim.trajectory.state(t - h)

    def axle_at(s):
        y = np.arctan2(s.R_wb[:, 1, 0], s.R_wb[:, 0, 0])
        return s.position[:, :2] - 1.5 * np.stack([np.cos(y), np.sin(y)], axis=1)

    v_axle = (axle_at(sp) - axle_at(sm)) / (2 * h)
    np.testing.assert_allclose(np.einsum("ni,ni->n", v_axle, left), 0.0, atol=1e-6)
    assert axle.shape == (4, 2)


def test_sideways_rotation_starts_and_stops() -> None:
    sim = scenarios.get("sideways").simulate(replace(SMALL, seconds=3.0))
    st = sim.trajectory.state(np.array([0.5, 0.99, 1.5, 2.01, 2.5]))
    np.testing.assert_allclose(st.omega_b[:, 2], [0.0, 0.0, 0.4, 0.0, 0.0], atol=1e-3)
    # total yaw = mean rate x duration = 0.2 rad
    end = sim.trajectory.state(np.array([3.0]))
    assert math.atan2(end.R_wb[0, 1, 0], end.R_wb[0, 0, 0]) == pytest.approx(0.2, abs=1e-12)


def test_imu_models_per_sample_noise_follows_the_density() -> None:
    from bags.sim.sensors import IMU_MODELS

    adis = IMU_MODELS["adis16448"]
    assert adis.rate_hz == 200.0
    assert adis.gyro_noise == pytest.approx(1.6968e-4 * math.sqrt(200.0))
    mems = IMU_MODELS["mems400"]
    assert mems.gyro_noise == pytest.approx(math.radians(0.014) * 20.0)
    sim = scenarios.get("still").simulate(replace(SMALL, seconds=2.0, imu=mems))
    noise = sim.imu.angular_velocity - sim.imu.true_angular_velocity - sim.imu.gyro_bias
    assert np.std(noise) == pytest.approx(mems.gyro_noise, rel=0.05)  # 2400 samples


def test_rolling_shutter_rows_at_their_times_and_range_at_the_stamp() -> None:
    """Row r is the scene at stamp + (r / H) T; the range truth is measured from the camera
    centre at the stamp to the point each pixel sees."""
    readout = 0.03
    opts = replace(SMALL, seconds=0.5)
    rolling = scenarios.get("brisk").simulate(replace(opts, rolling_shutter_readout_s=readout))
    glob = scenarios.get("brisk").simulate(opts)
    f = rolling.frame(3)
    h = rolling.camera.height
    cam = rolling.camera
    for row in (0, 40, h - 1):
        t_row = f.t + row / h * readout
        g = glob.frame_at(t_row, 3)
        assert np.abs(f.image[row].astype(int) - g.image[row].astype(int)).max() <= 1
        np.testing.assert_array_equal(f.object_id[row], g.object_id[row])
        # the point pixel (u, row) sees, from row's pose, measured from the stamp's centre
        fin = np.isfinite(g.range_m[row])
        pix = np.stack([np.arange(cam.width), np.full(cam.width, row)], -1).astype(float)
        rays = cam.pixel_to_bearing(pix[fin]) @ g.R_wc.T
        world = g.c_w + g.range_m[row, fin, None].astype(float) * rays
        expected = np.linalg.norm(world - f.c_w, axis=1)
        np.testing.assert_allclose(f.range_m[row, fin], expected, rtol=2e-5)
    # twist and pose are those of the stamp; the IMU reaches past the last row
    np.testing.assert_allclose(f.velocity, glob.frame(3).velocity, atol=1e-12)
    last = rolling.frame_stamps_ns[-1] + round(readout * 1e9) + rolling.imu_time_offset_ns
    assert rolling.imu.stamp_ns[-1] >= last
    with pytest.raises(ScenarioError, match="readout"):
        SimOptions(rolling_shutter_readout_s=-0.01)
