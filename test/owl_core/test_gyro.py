"""GyroBuffer: rotation between camera stamps against independent simulations."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from owl_core.errors import CalibrationError, InvalidInputError, TimeError
from owl_core.geometry import so3_exp
from owl_core.gyro import GyroBuffer, GyroProblem
from owl_core.types import GyroSamples

# Camera looking along IMU x (IMU x forward, y left, z up), from the contract.
Q_FORWARD = (-0.5, 0.5, -0.5, 0.5)
R_CAM_TO_IMU = Rotation.from_quat(Q_FORWARD).as_matrix()  # scipy also uses (x, y, z, w)
MS = 1_000_000
T_START = 1_700_000_000_000_000_000  # realistic epoch stamps stress int64 handling


def _samples(stamps: np.ndarray, rates: np.ndarray) -> GyroSamples:
    return GyroSamples(np.asarray(stamps, dtype=np.int64), np.asarray(rates, dtype=np.float64))


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle of the rotation between a and b, rad (scipy, accurate for tiny angles)."""
    return float(Rotation.from_matrix(a.T @ b).magnitude())


def _ode_rotation(rate_cam, t0: float, t1: float) -> np.ndarray:  # type: ignore[no-untyped-def]
    """R_{1<-0} by numerically integrating a world-fixed direction basis.

    e(t) = R_wc(t)^T d obeys de/dt = -Omega(t) x e; integrate the three basis
    directions (the columns of R_{t<-0}) with a tight-tolerance ODE solver.
    """

    def rhs(t: float, y: np.ndarray) -> np.ndarray:
        e = y.reshape(3, 3)  # rows = directions
        return (-np.cross(rate_cam(t), e)).ravel()

    sol = solve_ivp(rhs, (t0, t1), np.eye(3).ravel(), method="DOP853", rtol=1e-13, atol=1e-14)
    return sol.y[:, -1].reshape(3, 3).T  # columns = images of the basis vectors


def test_constant_rate_moves_world_fixed_direction() -> None:
    # Simulated independently: R_wc(t) = R0 expm([w] t), bearing e(t) = R_wc(t)^T d.
    w_cam = np.array([0.3, -1.1, 0.7])
    r0 = Rotation.from_rotvec([0.2, 0.4, -0.1]).as_matrix()
    d = np.array([0.3, -0.2, 0.93])
    d /= np.linalg.norm(d)

    def bearing(t: float) -> np.ndarray:
        return (r0 @ Rotation.from_rotvec(w_cam * t).as_matrix()).T @ d

    stamps = T_START + np.arange(0, 200) * 5 * MS  # 200 Hz for 1 s
    buf = GyroBuffer(Q_FORWARD)
    imu_rate = R_CAM_TO_IMU @ w_cam  # what an IMU-frame gyro measures
    assert buf.add(_samples(stamps, np.tile(imu_rate, (200, 1)))) == 200
    t0, t1 = T_START + 12_345_678, T_START + 45_678_901  # between samples
    dt = (t1 - t0) * 1e-9
    rot = buf.relative_rotation(t0, t1)
    np.testing.assert_allclose(
        rot @ bearing((t0 - T_START) * 1e-9), bearing((t1 - T_START) * 1e-9), atol=1e-14
    )
    np.testing.assert_allclose(rot, so3_exp(-w_cam * dt), atol=1e-15)
    np.testing.assert_allclose(buf.mean_rate_camera(t0, t1), w_cam, atol=1e-12)
    np.testing.assert_allclose(buf.rate_camera(t0), w_cam, atol=1e-15)


def test_extrinsic_yaw_left_moves_image_right() -> None:
    # IMU yaws left (+z up) at 1 rad/s: a point straight ahead moves to the
    # camera's right (+x) and stays at the image row (y = 0).
    buf = GyroBuffer(Q_FORWARD)
    stamps = np.arange(0, 11) * 10 * MS
    buf.add(_samples(stamps, np.tile([0.0, 0.0, 1.0], (11, 1))))
    e1 = buf.relative_rotation(0, 100 * MS) @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(e1, [np.sin(0.1), 0.0, np.cos(0.1)], atol=1e-15)
    np.testing.assert_allclose(buf.mean_rate_camera(0, 100 * MS), [0.0, -1.0, 0.0], atol=1e-13)


def test_piecewise_linear_rate_matches_ode() -> None:
    rng = np.random.default_rng(3)
    stamps = T_START + np.cumsum(rng.integers(3 * MS, 8 * MS, size=40))  # jittered ~200 Hz
    rates_imu = rng.normal(scale=2.0, size=(40, 3))  # fast, strongly non-commuting
    buf = GyroBuffer(Q_FORWARD, capacity_s=5.0)
    buf.add(_samples(stamps, rates_imu))
    rel = (stamps - T_START) * 1e-9
    rates_cam = rates_imu @ R_CAM_TO_IMU  # R^T w row-wise

    def rate(t: float) -> np.ndarray:
        return np.array([np.interp(t, rel, rates_cam[:, i]) for i in range(3)])

    for t0, t1 in [
        (stamps[2] + 1_234_567, stamps[20] - 777),  # inside intervals
        (stamps[5], stamps[9]),  # exactly on samples
        (stamps[0], stamps[-1]),  # the whole buffer
        (stamps[7] + 10, stamps[7] + 2 * MS),  # within one sample interval
    ]:
        ref = _ode_rotation(rate, (t0 - T_START) * 1e-9, (t1 - T_START) * 1e-9)
        assert _angle(buf.relative_rotation(t0, t1), ref) < 1e-9


def test_time_offset() -> None:
    # A rate ramping in time: the IMU stamps an event `offset` later than the camera.
    offset = 7 * MS
    stamps_cam = np.arange(0, 101) * 5 * MS
    ramp = np.stack([np.linspace(0, 2, 101), np.linspace(1, -1, 101), np.full(101, 0.5)], -1)
    buf = GyroBuffer(imu_time_offset_ns=offset)
    buf.add(_samples(stamps_cam + offset, ramp))
    plain = GyroBuffer()
    plain.add(_samples(stamps_cam, ramp))
    t0, t1 = 100 * MS, 133 * MS
    np.testing.assert_allclose(
        buf.relative_rotation(t0, t1), plain.relative_rotation(t0, t1), atol=1e-15
    )
    ignored = GyroBuffer()
    ignored.add(_samples(stamps_cam + offset, ramp))
    assert _angle(ignored.relative_rotation(t0, t1), plain.relative_rotation(t0, t1)) > 1e-4
    assert buf.covers(0, 500 * MS) and not buf.covers(0, 500 * MS + 1)
    assert buf.camera_span_ns == (0, 500 * MS)


def test_bias_is_subtracted_in_imu_frame() -> None:
    w_cam = np.array([0.2, 0.1, -0.3])
    bias_imu = np.array([0.01, -0.02, 0.005])
    stamps = np.arange(0, 50) * 5 * MS
    buf = GyroBuffer(Q_FORWARD)
    buf.add(_samples(stamps, np.tile(R_CAM_TO_IMU @ w_cam + bias_imu, (50, 1))))
    t0, t1 = 3 * MS, 201 * MS
    dt = (t1 - t0) * 1e-9
    np.testing.assert_allclose(
        buf.relative_rotation(t0, t1, bias_imu), so3_exp(-w_cam * dt), atol=1e-15
    )
    biased = so3_exp(-(w_cam + R_CAM_TO_IMU.T @ bias_imu) * dt)
    np.testing.assert_allclose(buf.relative_rotation(t0, t1), biased, atol=1e-15)
    np.testing.assert_allclose(buf.mean_rate_camera(t0, t1, bias_imu), w_cam, atol=1e-12)


def test_interval_edges_and_inverse() -> None:
    stamps = np.array([0, 10, 20, 30]) * MS
    rates = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 3.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    buf = GyroBuffer()
    buf.add(_samples(stamps, rates))
    # Interpolation at both ends: about z only over [2.5, 10] ms, rate 1.5 -> 3 rad/s.
    r = buf.relative_rotation(int(2.5 * MS), 10 * MS)
    np.testing.assert_allclose(r, so3_exp([0.0, 0.0, -(1.5 + 3.0) / 2 * 0.0075]), atol=1e-15)
    np.testing.assert_allclose(buf.rate_camera(5 * MS), [0.0, 0.0, 2.0], atol=1e-15)
    np.testing.assert_allclose(buf.relative_rotation(0, 0), np.eye(3), atol=0)
    np.testing.assert_allclose(buf.relative_rotation(30 * MS, 30 * MS), np.eye(3), atol=0)
    fwd = buf.relative_rotation(5 * MS, 27 * MS)
    np.testing.assert_allclose(buf.relative_rotation(27 * MS, 5 * MS), fwd.T, atol=1e-16)
    # Splitting at a non-sample time composes exactly.
    split = buf.relative_rotation(16 * MS, 27 * MS) @ buf.relative_rotation(5 * MS, 16 * MS)
    np.testing.assert_allclose(split, fwd, atol=1e-15)
    assert buf.covers(0, 30 * MS) and not buf.covers(-1, 30 * MS)
    assert not buf.covers(0, 30 * MS + 1)
    with pytest.raises(TimeError, match=r"\[0, 30000001\] ns.*\[0, 30000000\]"):
        buf.relative_rotation(0, 30 * MS + 1)
    with pytest.raises(TimeError, match="no samples"):
        GyroBuffer().relative_rotation(0, 1)


def test_drops_are_counted() -> None:
    buf = GyroBuffer()
    stamps = np.array([10, 20, 20, 15, 30, 40, 35, 50]) * MS
    rates = np.zeros((8, 3))
    rates[4, 1] = np.nan  # 30 ms: non-finite
    assert buf.add(_samples(stamps, rates)) == 4  # 10, 20, 40, 50
    assert buf.dropped == {"non_finite": 1, "duplicate": 1, "out_of_order": 2}
    np.testing.assert_array_equal(buf.stamps_ns, np.array([10, 20, 40, 50]) * MS)
    # against the newest accepted stamp of an earlier call
    assert buf.add(_samples(np.array([50, 45, 60]) * MS, np.zeros((3, 3)))) == 1
    assert buf.dropped == {"non_finite": 1, "duplicate": 2, "out_of_order": 3}
    buf.reset()
    assert len(buf) == 0 and buf.dropped == {"non_finite": 0, "duplicate": 0, "out_of_order": 0}
    assert buf.camera_span_ns is None and not buf.covers(0, 0)


def test_intake_reports_what_it_rejected_and_never_bridges_a_gap() -> None:
    buf = GyroBuffer()
    stamps = np.array([10, 20, 20, 15, 30, 90, 100, 95]) * MS
    rates = np.zeros((8, 3))
    rates[4] = (np.nan, 1.0, 2.0)  # 30 ms: non-finite
    got = buf.intake(_samples(stamps, rates), max_gap_ns=50 * MS)
    # 90 ms opens a gap (70 ms after 20 ms): what lies before it is forgotten
    assert (got.accepted, got.non_finite, got.duplicate, got.out_of_order, got.gaps) == (
        2,
        1,
        1,
        2,
        1,
    )
    np.testing.assert_array_equal(buf.stamps_ns, np.array([90, 100]) * MS)
    assert not buf.covers(20 * MS, 95 * MS) and buf.covers(90 * MS, 100 * MS)
    # the last problem, in sample order: 95 ms after 100 ms
    assert got.problem == GyroProblem("out_of_order", 95 * MS, 100 * MS, (0.0, 0.0, 0.0))
    last = buf.intake(_samples(np.array([100, 160]) * MS, np.ones((2, 3))), 50 * MS)
    assert last.gaps == 1 and last.duplicate == 1
    assert last.problem == GyroProblem("gap", 160 * MS, 100 * MS, (1.0, 1.0, 1.0))
    assert len(buf) == 1
    nan = buf.intake(_samples(np.array([170]) * MS, np.array([[np.inf, 0.0, 0.0]])))
    assert nan.problem == GyroProblem("non_finite", 170 * MS, None, (np.inf, 0.0, 0.0))
    # no limit: any gap is bridged (add() is intake() without one)
    assert buf.intake(_samples(np.array([10_000]) * MS, np.zeros((1, 3)))).gaps == 0
    assert len(buf) == 2


def test_set_calibration_reads_the_held_samples_anew() -> None:
    buf = GyroBuffer()
    t = T_START + np.arange(0, 101) * MS
    buf.add(_samples(t, np.tile([0.0, 0.0, 0.5], (t.size, 1))))
    before = buf.mean_rate_camera(int(t[0]), int(t[-1]))
    np.testing.assert_allclose(before, [0.0, 0.0, 0.5], atol=1e-12)
    buf.set_calibration(Q_FORWARD, 10 * MS)
    assert buf.imu_time_offset_ns == 10 * MS and len(buf) == 101
    np.testing.assert_allclose(buf.camera_to_imu_rotation, R_CAM_TO_IMU, atol=1e-12)
    after = buf.mean_rate_camera(int(t[0]), int(t[-1]) - 10 * MS)
    np.testing.assert_allclose(after, R_CAM_TO_IMU.T @ [0.0, 0.0, 0.5], atol=1e-12)
    with pytest.raises(CalibrationError):
        buf.set_calibration((0.0, 0.0, 0.0, 2.0), 0)


def test_capacity_bounds_memory_and_keeps_newest() -> None:
    buf = GyroBuffer(capacity_s=0.5)
    rng = np.random.default_rng(0)
    stamps = np.arange(0, 3000) * MS  # 3 s at 1 kHz, added one message at a time
    rates = rng.normal(size=(3000, 3))
    for i in range(3000):
        buf.add(_samples(stamps[i : i + 1], rates[i : i + 1]))
    assert len(buf) == 501  # [2.499, 2.999] s
    np.testing.assert_array_equal(buf.stamps_ns, stamps[-501:])
    np.testing.assert_array_equal(buf.rates_imu, rates[-501:])
    assert buf._t.shape[0] < 4 * 501  # the storage does not grow with the stream
    with pytest.raises(TimeError):
        buf.relative_rotation(2000 * MS, 2600 * MS)
    batch = GyroBuffer(capacity_s=0.5)
    batch.add(_samples(stamps, rates))
    np.testing.assert_array_equal(
        batch.relative_rotation(2600 * MS, 2900 * MS), buf.relative_rotation(2600 * MS, 2900 * MS)
    )


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"camera_to_imu_rotation_xyzw": (0, 0, 0, 0)}, CalibrationError, "unit quaternion"),
        ({"camera_to_imu_rotation_xyzw": (0, 0, 1)}, CalibrationError, r"\[0\.0, 0\.0, 1\.0\]"),
        ({"camera_to_imu_rotation_xyzw": (0, 0, np.nan, 1)}, CalibrationError, "nan"),
        ({"imu_time_offset_ns": 0.5}, InvalidInputError, "0.5"),
        ({"capacity_s": 0.0}, InvalidInputError, "capacity_s.*0.0"),
    ],
)
def test_bad_construction(kwargs: dict, error: type, match: str) -> None:  # type: ignore[type-arg]
    with pytest.raises(error, match=match):
        GyroBuffer(**kwargs)


def test_bad_samples() -> None:
    buf = GyroBuffer()
    with pytest.raises(InvalidInputError, match="integer"):
        buf.add(GyroSamples(np.array([0.0, 1.0]), np.zeros((2, 3))))  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match=r"\(2, 3\), got \(2, 2\)"):
        buf.add(_samples(np.array([0, 1]), np.zeros((2, 2))))
    buf.add(_samples(np.array([0, 10]), np.zeros((2, 3))))
    with pytest.raises(InvalidInputError, match="bias_imu"):
        buf.relative_rotation(0, 10, bias_imu=(0.0, 0.0))


def test_relative_rotations_match_one_interval_each() -> None:
    # The batched form (the engine's fit window: several past frames to the current one)
    # splits the pieces at every start; the result must equal the independent integrations
    # and the ODE reference.
    rng = np.random.default_rng(11)
    stamps = T_START + np.cumsum(rng.integers(2 * MS, 4 * MS, size=80))  # jittered ~330 Hz
    rates_imu = rng.normal(scale=1.5, size=(80, 3))
    buf = GyroBuffer(Q_FORWARD, imu_time_offset_ns=3 * MS, capacity_s=5.0)
    buf.add(_samples(stamps, rates_imu))
    bias = np.array([0.01, -0.02, 0.03])
    t1 = int(stamps[70]) - 3 * MS - 1234
    starts = np.array([t1 - 33_333_333 * k - 17 * k for k in (1, 2, 3, 4)] + [t1], np.int64)
    batch = buf.relative_rotations(starts, t1, bias)
    assert batch.shape == (5, 3, 3)
    for t0, rot in zip(starts, batch, strict=True):
        one = buf.relative_rotation(int(t0), t1, bias)
        assert _angle(rot, one) < 1e-12
    np.testing.assert_array_equal(batch[-1], np.eye(3))
    rel = (stamps - 3 * MS - T_START) * 1e-9
    rates_cam = (rates_imu - bias) @ R_CAM_TO_IMU

    def rate(t: float) -> np.ndarray:
        return np.array([np.interp(t, rel, rates_cam[:, i]) for i in range(3)])

    ref = _ode_rotation(rate, (starts[3] - T_START) * 1e-9, (t1 - T_START) * 1e-9)
    assert _angle(batch[3], ref) < 1e-9
    assert buf.relative_rotations(np.zeros(0, np.int64), t1).shape == (0, 3, 3)
    with pytest.raises(InvalidInputError, match=r"after t1_ns"):
        buf.relative_rotations([t1 + 1], t1)
    with pytest.raises(TimeError, match="do not cover"):
        buf.relative_rotations([int(stamps[0]) - 3 * MS - 1, t1], t1)
