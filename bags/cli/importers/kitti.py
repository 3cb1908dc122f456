"""The KITTI odometry layout -> Dataset.

Read (``ROOT`` = one sequence folder, e.g. ``sequences/00``)::

    image_0/000000.png ...   left grey camera (``--colour``: image_2/, the left colour one)
    calib.txt                lines "P0: 12 numbers" (3x4 projection, row-major) ... P2
    times.txt                one stamp per image, seconds from the sequence start
    poses.txt                (optional, or --poses FILE) 12 numbers per line: the 3x4 pose
                             of camera 0 in the world (= camera 0 at image 0), per image
    imu.csv                  (optional, or --imu FILE) 7 columns: time [s, times.txt clock],
                             w_x w_y w_z [rad/s], a_x a_y a_z [m/s^2]; IMU axes given by
                             --camera-to-imu-rotation-xyzw (default: those of camera 0)

Stamps are ``round(times.txt * 1e9)`` ns (the sequence clock starts at 0). The images are
rectified: the camera model is K = P[:, :3] without distortion. For image_2 the camera
sits at ``-K^-1 P2[:, 3]`` in camera 0's frame (rectified cameras share camera 0's axes).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bags.cli.importers.common import (
    Dataset,
    DatasetError,
    PoseTrack,
    _lines,
    numbers,
    read_stamped_csv,
    require_file,
)
from owl_core.camera import CameraModel
from owl_core.errors import CalibrationError
from owl_core.geometry import quat_xyzw_to_matrix


def is_kitti(root: Path) -> bool:
    """Whether ``root`` looks like a KITTI odometry sequence folder."""
    return (root / "times.txt").is_file() or (root / "calib.txt").is_file()


def read_calib(path: Path, key: str) -> np.ndarray:
    """The (3, 4) projection matrix ``key`` ("P0" or "P2") of calib.txt."""
    for number, text in _lines(path):
        name, _, rest = text.partition(":")
        if name.strip() != key:
            continue
        parts = rest.split()
        if len(parts) != 12:
            raise DatasetError(
                f"{path} line {number}: {key} has {len(parts)} numbers, expected 12"
            )
        return numbers([float(_number(p, path, number)) for p in parts], 12, path, key).reshape(
            3, 4
        )
    raise DatasetError(f"{path}: no {key} line")


def _number(text: str, path: Path, number: int) -> float:
    try:
        return float(text)
    except ValueError:
        raise DatasetError(f"{path} line {number}: {text!r} is not a number") from None


def read_times(path: Path) -> np.ndarray:
    """(F,) int64 ns stamps of times.txt (one number per line, strictly increasing)."""
    stamps, _ = read_stamped_csv(path, 1, seconds=True)
    return stamps


def read_poses(path: Path, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(R_wc (F, 3, 3), c_w (F, 3)) from a KITTI poses file with ``count`` lines."""
    rows: list[list[float]] = []
    for number, text in _lines(path):
        parts = text.split()
        if len(parts) != 12:
            raise DatasetError(f"{path} line {number}: {len(parts)} columns, expected 12")
        rows.append([_number(p, path, number) for p in parts])
    if len(rows) != count:
        raise DatasetError(f"{path}: {len(rows)} poses for {count} images in times.txt")
    m = np.asarray(rows, dtype=np.float64).reshape(-1, 3, 4)
    if not np.all(np.isfinite(m)):
        raise DatasetError(f"{path}: non-finite pose values")
    u, _, vt = np.linalg.svd(m[:, :, :3])
    return u @ vt, m[:, :, 3].copy()


def read_kitti(
    root: Path,
    *,
    colour: bool = False,
    poses: Path | None = None,
    imu: Path | None = None,
    camera_to_imu_xyzw: tuple[float, float, float, float] | None = None,
    ground_truth: bool = True,
) -> Dataset:
    """Read a KITTI odometry sequence folder (see the module docstring).

    Raises:
        DatasetError: a missing file, a wrong column count, a bad number, stamps out of
            order, or as many poses as images not given (the file named).
    """
    folder = root / ("image_2" if colour else "image_0")
    if not folder.is_dir():
        raise DatasetError(f"{folder}: image folder is missing")
    p = read_calib(root / "calib.txt", "P2" if colour else "P0")
    stamps = read_times(root / "times.txt")
    files = tuple(folder / f"{i:06d}.png" for i in range(stamps.size))
    k = p[:, :3]
    if abs(k[2, 2] - 1) > 1e-9 or k[1, 0] or k[2, 0] or k[2, 1]:
        raise DatasetError(f"{root / 'calib.txt'}: {'P2' if colour else 'P0'} is not K [I | t]")
    first = files[0]
    import cv2

    img = cv2.imread(str(require_file(first)), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{first}: unreadable image (not a PNG or damaged)")
    h, w = img.shape[:2]
    try:
        camera = CameraModel(w, h, k, np.zeros(0), "none")
    except CalibrationError as err:
        raise DatasetError(f"{root / 'calib.txt'}: {err}") from None
    t_0c = -np.linalg.solve(k, p[:, 3])  # camera centre in camera 0's frame
    q = np.asarray(camera_to_imu_xyzw or (0.0, 0.0, 0.0, 1.0), dtype=np.float64)
    r_ic = quat_xyzw_to_matrix(q / np.linalg.norm(q))
    imu_path = (
        imu if imu is not None else (root / "imu.csv" if (root / "imu.csv").exists() else None)
    )
    if imu_path is not None:
        imu_t, imu_v = read_stamped_csv(imu_path, 7, seconds=True)
    else:
        imu_t, imu_v = np.zeros(0, dtype=np.int64), np.zeros((0, 6))
    pose_path = poses if poses is not None else (root / "poses.txt")
    track = None
    if ground_truth and (poses is not None or pose_path.exists()):
        r_w0, c_w0 = read_poses(require_file(pose_path), stamps.size)
        track = PoseTrack(stamps, r_w0, c_w0, None, None, pose_path)
    return Dataset(
        root=root,
        layout="kitti",
        camera=camera,
        image_stamps_ns=stamps,
        image_files=files,
        imu_stamps_ns=imu_t,
        gyro=imu_v[:, 0:3].copy(),
        accel=imu_v[:, 3:6].copy(),
        R_ic=r_ic,
        t_ic=r_ic @ t_0c,
        track=track,
        R_xc=np.eye(3),
        t_xc=t_0c,
        extrinsic_source="--camera-to-imu-rotation-xyzw" if camera_to_imu_xyzw else "identity",
    )
