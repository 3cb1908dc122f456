"""Small typed records at the boundaries of owl_core.

Time is integer nanoseconds (as rosbags and builtin_interfaces/Time use it);
angles in radians, angular rates in rad/s; vectors in the camera optical frame
(REP 103: x right, y down, z forward) unless the field says otherwise.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


class PointFlag(enum.IntFlag):
    """Bits of the per-point ``flags`` field (uint8), as the contract names them."""

    L_LOCAL = 1  #: L came from the local deformation rule
    L_HEADING = 2  #: L came from the heading route (|omega| cot(alpha))
    MOVING = 4  #: suspected independently moving point (or outlier)
    LOW_QUALITY = 8  #: quality below EngineOptions.min_quality
    NO_GYRO = 16  #: frame processed without gyro derotation (uncompensated rotation)
    IMU_GAP = 32  #: the IMU did not fully cover the frame interval


@dataclass(frozen=True)
class ImageFrame:
    """One camera image.

    Attributes:
        stamp_ns: capture time, integer nanoseconds (camera clock).
        image: (H, W) uint8 grey image (adapters convert colour and 16-bit).
    """

    stamp_ns: int
    image: npt.NDArray[np.uint8]


@dataclass(frozen=True)
class GyroSamples:
    """A run of gyro samples in the IMU frame, in time order.

    Attributes:
        stamp_ns: (N,) int64 sample times, nanoseconds (IMU clock).
        angular_velocity: (N, 3) float64 angular velocity in the IMU frame, rad/s.
    """

    stamp_ns: npt.NDArray[np.int64]
    angular_velocity: FloatArray


@dataclass(frozen=True)
class FrameResult:
    """Everything the engine measured for one image. N = number of output points.

    Arrays are empty (N = 0) when the frame produced no points; ``reasons`` then
    says why. All per-point arrays share the first dimension N.

    Attributes:
        stamp_ns: the image stamp, nanoseconds.
        pixels: (N, 2) float64 pixel coordinates (u, v) in the distorted image.
        bearings: (N, 3) float64 unit bearings e, camera optical frame.
        looming: (N,) float64 L = (t.e)/r, 1/s (positive while the range shrinks).
        omega: (N, 3) float64 perceived rotation (e x t)/r, 1/s.
        rot: (N, 4) float64 RoT = ToR^-1 scalar-first (w, x, y, z), seconds.
        range_over_speed: (N,) float64 r/|t|, seconds.
        points: (N, 3) float64 scaled points e * r/|t|, seconds.
        quality: (N,) float64 in [0, 1], 1 = rigid, well-fitted neighbourhood.
        ids: (N,) uint32 persistent track ids.
        flags: (N,) uint8 PointFlag bits.
        heading: (3,) unit translation direction t/|t| (camera frame), or None
            when the frame gives none (no translation, too few points).
        heading_sigma_rad: 1-sigma angular uncertainty of ``heading``, radians
            (inf when heading is None).
        gyro_bias: (3,) current gyro-bias estimate, IMU frame, rad/s.
        timings: seconds spent per stage (keys such as "detect", "track",
            "integrate", "looming", "heading", "total").
        reasons: human-readable reasons why points are missing or the frame
            produced none (empty when nothing was dropped).
        dropped: counts of dropped features per reason key.
        speed_rate: ``d ln|t|/dt`` at the stamp, 1/s: the relative rate of change of the
            camera's speed that the engine measured from frame to frame (r/|t| and L are
            in units of the speed at the stamp); 0 without ``estimate_speed_change`` and
            until its filter has a measurement.
    """

    stamp_ns: int
    pixels: FloatArray
    bearings: FloatArray
    looming: FloatArray
    omega: FloatArray
    rot: FloatArray
    range_over_speed: FloatArray
    points: FloatArray
    quality: FloatArray
    ids: npt.NDArray[np.uint32]
    flags: npt.NDArray[np.uint8]
    heading: FloatArray | None
    heading_sigma_rad: float
    gyro_bias: FloatArray
    timings: dict[str, float] = field(default_factory=dict)
    reasons: tuple[str, ...] = ()
    dropped: dict[str, int] = field(default_factory=dict)
    speed_rate: float = 0.0

    @property
    def num_points(self) -> int:
        """N, the number of output points."""
        return int(self.looming.shape[0])
