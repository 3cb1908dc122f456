"""CameraModel: exact inverse over the whole image, agreement with OpenCV, validation."""

import cv2
import numpy as np
import pytest

from owl_core.camera import CameraModel
from owl_core.errors import CalibrationError, InvalidInputError

W, H = 640, 480
K_PINHOLE = np.array([[460.0, 0.0, 322.5], [0.0, 458.0, 241.25], [0.0, 0.0, 1.0]])
K_FISHEYE = np.array([[250.0, 0.0, 318.0], [0.0, 251.0, 242.0], [0.0, 0.0, 1.0]])

# Realistic coefficients: a wide-angle webcam-like plumb_bob, an OpenCV
# rational fit, and a typical 180-degree-class fisheye.
CAMERAS = {
    "plumb_bob": CameraModel(
        W, H, K_PINHOLE, np.array([-0.28, 0.07, 2e-4, -1.5e-4, 0.0]), "plumb_bob"
    ),
    "rational_polynomial": CameraModel(
        W,
        H,
        K_PINHOLE,
        np.array([-0.3, 0.1, 1e-3, -5e-4, -0.01, 0.05, 0.01, 0.002]),
        "rational_polynomial",
    ),
    "equidistant": CameraModel(
        W, H, K_FISHEYE, np.array([-0.013, 0.018, -0.021, 0.007]), "equidistant"
    ),
    "none": CameraModel.pinhole(W, H, 460.0, 458.0, 322.5, 241.25),
}


def _grid(step: float = 2.0) -> np.ndarray:
    """Dense pixel grid covering the whole image including its border."""
    u, v = np.meshgrid(
        np.arange(-0.5, W - 0.5 + 1e-9, step), np.arange(-0.5, H - 0.5 + 1e-9, step)
    )
    corners = [[-0.5, -0.5], [W - 0.5, -0.5], [-0.5, H - 0.5], [W - 0.5, H - 0.5]]
    return np.concatenate([np.stack([u.ravel(), v.ravel()], axis=-1), corners])


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors, accurate for tiny angles."""
    return 2.0 * np.arctan2(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_round_trip_whole_image(name: str) -> None:
    cam = CAMERAS[name]
    px = _grid()
    bearings = cam.pixel_to_bearing(px)
    assert bearings.shape == (px.shape[0], 3)
    assert np.all(np.isfinite(bearings))
    np.testing.assert_allclose(np.linalg.norm(bearings, axis=1), 1.0, atol=1e-15)
    back = cam.bearing_to_pixel(bearings)
    assert np.max(np.abs(back - px)) < 1e-6
    # and the other way: re-deriving the bearings agrees to ~1e-9 rad or better
    again = cam.pixel_to_bearing(back)
    assert np.max(_angle(again, bearings)) < 1e-9


@pytest.mark.parametrize("name", ["plumb_bob", "rational_polynomial"])
def test_forward_model_matches_cv2_project_points(name: str) -> None:
    cam = CAMERAS[name]
    bearings = cam.pixel_to_bearing(_grid(step=7.0))
    rng = np.random.default_rng(5)
    points = bearings * rng.uniform(0.5, 20.0, size=(len(bearings), 1))  # any range
    ref, _ = cv2.projectPoints(
        points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), np.array(cam.K), np.array(cam.D)
    )
    np.testing.assert_allclose(cam.bearing_to_pixel(points), ref.reshape(-1, 2), atol=1e-9)


def test_forward_model_matches_cv2_fisheye() -> None:
    cam = CAMERAS["equidistant"]
    bearings = cam.pixel_to_bearing(_grid(step=7.0))
    front = bearings[bearings[:, 2] > 0.05]  # OpenCV's fisheye uses atan(r): Z > 0 only
    ref, _ = cv2.fisheye.projectPoints(
        front.reshape(1, -1, 3), np.zeros(3), np.zeros(3), np.array(cam.K), np.array(cam.D)
    )
    np.testing.assert_allclose(cam.bearing_to_pixel(front), ref.reshape(-1, 2), atol=1e-9)


def test_inverse_agrees_with_tightly_converged_opencv() -> None:
    # Independent check of pixel_to_bearing: OpenCV's iterative undistortion,
    # with the criteria tightened far beyond its default (5 iterations).
    cam = CAMERAS["plumb_bob"]
    px = _grid(step=13.0)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    ref = cv2.undistortPointsIter(
        px.reshape(-1, 1, 2), np.array(cam.K), np.array(cam.D), None, None, crit
    ).reshape(-1, 2)
    ours = cam.pixel_to_bearing(px)
    np.testing.assert_allclose(ours[:, :2] / ours[:, 2:], ref, atol=1e-9)


def test_equidistant_beyond_90_degrees() -> None:
    # A fisheye images rays behind the image plane; the model is monotonic to pi here.
    cam = CAMERAS["equidistant"]
    theta = np.linspace(0.0, 1.7, 50)
    phi = np.linspace(-np.pi, np.pi, 50)
    b = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    px = cam.bearing_to_pixel(b)
    assert np.all(np.isfinite(px))
    assert np.max(_angle(cam.pixel_to_bearing(px), b)) < 1e-12
    # radius in normalised image coordinates is theta_d, exactly as the formula says
    k1, k2, k3, k4 = cam.D
    theta_d = theta * (1 + k1 * theta**2 + k2 * theta**4 + k3 * theta**6 + k4 * theta**8)
    rd = np.hypot((px[:, 0] - cam.cx) / cam.fx, (px[:, 1] - cam.cy) / cam.fy)
    np.testing.assert_allclose(rd, theta_d, atol=1e-12)


@pytest.mark.parametrize("name", ["plumb_bob", "rational_polynomial", "none"])
def test_behind_camera_is_nan(name: str) -> None:
    cam = CAMERAS[name]
    px = cam.bearing_to_pixel(
        [[0.1, 0.2, -1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [np.nan, 0, 1], [0.1, 0.2, 1.0]]
    )
    assert np.all(np.isnan(px[:4]))
    assert np.all(np.isfinite(px[4]))


def test_fold_over_region_is_nan() -> None:
    # f(r) = r (1 + k1 r^2) stops increasing at r = 1 / sqrt(-3 k1).
    k1 = -0.4
    cam = CameraModel(W, H, K_PINHOLE, np.array([k1, 0.0, 0.0, 0.0, 0.0]), "plumb_bob")
    r_max = 1.0 / np.sqrt(-3.0 * k1)
    assert cam.valid_limit == pytest.approx(r_max, rel=1e-12)
    inside = cam.bearing_to_pixel([[0.99 * r_max, 0.0, 1.0]])
    beyond = cam.bearing_to_pixel([[1.01 * r_max, 0.0, 1.0], [3.0 * r_max, 0.0, 1.0]])
    assert np.all(np.isfinite(inside))
    assert np.all(np.isnan(beyond))  # OpenCV would fold these back into the image
    # pixels beyond the image of r_max have no preimage
    rd_max = r_max * (1.0 + k1 * r_max**2)
    u_out = cam.cx + cam.fx * rd_max * 1.001
    assert np.all(np.isnan(cam.pixel_to_bearing([[u_out, cam.cy]])))
    assert np.all(np.isfinite(cam.pixel_to_bearing([[cam.cx + cam.fx * rd_max * 0.999, cam.cy]])))


def test_skew_round_trip_and_shapes() -> None:
    k = K_PINHOLE.copy()
    k[0, 1] = 0.8
    cam = CameraModel(W, H, k, np.array([-0.2, 0.05, 1e-3, 1e-3, 0.0]), "plumb_bob")
    px = _grid(step=11.0).reshape(-1, 1, 2)[:300].reshape(10, 30, 2)
    b = cam.pixel_to_bearing(px)
    assert b.shape == (10, 30, 3)
    np.testing.assert_allclose(cam.bearing_to_pixel(b), px, atol=1e-9)
    # skew enters u = fx xd + s yd + cx
    plain = CameraModel(W, H, k, np.zeros(5), "plumb_bob")
    np.testing.assert_allclose(
        plain.bearing_to_pixel([0.1, 0.2, 1.0]),
        [460.0 * 0.1 + 0.8 * 0.2 + 322.5, 458.0 * 0.2 + 241.25],
        atol=1e-12,
    )


def test_pinhole_is_plain_projection() -> None:
    cam = CAMERAS["none"]
    np.testing.assert_allclose(
        cam.bearing_to_pixel([[0.2, -0.1, 2.0]]), [[322.5 + 46.0, 241.25 - 22.9]], atol=1e-12
    )
    b = cam.pixel_to_bearing([[322.5, 241.25]])
    np.testing.assert_allclose(b, [[0.0, 0.0, 1.0]], atol=0)


def test_in_image() -> None:
    cam = CAMERAS["none"]
    px = np.array(
        [[-0.5, -0.5], [W - 0.5, H - 0.5], [-0.6, 10], [10, H - 0.4], [np.nan, 3], [5.0, 5.0]]
    )
    np.testing.assert_array_equal(cam.in_image(px), [True, True, False, False, False, True])
    np.testing.assert_array_equal(
        cam.in_image(px, margin_px=5.0), [False, False, False, False, False, True]
    )


def test_record_semantics() -> None:
    a = CameraModel(W, H, K_PINHOLE.ravel().tolist(), [0.0] * 5, "plumb_bob")  # ROS flat K
    b = CameraModel(W, H, K_PINHOLE, np.zeros(5), "plumb_bob")
    assert a == b and hash(a) == hash(b)
    assert a != CAMERAS["none"]
    with pytest.raises(ValueError, match="read-only"):
        a.K[0, 0] = 1.0
    with pytest.raises(AttributeError):
        a.width = 3  # type: ignore[misc]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"K": [[0.0, 0, 320], [0, 460, 240], [0, 0, 1]]}, r"fx.*0\.0"),
        ({"K": [[460.0, 0, 320], [0, -5, 240], [0, 0, 1]]}, r"fy.*-5\.0"),
        ({"K": [[460.0, 0, 320], [0, np.nan, 240], [0, 0, 1]]}, "finite"),
        ({"K": [[460.0, 0, 320], [0, 460, 240], [0, 0, 2]]}, "must be"),
        ({"K": np.eye(2)}, r"\(2, 2\)"),
        ({"D": [0.1, 0.0, 0.0, 0.0]}, "needs 5 coefficients.*got 4"),
        ({"D": [0.1, 0.0, 0.0, np.inf, 0.0]}, "finite"),
        ({"distortion_model": "fisheye"}, "'fisheye'"),
        ({"distortion_model": "rational_polynomial"}, "needs 8"),
        ({"distortion_model": "equidistant"}, "needs 4"),
        ({"distortion_model": "none", "D": [0.1, 0, 0, 0, 0]}, "no coefficients"),
        ({"width": 0}, "width.*0"),
        ({"height": 480.5}, "height.*480.5"),
        ({"D": [-1e6, 0.0, 0.0, 0.0, 0.0]}, "folds over"),
    ],
)
def test_validation(kwargs: dict, match: str) -> None:  # type: ignore[type-arg]
    args = {
        "width": W,
        "height": H,
        "K": K_PINHOLE,
        "D": np.zeros(5),
        "distortion_model": "plumb_bob",
    }
    args.update(kwargs)
    with pytest.raises(CalibrationError, match=match):
        CameraModel(**args)


def test_bad_point_shapes() -> None:
    cam = CAMERAS["none"]
    with pytest.raises(InvalidInputError, match=r"\(4, 3\)"):
        cam.pixel_to_bearing(np.zeros((4, 3)))
    with pytest.raises(InvalidInputError, match=r"\(4, 2\)"):
        cam.bearing_to_pixel(np.zeros((4, 2)))
