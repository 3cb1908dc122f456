"""CameraInfo <-> CameraModel: every model round trips, binning/ROI, and errors name values."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo

from msg_adapters.camera_info import camera_info_to_model, camera_model_to_info
from msg_adapters.errors import CameraInfoError
from msg_adapters.stamps import make_header
from owl_core.camera import CameraModel

K = np.array([[400.0, 0.0, 161.5], [0.0, 401.0, 118.25], [0.0, 0.0, 1.0]])
MODELS = {
    "plumb_bob": [-0.21, 0.05, 0.001, -0.0007, -0.004],
    "rational_polynomial": [0.1, -0.02, 0.0005, 0.0003, 0.001, 0.12, -0.01, 0.002],
    "equidistant": [0.02, -0.01, 0.003, -0.0005],
    "none": [],
}


@pytest.mark.parametrize("name", list(MODELS))
def test_model_info_model_round_trip_is_exact(name):
    model = CameraModel(320, 240, K, np.array(MODELS[name]), name)
    info = camera_model_to_info(model, make_header(7, "cam_optical"))
    wire = deserialize_message(serialize_message(info), CameraInfo)
    back = camera_info_to_model(wire)
    assert back == model
    assert wire.header.frame_id == "cam_optical"
    np.testing.assert_array_equal(np.asarray(wire.p).reshape(3, 4)[:, :3], K)
    np.testing.assert_array_equal(np.asarray(wire.r).reshape(3, 3), np.eye(3))


def test_none_is_written_as_plumb_bob_zeros():
    info = camera_model_to_info(CameraModel.pinhole(320, 240, 400, 400, 160, 120))
    assert info.distortion_model == "plumb_bob"
    assert list(info.d) == [0.0] * 5


@pytest.mark.parametrize(
    ("model", "d"),
    [("plumb_bob", [0.0] * 5), ("rational_polynomial", [0.0] * 8), ("plumb_bob", []), ("", [])],
)
def test_zero_distortion_reads_as_none(model, d):
    info = CameraInfo(width=320, height=240, distortion_model=model, d=d, k=K.reshape(9))
    assert camera_info_to_model(info).distortion_model == "none"


def test_equidistant_with_zero_coefficients_is_not_pinhole():
    # theta_d = theta differs from tan(theta): zeros must keep the fisheye model
    info = CameraInfo(
        width=320, height=240, distortion_model="equidistant", d=[0.0] * 4, k=K.reshape(9)
    )
    model = camera_info_to_model(info)
    assert model.distortion_model == "equidistant"


def test_trailing_zero_coefficients_are_dropped():
    d = [*MODELS["plumb_bob"], 0.0, 0.0, 0.0]
    info = CameraInfo(width=320, height=240, distortion_model="plumb_bob", d=d, k=K.reshape(9))
    np.testing.assert_array_equal(camera_info_to_model(info).D, MODELS["plumb_bob"])


def test_binning_and_roi_describe_the_published_image():
    info = CameraInfo(width=640, height=480, distortion_model="plumb_bob", d=[0.0] * 5)
    info.k = np.array([[800.0, 0, 320.0], [0, 800.0, 240.0], [0, 0, 1]]).reshape(9)
    info.binning_x = info.binning_y = 2
    info.roi.x_offset, info.roi.y_offset, info.roi.width, info.roi.height = 100, 40, 400, 300
    model = camera_info_to_model(info)
    assert (model.width, model.height) == (200, 150)
    np.testing.assert_array_equal(model.K, [[400.0, 0, 110.0], [0, 400.0, 100.0], [0, 0, 1]])


def test_zero_k_is_an_error_naming_the_field():
    info = CameraInfo(width=320, height=240, distortion_model="plumb_bob", d=[0.0] * 5)
    info.header.frame_id = "front"
    with pytest.raises(CameraInfoError, match=r"camera_info.k is all zero.*'front'"):
        camera_info_to_model(info)


def test_unknown_model_names_the_value():
    info = CameraInfo(width=320, height=240, distortion_model="kannala_brandt", d=[0.1] * 4)
    info.k = K.reshape(9)
    with pytest.raises(CameraInfoError, match="'kannala_brandt'"):
        camera_info_to_model(info)


def test_wrong_coefficient_count_and_zero_size_are_camera_info_errors():
    info = CameraInfo(width=320, height=240, distortion_model="plumb_bob", d=[0.1, 0.2, 0.3])
    info.k = K.reshape(9)
    with pytest.raises(CameraInfoError, match="needs 5 coefficients"):
        camera_info_to_model(info)
    info.d = MODELS["plumb_bob"]
    info.width = 0
    with pytest.raises(CameraInfoError, match="width must be positive, got 0"):
        camera_info_to_model(info)


def test_rectified_input_uses_p_and_ignores_d():
    model = CameraModel(320, 240, K, np.array(MODELS["plumb_bob"]), "plumb_bob")
    info = camera_model_to_info(model, make_header(7, "cam_optical"))
    p = np.array([[380.0, 0.0, 158.0, 0.0], [0.0, 380.0, 121.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    info.p = p.reshape(12)
    raw = camera_info_to_model(info)
    assert raw.distortion_model == "plumb_bob"
    np.testing.assert_array_equal(raw.K, K)
    rect = camera_info_to_model(info, rectified=True)
    assert rect.distortion_model == "none" and rect.D.size == 0
    np.testing.assert_array_equal(rect.K, p[:, :3])
    info.p = np.zeros(12)
    with pytest.raises(CameraInfoError, match=r"camera_info\.p is all zero"):
        camera_info_to_model(info, rectified=True)


def test_pipeline_rectified_parameter_takes_p():
    from owl_ros.params import build_options
    from owl_ros.pipeline import Pipeline

    model = CameraModel(320, 240, K, np.array(MODELS["plumb_bob"]), "plumb_bob")
    info = camera_model_to_info(model, make_header(7, "cam_optical"))
    info.p = np.array([[380.0, 0, 158, 0], [0, 380.0, 121, 0], [0, 0, 1, 0]]).reshape(12)
    for rectified, fx, dist in ((False, 400.0, "plumb_bob"), (True, 380.0, "none")):
        pipe = Pipeline(build_options({"rectified": rectified}))
        pipe.add_camera_info(info)
        assert pipe.camera is not None
        assert (pipe.camera.K[0, 0], pipe.camera.distortion_model) == (fx, dist)


@pytest.mark.parametrize(
    "roi",
    [(100, 40, 0, 0), (0, 0, 400, 0), (300, 0, 400, 300), (0, 200, 400, 300)],
    ids=["offsets-only", "zero-height", "beyond-width", "beyond-height"],
)
def test_partial_or_outside_roi_is_refused_not_ignored(roi):
    info = CameraInfo(width=640, height=480, distortion_model="plumb_bob", d=[0.0] * 5)
    info.k = K.reshape(9)
    info.roi.x_offset, info.roi.y_offset, info.roi.width, info.roi.height = roi
    with pytest.raises(CameraInfoError, match=r"camera_info\.roi .* 640x480 image"):
        camera_info_to_model(info)
    # the full image as ROI is the same as no ROI
    info.roi.x_offset, info.roi.y_offset, info.roi.width, info.roi.height = 0, 0, 640, 480
    assert camera_info_to_model(info).K[0, 2] == K[0, 2]
