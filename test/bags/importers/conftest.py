"""Dataset folders written from rendered scenarios (ASL and KITTI layouts), with their truth.

The renderer's camera sits at the body (IMU) origin; the ASL folder moves the camera by a
lever arm ``LEVER`` in ``T_BS`` and writes the body poses that put the camera exactly where
the renderer had it, so the imported twist must equal the renderer's.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from bags.sim import scenarios
from bags.sim.scenarios import SimOptions, Simulation
from bags.sim.sensors import ImuOptions

REPO = Path(__file__).resolve().parents[3]
SHARED_DATA = REPO.parent / "shared" / "data"
#: camera origin in the body frame of the ASL folder, m
LEVER = np.array([0.05, -0.02, 0.01])
BIAS = (0.003, -0.002, 0.004)
#: ground-truth sampling of the ASL folder: 200 Hz, first sample 1.3 ms after the first image
GT_RATE_HZ = 200.0
GT_OFFSET_S = 0.0013


@dataclass(frozen=True)
class Folder:
    """A written dataset folder and the simulation it came from."""

    root: Path
    sim: Simulation
    stamps_ns: np.ndarray
    gt_spacing_s: float
    bias: tuple[float, float, float] = (0.0, 0.0, 0.0)


def shared_recording(name: str) -> Path:
    """The shared recording ``name``; missing: fail in CI (CI=true), skip elsewhere."""
    path = SHARED_DATA / name
    if not (path / "mav0").is_dir():
        msg = f"shared recording {name} not found beside the repository ({path})"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    return path


def _sim(rate: float, seconds: float) -> Simulation:
    opts = SimOptions(
        seconds=seconds,
        rate_hz=rate,
        width=320,
        height=240,
        distortion=(-0.25, 0.07, 0.0005, -0.0003, 0.0),
        imu=ImuOptions(gyro_bias=BIAS),
    )
    return scenarios.get("street").simulate(opts)


def _yaml_matrix(r: np.ndarray, t: np.ndarray) -> str:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return "  cols: 4\n  rows: 4\n  data: [" + ", ".join(f"{v:.17g}" for v in m.ravel()) + "]\n"


def write_asl(root: Path, rate: float = 20.0, seconds: float = 1.0) -> Folder:
    """An ASL (EuRoC) folder of the street scenario with state_groundtruth_estimate0."""
    sim = _sim(rate, seconds)
    cam = root / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    stamps = sim.frame_stamps_ns
    lines = ["#timestamp [ns],filename"]
    for f in sim.frames():
        cv2.imwrite(str(cam / "data" / f"{f.stamp_ns}.png"), f.image)
        lines.append(f"{f.stamp_ns},{f.stamp_ns}.png")
    (cam / "data.csv").write_text("\n".join(lines) + "\n")
    k = sim.camera.K
    d = sim.camera.D
    (cam / "sensor.yaml").write_text(
        "%YAML:1.0\nsensor_type: camera\nT_BS:\n"
        + _yaml_matrix(sim.R_bc, LEVER)
        + f"rate_hz: {rate}\nresolution: [320, 240]\ncamera_model: pinhole\n"
        "intrinsics: ["
        + ", ".join(repr(float(v)) for v in (k[0, 0], k[1, 1], k[0, 2], k[1, 2]))
        + "]\n"
        "distortion_model: radial-tangential\n"
        "distortion_coefficients: [" + ", ".join(repr(float(v)) for v in d[:4]) + "]\n"
    )
    imu = root / "mav0" / "imu0"
    imu.mkdir(parents=True)
    rows = ["#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z"]
    for ns, w, a in zip(
        sim.imu.stamp_ns, sim.imu.angular_velocity, sim.imu.linear_acceleration, strict=True
    ):
        rows.append(f"{ns}," + ",".join(f"{v:.17g}" for v in (*w, *a)))
    (imu / "data.csv").write_text("\n".join(rows) + "\n")
    (imu / "sensor.yaml").write_text(
        "sensor_type: imu\nT_BS:\n" + _yaml_matrix(np.eye(3), np.zeros(3))
    )
    gt = root / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir(parents=True)
    t = np.arange(-0.05 + GT_OFFSET_S, seconds + 0.05, 1.0 / GT_RATE_HZ)
    st = sim.trajectory.state(t)
    r_wb = st.R_wb
    lever_w = np.einsum("kij,j->ki", r_wb, LEVER)
    p_wb = st.position - lever_w  # the camera (at p_wb + R_wb LEVER) is where it was rendered
    w_w = np.einsum("kij,kj->ki", r_wb, st.omega_b)
    v_wb = st.velocity - np.cross(w_w, lever_w)
    from owl_core.geometry import matrix_to_quat_xyzw

    q = matrix_to_quat_xyzw(r_wb)
    rows = ["#timestamp,p_RS_R_x,p_RS_R_y,p_RS_R_z,q_RS_w,q_RS_x,q_RS_y,q_RS_z,v_x,v_y,v_z,"
            "b_w_x,b_w_y,b_w_z,b_a_x,b_a_y,b_a_z"]  # fmt: skip
    start = int(sim.options.start_ns)
    for i, ti in enumerate(t):
        vals = (*p_wb[i], q[i, 3], q[i, 0], q[i, 1], q[i, 2], *v_wb[i], *BIAS, 0.0, 0.0, 0.0)
        rows.append(f"{start + round(ti * 1e9)}," + ",".join(f"{v:.17g}" for v in vals))
    (gt / "data.csv").write_text("\n".join(rows) + "\n")
    return Folder(root, sim, stamps, 1.0 / GT_RATE_HZ, BIAS)


def write_kitti(root: Path, rate: float = 10.0, seconds: float = 1.5) -> Folder:
    """A KITTI odometry folder (image_0, calib.txt, times.txt, poses.txt, imu.csv)."""
    sim = scenarios.get("street").simulate(
        SimOptions(seconds=seconds, rate_hz=rate, width=320, height=240, imu=ImuOptions())
    )
    img = root / "image_0"
    img.mkdir(parents=True)
    stamps = sim.frame_stamps_ns
    t0 = int(stamps[0])
    times, poses = [], []
    r0, c0 = sim.pose(0.0)
    for i, f in enumerate(sim.frames()):
        cv2.imwrite(str(img / f"{i:06d}.png"), f.image)
        times.append(f"{(f.stamp_ns - t0) * 1e-9:.6e}")
        r = r0.T @ f.R_wc  # world = camera 0 at image 0, as KITTI's poses
        c = r0.T @ (f.c_w - c0)
        poses.append(" ".join(f"{v:.12e}" for v in np.c_[r, c].ravel()))
    (root / "times.txt").write_text("\n".join(times) + "\n")
    (root / "poses.txt").write_text("\n".join(poses) + "\n")
    p = np.c_[sim.camera.K, np.zeros(3)]
    p1 = p.copy()
    p1[0, 3] = -0.54 * sim.camera.K[0, 0]
    calib = [
        f"P{i}: " + " ".join(f"{v:.12e}" for v in m.ravel()) for i, m in enumerate((p, p1, p, p1))
    ]
    (root / "calib.txt").write_text("\n".join(calib) + "\n")
    rows = ["# t [s], w_x, w_y, w_z, a_x, a_y, a_z"]
    for ns, w, a in zip(
        sim.imu.stamp_ns, sim.imu.angular_velocity, sim.imu.linear_acceleration, strict=True
    ):
        rows.append(f"{(int(ns) - t0) * 1e-9:.9f}," + ",".join(f"{v:.17g}" for v in (*w, *a)))
    (root / "imu.csv").write_text("\n".join(rows) + "\n")
    return Folder(root, sim, stamps - t0, 1.0 / rate)


def twist_error_bound(sim: Simulation, h: float, interpolated: bool) -> tuple[float, float]:
    """(linear m/s, angular rad/s) bound of the importer's differentiation error.

    3-point derivative: h^2/6 |x'''| (x = position; for the rotation |w''| plus the
    commutator |w x w'|/12... taken as h^2/12 |w||w'|); linear interpolation between
    samples adds h^2/8 of the second derivative of the interpolated velocity. The
    derivatives are taken numerically from the renderer's exact twist on a 1 ms grid.
    """
    t = np.arange(-0.05, sim.options.seconds + 0.05, 1e-3)
    st = sim.trajectory.state(t)
    w = st.omega_b
    dt = 1e-3
    w1 = np.gradient(w, dt, axis=0)
    w2 = np.gradient(w1, dt, axis=0)
    a1 = np.gradient(st.acceleration, dt, axis=0)  # jerk
    v2 = np.gradient(np.gradient(st.velocity, dt, axis=0), dt, axis=0)
    wmax, w1max, w2max = (float(np.max(np.linalg.norm(x, axis=1))) for x in (w, w1, w2))
    jerk = float(np.max(np.linalg.norm(a1, axis=1)))
    speed = float(np.max(np.linalg.norm(st.velocity, axis=1)))
    ang = h**2 / 6 * w2max + h**2 / 12 * wmax * w1max
    lin = h**2 / 6 * jerk
    if interpolated:
        ang += h**2 / 8 * w2max
        # slerp of the rotation that carries v into the camera frame: h^2/8 |w'| |v|
        lin += h**2 / 8 * (float(np.max(np.linalg.norm(v2, axis=1))) + w1max * speed)
    return lin + 1e-9, ang + 1e-9


@pytest.fixture(scope="module")
def asl_folder(tmp_path_factory: pytest.TempPathFactory) -> Folder:
    """The rendered ASL folder (module-scoped: read-only for the tests)."""
    return write_asl(tmp_path_factory.mktemp("asl") / "street_asl")


@pytest.fixture(scope="module")
def kitti_folder(tmp_path_factory: pytest.TempPathFactory) -> Folder:
    """The rendered KITTI folder (module-scoped: read-only for the tests)."""
    return write_kitti(tmp_path_factory.mktemp("kitti") / "00")


@pytest.fixture(scope="session")
def asl_writer() -> Callable[..., Folder]:
    """write_asl as a fixture (a fresh folder to break)."""
    return write_asl


@pytest.fixture(scope="session")
def kitti_writer() -> Callable[..., Folder]:
    """write_kitti as a fixture (a fresh folder to break)."""
    return write_kitti


@pytest.fixture(scope="session")
def bound() -> Callable[[Simulation, float, bool], tuple[float, float]]:
    """twist_error_bound as a fixture."""
    return twist_error_bound


@pytest.fixture(scope="session")
def shared() -> Callable[[str], Path]:
    """shared_recording as a fixture."""
    return shared_recording
