"""What every dataset importer shares: the Dataset record, strict file readers, the
ground-truth twist from poses, and the bag writer.

Ground truth from poses (:func:`camera_twist`)
----------------------------------------------
A :class:`PoseTrack` holds K poses ``T_wx`` (frame ``x`` of the ground-truth sensor in a
world frame) at stamps ``t_k``; ``T_xc`` places the camera in ``x``. The camera pose is
``R_wc = R_wx R_xc``, ``c_w = p_wx + R_wx t_xc``. At every interior sample (``0 < k <
K-1``, both neighbours closer than ``max_gap_s``):

- angular velocity (camera frame, rad/s): the 3-point derivative in the tangent space of
  ``R_wc(t_k)``, ``w_k = (h0^2 phi_+ - h1^2 phi_-) / (h0 h1 (h0 + h1))`` with ``phi_+- =
  log(R_k^T R_{k+-1})``, ``h0 = t_k - t_{k-1}``, ``h1 = t_{k+1} - t_k`` (the central
  difference for even spacing; exact for a quadratic rotation vector);
- linear velocity (world frame, m/s): the same 3-point derivative of ``c_w``; when the
  dataset gives the velocity of ``x`` (EuRoC ``v_RS_R``) that is used instead, plus the
  lever arm ``(R_wc w) x (R_wx t_xc)``.

Error of the 3-point derivative: ``h^2/6 |x'''|`` for evenly spaced samples (``x`` the
position for the velocity, the rotation for the angular velocity, where ``|w''|`` and,
for a rotation, the commutator ``|w x w'|/12`` enter). At an image stamp between samples
k and k+1 the velocities are interpolated linearly (adding up to ``h^2/8 |v''|``) and the
rotation by slerp; the camera-frame linear velocity is ``R_wc(t)^T v_w(t)``. Image stamps
outside the interior samples, or in a gap longer than ``max_gap_s``, get no twist.

Time alignment: ground-truth stamps are taken to be on the camera's clock, as EuRoC,
TUM-VI (both aligned by the dataset authors) and KITTI (pose k belongs to image k) give
them; no offset is estimated.

The gyro bias (EuRoC ``b_w_RS_S``, IMU frame, rad/s) is interpolated linearly to the
image stamps and written on ``/ground_truth/gyro_bias`` (geometry_msgs/Vector3Stamped,
frame ``imu_link``).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import cv2
import numpy as np
import numpy.typing as npt

from bags import layout
from bags.errors import BagError
from bags.io import BagWriter, typestore
from bags.layout import CAMERA_FRAME, IMU_FRAME
from owl_core.camera import CameraModel
from owl_core.geometry import matrix_to_quat_xyzw, so3_exp, so3_log

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

PROG = "owl_import"

#: Topics, types and QoS names: the standard layout's inputs and the truth a dataset has.
TOPICS = layout.subset("image", "info", "imu", "tf", "twist", "bias")


class DatasetError(BagError, ValueError):
    """A dataset folder that cannot be imported (one line naming the file and the problem)."""


# ------------------------------------------------------------------------ records


@dataclass(frozen=True)
class PoseTrack:
    """Ground-truth poses of a frame ``x`` in a world frame. K samples.

    Attributes:
        stamps_ns: (K,) int64 strictly increasing stamps, camera clock.
        R_wx: (K, 3, 3) rotations x -> world.
        p_wx: (K, 3) positions of x's origin, world, m.
        v_wx: (K, 3) velocity of x's origin, world, m/s, or None (differentiate p_wx).
        gyro_bias: (K, 3) gyro bias, IMU frame, rad/s, or None.
        source: the file the poses came from.
    """

    stamps_ns: I64
    R_wx: F64
    p_wx: F64
    v_wx: F64 | None
    gyro_bias: F64 | None
    source: Path


@dataclass(frozen=True)
class Dataset:
    """A dataset folder as read (images are only listed, decoded one at a time later).

    Attributes:
        root: the folder given. layout: "asl" or "kitti".
        camera: the camera model at the stored image size.
        image_stamps_ns: (F,) int64 strictly increasing image stamps.
        image_files: F image paths.
        imu_stamps_ns: (M,) int64 IMU stamps (M = 0: no IMU).
        gyro: (M, 3) rad/s, IMU frame. accel: (M, 3) m/s^2, IMU frame.
        R_ic: (3, 3) rotation camera -> IMU frame (camera_to_imu_rotation_xyzw).
        t_ic: (3,) camera origin in the IMU frame, m.
        track: ground-truth poses, or None.
        R_xc, t_xc: the camera in the track's frame x (rotation, translation in m).
        extrinsic_source: where R_ic came from (for the user).
    """

    root: Path
    layout: str
    camera: CameraModel
    image_stamps_ns: I64
    image_files: tuple[Path, ...]
    imu_stamps_ns: I64
    gyro: F64
    accel: F64
    R_ic: F64
    t_ic: F64
    track: PoseTrack | None = None
    R_xc: F64 = field(default_factory=lambda: np.eye(3))
    t_xc: F64 = field(default_factory=lambda: np.zeros(3))
    extrinsic_source: str = ""


@dataclass(frozen=True)
class ImportOptions:
    """What to import.

    Attributes:
        start_s: skip images before first image + start_s, s (>= 0).
        seconds: keep images up to start + seconds, s (None = to the end).
        every: keep every Nth image (>= 1).
        scale: image scale factor (0 < scale <= 1 typical; intrinsics adjusted).
        imu_margin_s: IMU samples kept before the first and after the last image, s.
        overwrite: replace an existing output bag.
    """

    start_s: float = 0.0
    seconds: float | None = None
    every: int = 1
    scale: float = 1.0
    imu_margin_s: float = 0.5
    overwrite: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.start_s) and self.start_s >= 0):
            raise DatasetError(f"--start must be >= 0 seconds, got {self.start_s!r}")
        if self.seconds is not None and not (math.isfinite(self.seconds) and self.seconds > 0):
            raise DatasetError(f"--seconds must be > 0, got {self.seconds!r}")
        if isinstance(self.every, bool) or not isinstance(self.every, int) or self.every < 1:
            raise DatasetError(f"--every must be an integer >= 1, got {self.every!r}")
        if not (math.isfinite(self.scale) and 0 < self.scale <= 4):
            raise DatasetError(f"--scale must be in (0, 4], got {self.scale!r}")


@dataclass(frozen=True)
class ImportSummary:
    """What :func:`write_dataset` wrote."""

    out_path: Path
    frames: int
    imu_samples: int
    twist_frames: int
    bias_frames: int
    camera: CameraModel
    camera_to_imu_rotation_xyzw: tuple[float, float, float, float]
    elapsed_s: float


# ------------------------------------------------------------------------ file readers


def require_file(path: Path) -> Path:
    """``path`` if it is a file, else DatasetError naming it."""
    if not path.is_file():
        what = "is a directory" if path.is_dir() else "is missing"
        raise DatasetError(f"{path}: {what} (expected a file)")
    return path


def _lines(path: Path) -> Iterator[tuple[int, str]]:
    """(line number, stripped text) of the non-empty, non-comment lines."""
    try:
        with require_file(path).open("r", encoding="utf-8", errors="strict") as f:
            for number, line in enumerate(f, start=1):
                text = line.strip()
                if text and not text.startswith("#"):
                    yield number, text
    except (OSError, UnicodeDecodeError) as err:
        raise DatasetError(f"{path}: cannot read ({' '.join(str(err).split())})") from None


def _split(text: str) -> list[str]:
    sep = "," if "," in text else None
    return [p.strip() for p in text.split(sep)]


def check_increasing(stamps: I64, path: Path, lines: Sequence[int]) -> None:
    """DatasetError at the first stamp that is not after its predecessor."""
    if stamps.size < 2:
        return
    bad = np.flatnonzero(np.diff(stamps) <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise DatasetError(
            f"{path} line {lines[k]}: stamp {int(stamps[k])} is not after the previous one "
            f"({int(stamps[k - 1])}): stamps out of order"
        )


def read_stamped_csv(path: Path, columns: int, seconds: bool = False) -> tuple[I64, F64]:
    """A CSV of ``stamp, v1, ..., v{columns-1}`` (``#`` comments and blank lines skipped).

    Args:
        path: the file.
        columns: exact number of columns, stamp included.
        seconds: the stamp is a decimal number of seconds (else integer nanoseconds).

    Returns:
        (N,) int64 stamps (ns, strictly increasing) and (N, columns - 1) float64 values.

    Raises:
        DatasetError: missing file, a line with another column count, a value that is not
            a number, or stamps out of order (file and line named).
    """
    stamps: list[int] = []
    values: list[list[float]] = []
    lines: list[int] = []
    for number, text in _lines(path):
        parts = _split(text)
        if len(parts) != columns:
            raise DatasetError(f"{path} line {number}: {len(parts)} columns, expected {columns}")
        try:
            stamp = round(float(parts[0]) * 1e9) if seconds else int(parts[0])
            row = [float(p) for p in parts[1:]]
        except ValueError:
            raise DatasetError(f"{path} line {number}: not a number in {text[:80]!r}") from None
        if not all(math.isfinite(v) for v in row):
            raise DatasetError(f"{path} line {number}: non-finite value in {text[:80]!r}")
        stamps.append(stamp)
        values.append(row)
        lines.append(number)
    if not stamps:
        raise DatasetError(f"{path}: no data lines")
    out_t = np.asarray(stamps, dtype=np.int64)
    check_increasing(out_t, path, lines)
    return out_t, np.asarray(values, dtype=np.float64).reshape(len(stamps), columns - 1)


def read_yaml(path: Path) -> dict[str, Any]:
    """A sensor.yaml as a dict (OpenCV's ``%YAML:1.0`` first line accepted)."""
    import yaml

    text = "\n".join(t for t in _all_text(path).splitlines() if not t.startswith("%YAML"))
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise DatasetError(f"{path}: not valid YAML ({' '.join(str(err).split())})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a YAML mapping")
    return data


def _all_text(path: Path) -> str:
    try:
        return require_file(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise DatasetError(f"{path}: cannot read ({' '.join(str(err).split())})") from None


def numbers(value: Any, count: int, path: Path, key: str) -> F64:
    """``value`` as ``count`` finite floats, else DatasetError naming file and key."""
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: {key} is not a list of numbers: {value!r}") from None
    if arr.size != count or not np.all(np.isfinite(arr)):
        raise DatasetError(f"{path}: {key} needs {count} finite numbers, got {arr.size}")
    return arr


def transform(value: Any, path: Path, key: str = "T_BS") -> tuple[F64, F64]:
    """(R (3, 3), t (3,)) of a 4x4 ``{rows, cols, data}`` or nested-list transform."""
    data = value.get("data") if isinstance(value, dict) else value
    m = numbers(data, 16, path, key).reshape(4, 4)
    r = m[:3, :3]
    if not np.allclose(m[3], [0, 0, 0, 1]) or abs(np.linalg.det(r) - 1) > 1e-3:
        raise DatasetError(
            f"{path}: {key} is not a rigid transform (rotation det {np.linalg.det(r):.4f})"
        )
    u, _, vt = np.linalg.svd(r)  # re-orthonormalise (files give about 9 digits)
    return u @ vt, m[:3, 3].copy()


def quat_wxyz_to_matrix(q: F64) -> F64:
    """(K, 4) Hamilton quaternions w, x, y, z (any norm) -> (K, 3, 3) rotations."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    out = np.empty((q.shape[0], 3, 3))
    out[:, 0] = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], 1)
    out[:, 1] = np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], 1)
    out[:, 2] = np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1)
    return out


# ------------------------------------------------------------------------ ground truth


def _three_point(f_minus: F64, f0: F64, f_plus: F64, h0: F64, h1: F64) -> F64:
    """Derivative at the middle sample of unevenly spaced samples (exact for quadratics)."""
    h0 = h0[:, None]
    h1 = h1[:, None]
    return (h0**2 * f_plus - h1**2 * f_minus + (h1**2 - h0**2) * f0) / (h0 * h1 * (h0 + h1))


def camera_twist(
    track: PoseTrack,
    R_xc: F64,
    t_xc: F64,
    stamps_ns: I64,
    max_gap_s: float = 0.25,
) -> tuple[npt.NDArray[np.bool_], F64, F64]:
    """Camera-frame linear and angular velocity at image stamps (see the module docstring).

    Args:
        track: K >= 3 ground-truth poses of frame x.
        R_xc: (3, 3) camera -> x rotation. t_xc: (3,) camera origin in x, m.
        stamps_ns: (F,) image stamps, ns.
        max_gap_s: no twist across ground-truth gaps longer than this, s.

    Returns:
        (F,) bool valid, (F, 3) linear velocity m/s and (F, 3) angular velocity rad/s,
        both in the camera optical frame (NaN where not valid).
    """
    t = (track.stamps_ns - track.stamps_ns[0]) * 1e-9
    k_count = t.size
    f = np.asarray(stamps_ns).size
    nan = np.full((f, 3), np.nan)
    if k_count < 3:
        return np.zeros(f, dtype=bool), nan, nan.copy()
    r_wc = track.R_wx @ R_xc
    c_w = track.p_wx + track.R_wx @ t_xc
    h0 = t[1:-1] - t[:-2]
    h1 = t[2:] - t[1:-1]
    r_mid = r_wc[1:-1]
    phi_m = so3_log(np.swapaxes(r_mid, 1, 2) @ r_wc[:-2])
    phi_p = so3_log(np.swapaxes(r_mid, 1, 2) @ r_wc[2:])
    w_c = np.full((k_count, 3), np.nan)
    w_c[1:-1] = _three_point(phi_m, np.zeros_like(phi_m), phi_p, h0, h1)
    v_w = np.full((k_count, 3), np.nan)
    if track.v_wx is not None:
        lever = track.R_wx @ t_xc
        w_w = np.einsum("kij,kj->ki", r_wc, np.nan_to_num(w_c))
        v_w = track.v_wx + np.cross(w_w, lever)
        v_w[[0, -1]] = np.nan
    else:
        v_w[1:-1] = _three_point(c_w[:-2], c_w[1:-1], c_w[2:], h0, h1)
    ok_k = np.zeros(k_count, dtype=bool)
    ok_k[1:-1] = (h0 <= max_gap_s) & (h1 <= max_gap_s)
    ts = (np.asarray(stamps_ns, dtype=np.int64) - track.stamps_ns[0]) * 1e-9
    k = np.clip(np.searchsorted(t, ts, side="right") - 1, 0, k_count - 2)
    a1 = np.clip((ts - t[k]) / np.maximum(t[k + 1] - t[k], 1e-12), 0.0, 1.0)
    # a sample with zero weight (an image stamp exactly on a pose) need not be valid
    valid = (ts >= t[0]) & (ts <= t[-1]) & (ok_k[k] | (a1 == 1)) & (ok_k[k + 1] | (a1 == 0))
    valid &= (t[k + 1] - t[k]) <= max_gap_s
    a = a1[:, None]

    def mix(x: F64) -> F64:
        lo, hi = np.nan_to_num(x[k]), np.nan_to_num(x[k + 1])
        return np.where(a == 0, lo, np.where(a == 1, hi, (1 - a) * lo + a * hi))

    w_out = mix(w_c)
    v_out_w = mix(v_w)
    rel = so3_log(np.swapaxes(r_wc[k], 1, 2) @ r_wc[k + 1])
    r_t = r_wc[k] @ so3_exp(a * rel)
    v_out = np.einsum("kji,kj->ki", r_t, v_out_w)
    v_out[~valid] = np.nan
    w_out[~valid] = np.nan
    return valid, v_out, w_out


def interpolate(stamps_ns: I64, values: F64, at_ns: I64) -> tuple[npt.NDArray[np.bool_], F64]:
    """Linear interpolation of (K, 3) ``values`` to ``at_ns``; valid inside the stamps."""
    t = (stamps_ns - stamps_ns[0]) * 1e-9
    ts = (np.asarray(at_ns, dtype=np.int64) - stamps_ns[0]) * 1e-9
    valid = (ts >= t[0]) & (ts <= t[-1])
    out = np.stack([np.interp(ts, t, values[:, i]) for i in range(3)], axis=1)
    out[~valid] = np.nan
    return valid, out


# ------------------------------------------------------------------------ selection


def select_frames(ds: Dataset, opts: ImportOptions) -> npt.NDArray[np.intp]:
    """Indices of the images kept by --start, --seconds and --every."""
    t = (ds.image_stamps_ns - ds.image_stamps_ns[0]) * 1e-9
    keep = t >= opts.start_s - 1e-9
    if opts.seconds is not None:
        keep &= t <= opts.start_s + opts.seconds + 1e-9
    idx = np.flatnonzero(keep)[:: opts.every]
    if idx.size < 2:
        raise DatasetError(
            f"{ds.root}: --start {opts.start_s:g} --seconds {opts.seconds} --every {opts.every} "
            f"keeps {idx.size} of {t.size} images (need at least 2; the images span "
            f"{t[-1]:.2f} s)"
        )
    return idx


def scaled_camera(camera: CameraModel, scale: float) -> CameraModel:
    """The camera after resizing the image by ``scale`` (pixel centres: u' = (u+.5)s-.5)."""
    if scale == 1.0:
        return camera
    w = max(1, round(camera.width * scale))
    h = max(1, round(camera.height * scale))
    sx, sy = w / camera.width, h / camera.height
    k = np.asarray(camera.K, dtype=np.float64).copy()
    k[0, 0] *= sx
    k[0, 1] *= sx
    k[1, 1] *= sy
    k[0, 2] = (k[0, 2] + 0.5) * sx - 0.5
    k[1, 2] = (k[1, 2] + 0.5) * sy - 0.5
    return CameraModel(w, h, k, np.asarray(camera.D), camera.distortion_model)


# ------------------------------------------------------------------------ images


def load_image(path: Path, camera: CameraModel, out_camera: CameraModel) -> tuple[Any, str]:
    """Decode one image file -> (array, encoding) at the output size (mono8 or mono16).

    Colour images are converted to grey (cv2 BT.601 weights).

    Raises:
        DatasetError: unreadable or damaged file, or a size other than the calibration's.
    """
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        if not path.is_file():
            raise DatasetError(f"{path}: image file is missing")
        raise DatasetError(f"{path}: unreadable image (not a PNG/JPEG or damaged)")
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if img.dtype not in (np.uint8, np.uint16) or img.ndim != 2:
        raise DatasetError(f"{path}: unsupported image format {img.dtype} {img.shape}")
    h, w = img.shape
    if (w, h) != (camera.width, camera.height):
        raise DatasetError(
            f"{path}: image is {w}x{h}, the calibration says {camera.width}x{camera.height}"
        )
    if (out_camera.width, out_camera.height) != (w, h):
        img = cv2.resize(img, (out_camera.width, out_camera.height), interpolation=cv2.INTER_AREA)
    return img, "mono8" if img.dtype == np.uint8 else "mono16"


# ------------------------------------------------------------------------ writing


def _tf_static(ns: int, r_ic: F64, t_ic: F64) -> Any:
    ts = typestore().types
    q = matrix_to_quat_xyzw(r_ic)
    tr = ts["geometry_msgs/msg/Transform"](
        translation=ts["geometry_msgs/msg/Vector3"](
            x=float(t_ic[0]), y=float(t_ic[1]), z=float(t_ic[2])
        ),
        rotation=ts["geometry_msgs/msg/Quaternion"](
            x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
        ),
    )
    stamp = ts["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    stamped = ts["geometry_msgs/msg/TransformStamped"](
        header=ts["std_msgs/msg/Header"](stamp=stamp, frame_id=IMU_FRAME),
        child_frame_id=CAMERA_FRAME,
        transform=tr,
    )
    return ts["tf2_msgs/msg/TFMessage"](transforms=[stamped])


def rotation_xyzw(r_ic: F64) -> tuple[float, float, float, float]:
    """camera_to_imu_rotation_xyzw of a rotation matrix (w >= 0)."""
    q = matrix_to_quat_xyzw(r_ic)
    q = -q if q[3] < 0 else q
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


class _Progress:
    def __init__(self, stream: TextIO | None, total: int) -> None:
        self.stream, self.total = stream, max(total, 1)
        self.t0 = self.last = time.monotonic()

    def __call__(self, done: int, force: bool = False) -> None:
        now = time.monotonic()
        if self.stream is None or (not force and now - self.last < 5.0):
            return
        self.last = now
        rate = done / max(now - self.t0, 1e-9)
        left = (self.total - done) / rate if rate > 0 else math.nan
        self.stream.write(
            f"{PROG}: frame {done}/{self.total} ({100 * done / self.total:.0f} %), "
            f"{rate:.1f} frames/s" + (f", ~{left:.0f} s left\n" if done < self.total else "\n")
        )
        self.stream.flush()


def _imu_message(ds: Dataset, j: int, acc_present: bool) -> Any:
    """sensor_msgs/Imu of IMU sample ``j`` (covariance -1 marks what is absent, REP 145)."""
    from sensor_msgs.msg import Imu

    from msg_adapters.stamps import make_header

    absent = [-1.0] + [0.0] * 8
    m = Imu(header=make_header(int(ds.imu_stamps_ns[j]), IMU_FRAME))
    m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = map(float, ds.gyro[j])
    m.orientation_covariance = list(absent)
    if acc_present:
        a_xyz = map(float, ds.accel[j])
        m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z = a_xyz
    else:
        m.linear_acceleration_covariance = list(absent)
    return m


@dataclass(frozen=True)
class _Truth:
    """Ground truth at the image stamps: (K,) masks of where it exists and (K, 3) values."""

    twist_ok: npt.NDArray[np.bool_]
    lin: F64
    ang: F64
    bias_ok: npt.NDArray[np.bool_]
    bias: F64


def _truth(ds: Dataset, stamps: npt.NDArray[np.int64]) -> _Truth:
    twist_ok = np.zeros(stamps.size, dtype=bool)
    bias_ok = np.zeros(stamps.size, dtype=bool)
    lin = ang = bias = np.zeros((stamps.size, 3))
    if ds.track is not None:
        twist_ok, lin, ang = camera_twist(ds.track, ds.R_xc, ds.t_xc, stamps)
        if ds.track.gyro_bias is not None:
            bias_ok, bias = interpolate(ds.track.stamps_ns, ds.track.gyro_bias, stamps)
    return _Truth(twist_ok, lin, ang, bias_ok, bias)


def _start_bag(
    bag: BagWriter, ds: Dataset, opts: ImportOptions, truth: _Truth, has_imu: bool
) -> None:
    """The bag's topics (those with data) and the import settings as custom data."""
    for key, (topic, msgtype, qos) in TOPICS.items():
        if (
            (key == "imu" and not has_imu)
            or (key == "twist" and not truth.twist_ok.any())
            or (key == "bias" and not truth.bias_ok.any())
        ):
            continue
        bag.add_topic(topic, msgtype, qos)
    bag.set_custom_data(
        "owl_import",
        repr(
            {
                "layout": ds.layout,
                "source": ds.root.name,
                "start_s": opts.start_s,
                "seconds": opts.seconds,
                "every": opts.every,
                "scale": opts.scale,
            }
        ),
    )


def _write_truth(bag: BagWriter, truth: _Truth, n: int, header: Any, ns: int) -> None:
    """Frame ``n``'s ground-truth twist and gyro bias, where they exist."""
    from geometry_msgs.msg import TwistStamped, Vector3Stamped

    from msg_adapters.stamps import make_header

    if truth.twist_ok[n]:
        tw = TwistStamped(header=header)
        tw.twist.linear.x, tw.twist.linear.y, tw.twist.linear.z = map(float, truth.lin[n])
        tw.twist.angular.x, tw.twist.angular.y, tw.twist.angular.z = map(float, truth.ang[n])
        bag.write(TOPICS["twist"][0], ns, tw)
    if truth.bias_ok[n]:
        b = Vector3Stamped(header=make_header(ns, IMU_FRAME))
        b.vector.x, b.vector.y, b.vector.z = map(float, truth.bias[n])
        bag.write(TOPICS["bias"][0], ns, b)


def write_dataset(
    ds: Dataset,
    out: str | Path,
    opts: ImportOptions | None = None,
    progress: TextIO | None = None,
) -> ImportSummary:
    """Write ``ds`` as a bag in the synthetic bags' layout, one image in memory at a time.

    Topics: ``/camera/image_raw`` (mono8/mono16), ``/camera/camera_info``, ``/imu/data``
    (when the dataset has an IMU), ``/tf_static`` (imu_link -> camera_optical_frame),
    ``/ground_truth/twist`` and ``/ground_truth/gyro_bias`` at image stamps where the
    poses / bias cover them. Messages are written in stamp order, serialised by
    ``BagWriter.write`` (``bags.io.serialize``). On any error nothing is left at ``out``
    (BagWriter builds the bag in a hidden sibling directory).

    Raises:
        DatasetError: an image missing, unreadable or of the wrong size.
        BagError: the output exists (no overwrite) or cannot be written.
    """
    from msg_adapters.camera_info import camera_model_to_info
    from msg_adapters.image import array_to_image
    from msg_adapters.stamps import make_header

    opts = opts or ImportOptions()
    t_start = time.monotonic()
    idx = select_frames(ds, opts)
    stamps = ds.image_stamps_ns[idx]
    files = [ds.image_files[i] for i in idx]
    missing = next((p for p in files if not p.is_file()), None)
    if missing is not None:  # fail before writing anything
        raise DatasetError(f"{missing}: image file is missing")
    out_camera = scaled_camera(ds.camera, opts.scale)
    margin = round(opts.imu_margin_s * 1e9)
    imu_keep = (ds.imu_stamps_ns >= stamps[0] - margin) & (ds.imu_stamps_ns <= stamps[-1] + margin)
    imu_keep &= ds.imu_stamps_ns >= 0
    imu_idx = np.flatnonzero(imu_keep)
    truth = _truth(ds, stamps)
    info = camera_model_to_info(out_camera)
    report = _Progress(progress, stamps.size)
    acc_present = bool(np.all(np.isfinite(ds.accel[imu_idx]))) if imu_idx.size else False
    imu_topic = TOPICS["imu"][0]
    with BagWriter(out, overwrite=opts.overwrite) as bag:
        _start_bag(bag, ds, opts, truth, bool(imu_idx.size))
        first = int(min(stamps[0], ds.imu_stamps_ns[imu_idx[0]] if imu_idx.size else stamps[0]))
        bag.write(TOPICS["tf"][0], first, _tf_static(first, ds.R_ic, ds.t_ic))
        j = 0
        for n, (ns_, path) in enumerate(zip(stamps.tolist(), files, strict=True)):
            ns = int(ns_)
            while j < imu_idx.size and ds.imu_stamps_ns[imu_idx[j]] <= ns:
                jj = int(imu_idx[j])
                bag.write(imu_topic, int(ds.imu_stamps_ns[jj]), _imu_message(ds, jj, acc_present))
                j += 1
            img, encoding = load_image(path, ds.camera, out_camera)
            header = make_header(ns, CAMERA_FRAME)
            bag.write(TOPICS["image"][0], ns, array_to_image(img, encoding, header))
            info.header = header
            bag.write(TOPICS["info"][0], ns, info)
            _write_truth(bag, truth, n, header, ns)
            report(n + 1)
        for jj in imu_idx[j:].tolist():
            bag.write(imu_topic, int(ds.imu_stamps_ns[jj]), _imu_message(ds, jj, acc_present))
    report(stamps.size, True)
    return ImportSummary(
        out_path=Path(out),
        frames=int(stamps.size),
        imu_samples=int(imu_idx.size),
        twist_frames=int(truth.twist_ok.sum()),
        bias_frames=int(truth.bias_ok.sum()),
        camera=out_camera,
        camera_to_imu_rotation_xyzw=rotation_xyzw(ds.R_ic),
        elapsed_s=time.monotonic() - t_start,
    )


def default_progress(quiet: bool) -> TextIO | None:
    """stderr unless quiet."""
    return None if quiet else sys.stderr
