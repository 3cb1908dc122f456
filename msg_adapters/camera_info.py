"""sensor_msgs/CameraInfo <-> owl_core.camera.CameraModel.

Distortion models: ``plumb_bob`` (k1 k2 p1 p2 k3), ``rational_polynomial`` (k1 k2 p1 p2 k3
k4 k5 k6), ``equidistant`` (k1 k2 k3 k4). A plumb_bob or rational_polynomial with all-zero
(or empty) D, and an empty model name with empty D, is the distortion-free model "none"
(same projection, cheaper to invert); ``camera_model_to_info`` writes "none" as plumb_bob
with five zeros, which is what ROS calibration tools expect, so model -> info -> model is
exact for every model. Trailing zeros beyond a model's coefficient count are ignored.

Binning and ROI follow image_geometry: the returned model describes the image actually
published (size ``roi`` / binning; ``cx' = (cx - x_offset) / binning_x``, ``fx' = fx /
binning_x``, likewise for y).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from sensor_msgs.msg import CameraInfo

from msg_adapters.errors import CameraInfoError
from owl_core.camera import DISTORTION_MODELS, CameraModel
from owl_core.errors import CalibrationError

#: ROS distortion model names accepted from CameraInfo.
ROS_DISTORTION_MODELS: tuple[str, ...] = ("plumb_bob", "rational_polynomial", "equidistant")
#: models for which all-zero coefficients mean "no distortion".
_ZERO_IS_NONE = ("plumb_bob", "rational_polynomial")


def _distortion(model: str, d: np.ndarray[Any, np.dtype[np.float64]]) -> tuple[str, Any]:
    if model == "" and not np.any(d):
        return "none", np.zeros(0)
    if model not in ROS_DISTORTION_MODELS:
        raise CameraInfoError(
            f"camera_info.distortion_model {model!r} is not supported; expected one of "
            f"{', '.join(ROS_DISTORTION_MODELS)}"
        )
    if model in _ZERO_IS_NONE and not np.any(d):
        return "none", np.zeros(0)
    count = DISTORTION_MODELS[model]
    if d.shape[0] > count and not np.any(d[count:]):
        d = d[:count]
    return model, d


def _check_roi(msg: Any) -> bool:
    """True for a real ROI, False for the all-zero "full resolution" one; a partial ROI
    (offsets without a size, a zero width or height) or one outside the image is an error,
    since ignoring it would shift the principal point silently."""
    roi = msg.roi
    x, y, w, h = (int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height))
    if x == y == w == h == 0:
        return False
    if w == 0 or h == 0 or x + w > int(msg.width) or y + h > int(msg.height):
        raise CameraInfoError(
            f"camera_info.roi (x_offset {x}, y_offset {y}, width {w}, height {h}) is not a "
            f"region of the {int(msg.width)}x{int(msg.height)} image (all zero means full)"
        )
    return True


def camera_info_to_model(msg: Any, rectified: bool = False) -> CameraModel:
    """CameraInfo -> CameraModel of the published image (binning and ROI applied).

    Args:
        msg: sensor_msgs/CameraInfo.
        rectified: the image is the rectified one (``image_rect``): the intrinsics are
            the left 3x3 of the projection P and there is no distortion (D is ignored);
            else K and D describe the raw image.

    Raises:
        CameraInfoError: all-zero K (uncalibrated camera), unsupported distortion_model,
            wrong number of D coefficients, zero size, an ROI that is neither all zero
            nor inside the image, or any other invalid calibration
            (the message names the field and value).
    """
    if rectified:
        k = np.asarray(msg.p, dtype=np.float64).reshape(3, 4)[:, :3].copy()
        field = "p"
    else:
        k = np.asarray(msg.k, dtype=np.float64).reshape(3, 3).copy()
        field = "k"
    if not np.any(k):
        raise CameraInfoError(
            f"camera_info.{field} is all zero (uncalibrated camera, frame_id "
            f"{msg.header.frame_id!r})"
        )
    if rectified:
        model, d = "none", np.zeros(0)
    else:
        model, d = _distortion(str(msg.distortion_model), np.asarray(msg.d, dtype=np.float64))
    bx, by = max(1, int(msg.binning_x)), max(1, int(msg.binning_y))
    has_roi = _check_roi(msg)
    roi = msg.roi
    width = int(roi.width) if has_roi else int(msg.width)
    height = int(roi.height) if has_roi else int(msg.height)
    if has_roi:
        k[0, 2] -= float(roi.x_offset)
        k[1, 2] -= float(roi.y_offset)
    if bx > 1 or by > 1:
        k[0, :] /= bx
        k[1, :] /= by
        width //= bx
        height //= by
    try:
        return CameraModel(width, height, k, d, model)
    except CalibrationError as exc:
        raise CameraInfoError(f"camera_info: {exc}") from exc


def camera_model_to_info(model: CameraModel, header: Any = None) -> Any:
    """CameraModel -> CameraInfo (R = identity, P = [K | 0], no binning, no ROI)."""
    msg = CameraInfo()
    if header is not None:
        msg.header = header
    msg.width = model.width
    msg.height = model.height
    if model.distortion_model == "none":
        msg.distortion_model = "plumb_bob"
        msg.d = [0.0] * DISTORTION_MODELS["plumb_bob"]
    else:
        msg.distortion_model = model.distortion_model
        msg.d = [float(c) for c in model.D]
    k = np.asarray(model.K, dtype=np.float64)
    msg.k = k.reshape(9).copy()
    msg.r = np.eye(3).reshape(9)
    msg.p = np.hstack([k, np.zeros((3, 1))]).reshape(12)
    return msg
