"""owl_core.geometry against scipy's independent rotation implementation."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from owl_core.errors import InvalidInputError
from owl_core.geometry import (
    matrix_to_quat_xyzw,
    quat_xyzw_to_matrix,
    skew,
    so3_exp,
    so3_log,
)

RNG = np.random.default_rng(1234)


def _rotvecs() -> np.ndarray:
    """Random rotation vectors over all angles, plus tiny and near-pi ones."""
    axes = RNG.normal(size=(300, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate(
        [
            RNG.uniform(0.0, np.pi, 200),
            10.0 ** RNG.uniform(-12, -3, 60),
            np.pi - 10.0 ** RNG.uniform(-9, -2, 39),
            [0.0],
        ]
    )
    return axes * angles[:, None]


def test_skew_is_cross_product() -> None:
    a, b = RNG.normal(size=(2, 50, 3))
    np.testing.assert_allclose(skew(a) @ b[..., None], np.cross(a, b)[..., None], atol=1e-14)
    np.testing.assert_array_equal(skew(a), -np.swapaxes(skew(a), -1, -2))


def test_so3_exp_matches_scipy() -> None:
    w = _rotvecs()
    np.testing.assert_allclose(so3_exp(w), Rotation.from_rotvec(w).as_matrix(), atol=2e-15)


def test_so3_exp_tiny_angle_is_first_order_accurate() -> None:
    w = np.array([1e-9, -2e-9, 3e-9])
    expected = np.eye(3) + skew(w) + 0.5 * skew(w) @ skew(w)
    np.testing.assert_allclose(so3_exp(w), expected, atol=1e-20, rtol=0)


def test_so3_log_inverts_exp() -> None:
    w = _rotvecs()
    r = so3_exp(w)
    back = so3_log(r)
    # Exact inverse below pi; near pi compare rotations (sign of axis is ambiguous at pi).
    below = np.linalg.norm(w, axis=1) < np.pi - 1e-6
    scale = np.maximum(np.linalg.norm(w[below], axis=1, keepdims=True), 1e-300)
    np.testing.assert_allclose(back[below] / scale, w[below] / scale, atol=1e-12)
    np.testing.assert_allclose(so3_exp(back), r, atol=1e-14)
    assert np.all(np.linalg.norm(back, axis=1) <= np.pi + 1e-12)


def test_so3_log_relative_precision_small_angles() -> None:
    w = np.array([[3e-11, -1e-11, 2e-11], [0.0, 0.0, 1e-8]])
    np.testing.assert_allclose(so3_log(so3_exp(w)), w, rtol=1e-6, atol=0)


def test_batched_shapes() -> None:
    w = RNG.normal(size=(4, 5, 3))
    r = so3_exp(w)
    assert r.shape == (4, 5, 3, 3)
    assert so3_log(r).shape == (4, 5, 3)
    assert matrix_to_quat_xyzw(r).shape == (4, 5, 4)
    assert quat_xyzw_to_matrix(matrix_to_quat_xyzw(r)).shape == (4, 5, 3, 3)
    assert so3_exp(np.zeros(3)).shape == (3, 3)


def test_quaternion_conversions_match_scipy() -> None:
    w = _rotvecs()
    q = matrix_to_quat_xyzw(so3_exp(w))
    ref = Rotation.from_rotvec(w).as_quat()  # scipy uses (x, y, z, w) too
    ref = np.where(ref[:, 3:4] < 0, -ref, ref)
    # At exactly w = 0 the sign is arbitrary; compare up to sign.
    dots = np.abs(np.sum(q * ref, axis=1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-14)
    assert np.all(q[:, 3] >= 0.0)
    np.testing.assert_allclose(
        quat_xyzw_to_matrix(ref), Rotation.from_quat(ref).as_matrix(), atol=2e-15
    )


def test_quat_is_normalised_and_contract_example() -> None:
    # Camera looking along IMU x (IMU x forward, y left, z up; camera z forward,
    # x right, y down): camera-frame vectors into the IMU frame.
    r = quat_xyzw_to_matrix([-0.5, 0.5, -0.5, 0.5])
    np.testing.assert_allclose(r @ [0, 0, 1], [1, 0, 0], atol=1e-15)  # forward
    np.testing.assert_allclose(r @ [1, 0, 0], [0, -1, 0], atol=1e-15)  # right = -left
    np.testing.assert_allclose(r @ [0, 1, 0], [0, 0, -1], atol=1e-15)  # down = -up
    np.testing.assert_allclose(quat_xyzw_to_matrix([0, 0, 0, 3.0]), np.eye(3))


@pytest.mark.parametrize(
    ("func", "value", "match"),
    [
        (so3_exp, np.zeros((2, 4)), r"\(2, 4\)"),
        (so3_log, np.zeros((3, 2)), r"\(3, 2\)"),
        (skew, np.zeros(2), r"\(2,\)"),
        (quat_xyzw_to_matrix, np.zeros(3), r"\(3,\)"),
        (quat_xyzw_to_matrix, np.zeros(4), "non-zero norm"),
        (quat_xyzw_to_matrix, [np.nan, 0, 0, 1], "finite"),
        (matrix_to_quat_xyzw, np.eye(4), r"\(4, 4\)"),
    ],
)
def test_bad_input_raises(func, value, match) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(InvalidInputError, match=match):
        func(value)
