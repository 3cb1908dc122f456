"""The ASL folder layout (EuRoC MAV, TUM-VI, anything recorded that way) -> Dataset.

Read (``ROOT`` is the folder holding ``mav0/``, or ``mav0`` itself)::

    mav0/cam0/data.csv           #timestamp [ns],filename
    mav0/cam0/data/<filename>    png or jpg, 8 or 16 bit, grey or colour
    mav0/cam0/sensor.yaml        T_BS, resolution, camera_model pinhole, intrinsics
                                 [fu, fv, cu, cv], distortion_model radial-tangential
                                 (-> plumb_bob k1 k2 p1 p2 0) or equidistant (-> equidistant)
    mav0/imu0/data.csv           timestamp [ns], w_x w_y w_z [rad/s], a_x a_y a_z [m/s^2]
    mav0/imu0/sensor.yaml        T_BS
    mav0/state_groundtruth_estimate0/data.csv   (EuRoC, optional) 17 columns: timestamp,
                                 p_RS_R xyz, q_RS wxyz, v_RS_R xyz, b_w_RS_S xyz, b_a_RS_S xyz
    mav0/mocap0/data.csv         (TUM-VI, optional) 8 columns: timestamp, p xyz, q wxyz

``T_BS`` is the sensor-to-body transform of each sensor; the camera-to-IMU transform is
``T_BS(imu0)^-1 T_BS(cam0)``. The ground-truth poses are those of the ground-truth sensor
(its own ``sensor.yaml`` ``T_BS``, identity when absent: EuRoC and TUM-VI give the IMU's).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bags.cli.importers.common import (
    Dataset,
    DatasetError,
    PoseTrack,
    _lines,
    _split,
    check_increasing,
    numbers,
    quat_wxyz_to_matrix,
    read_stamped_csv,
    read_yaml,
    require_file,
    transform,
)
from owl_core.camera import CameraModel
from owl_core.errors import CalibrationError

GROUND_TRUTH = (
    ("state_groundtruth_estimate0", 17),
    ("mocap0", 8),
)
DISTORTION = {
    "radial-tangential": "plumb_bob",
    "radtan": "plumb_bob",
    "plumb_bob": "plumb_bob",
    "equidistant": "equidistant",
    "equi": "equidistant",
    "none": "none",
}


def find_mav0(root: Path) -> Path:
    """The ``mav0`` folder of an ASL dataset at ``root`` (or ``root`` itself)."""
    for cand in (root / "mav0", root):
        if (cand / "cam0").is_dir():
            return cand
    raise DatasetError(f"{root}: not an ASL dataset folder (no mav0/cam0 directory)")


def is_asl(root: Path) -> bool:
    """Whether ``root`` looks like an ASL folder."""
    return (root / "mav0" / "cam0").is_dir() or (root / "cam0").is_dir()


def read_camera(sensor_yaml: Path) -> tuple[CameraModel, np.ndarray, np.ndarray]:
    """(camera model, R_bc, t_bc) from cam0/sensor.yaml."""
    y = read_yaml(sensor_yaml)
    for key in ("T_BS", "resolution", "intrinsics"):
        if key not in y:
            raise DatasetError(f"{sensor_yaml}: no {key}")
    model = str(y.get("camera_model", "pinhole"))
    if model != "pinhole":
        raise DatasetError(f"{sensor_yaml}: camera_model {model!r} is not supported (pinhole)")
    dist_name = str(y.get("distortion_model", "none"))
    if dist_name not in DISTORTION:
        raise DatasetError(
            f"{sensor_yaml}: distortion_model {dist_name!r} is not supported "
            f"(radial-tangential or equidistant)"
        )
    ros_model = DISTORTION[dist_name]
    w, h = (int(v) for v in numbers(y["resolution"], 2, sensor_yaml, "resolution"))
    fu, fv, cu, cv = numbers(y["intrinsics"], 4, sensor_yaml, "intrinsics")
    coeffs = y.get("distortion_coefficients", [])
    d = (
        np.zeros(0)
        if ros_model == "none"
        else numbers(coeffs, 4, sensor_yaml, "distortion_coefficients")
    )
    if ros_model == "plumb_bob":
        d = np.r_[d, 0.0]
    if ros_model == "plumb_bob" and not np.any(d):
        ros_model, d = "none", np.zeros(0)
    k = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    try:
        camera = CameraModel(w, h, k, d, ros_model)
    except CalibrationError as err:
        raise DatasetError(f"{sensor_yaml}: {err}") from None
    r, t = transform(y["T_BS"], sensor_yaml)
    return camera, r, t


def read_images(cam: Path) -> tuple[np.ndarray, tuple[Path, ...]]:
    """(stamps, files) from cam0/data.csv (2 columns, stamps strictly increasing)."""
    csv = require_file(cam / "data.csv")
    stamps: list[int] = []
    files: list[Path] = []
    lines: list[int] = []
    for number, text in _lines(csv):
        parts = _split(text)
        if len(parts) != 2:
            raise DatasetError(f"{csv} line {number}: {len(parts)} columns, expected 2")
        try:
            stamps.append(int(parts[0]))
        except ValueError:
            raise DatasetError(
                f"{csv} line {number}: stamp {parts[0]!r} is not an integer"
            ) from None
        files.append(cam / "data" / parts[1])
        lines.append(number)
    if len(stamps) < 2:
        raise DatasetError(f"{csv}: {len(stamps)} images listed (need at least 2)")
    out = np.asarray(stamps, dtype=np.int64)
    check_increasing(out, csv, lines)
    return out, tuple(files)


def read_ground_truth(mav0: Path) -> PoseTrack | None:
    """The EuRoC state estimate or the TUM-VI mocap poses (None when neither exists)."""
    for name, columns in GROUND_TRUTH:
        folder = mav0 / name
        csv = folder / "data.csv"
        if not csv.exists():
            continue
        stamps, v = read_stamped_csv(csv, columns)
        if stamps.size < 3:
            raise DatasetError(f"{csv}: {stamps.size} poses (need at least 3)")
        r_wg = quat_wxyz_to_matrix(v[:, 3:7])
        p_wg = v[:, 0:3]
        r_bg, t_bg = np.eye(3), np.zeros(3)
        if (folder / "sensor.yaml").exists():
            y = read_yaml(folder / "sensor.yaml")
            if "T_BS" in y:
                r_bg, t_bg = transform(y["T_BS"], folder / "sensor.yaml")
        # poses of the body frame: T_wb = T_wg T_bg^-1
        r_wb = r_wg @ r_bg.T
        p_wb = p_wg - np.einsum("kij,j->ki", r_wb, t_bg)
        vel = v[:, 7:10] if columns == 17 else None
        if vel is not None and np.any(t_bg):
            raise DatasetError(f"{folder / 'sensor.yaml'}: a velocity with a lever arm T_BS")
        bias = v[:, 10:13] if columns == 17 else None
        return PoseTrack(stamps, r_wb, p_wb, vel, bias, csv)
    return None


def read_asl(root: Path, ground_truth: bool = True) -> Dataset:
    """Read an ASL dataset folder (see the module docstring).

    Raises:
        DatasetError: a missing file, a wrong column count, a bad number or stamps out of
            order, naming the file (and line).
    """
    mav0 = find_mav0(root)
    cam = mav0 / "cam0"
    camera, r_bc, t_bc = read_camera(cam / "sensor.yaml")
    stamps, files = read_images(cam)
    imu_dir = mav0 / "imu0"
    imu_t, imu_v = read_stamped_csv(imu_dir / "data.csv", 7)
    r_bi, t_bi = np.eye(3), np.zeros(3)
    y = read_yaml(imu_dir / "sensor.yaml")
    if "T_BS" in y:
        r_bi, t_bi = transform(y["T_BS"], imu_dir / "sensor.yaml")
    r_ic = r_bi.T @ r_bc
    t_ic = r_bi.T @ (t_bc - t_bi)
    track = read_ground_truth(mav0) if ground_truth else None
    # the track is of the body frame b: the camera in b is T_BS(cam0)
    return Dataset(
        root=root,
        layout="asl",
        camera=camera,
        image_stamps_ns=stamps,
        image_files=files,
        imu_stamps_ns=imu_t,
        gyro=imu_v[:, 0:3].copy(),
        accel=imu_v[:, 3:6].copy(),
        R_ic=r_ic,
        t_ic=t_ic,
        track=track,
        R_xc=r_bc,
        t_xc=t_bc,
        extrinsic_source="T_BS of cam0/sensor.yaml and imu0/sensor.yaml",
    )
