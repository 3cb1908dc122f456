"""Rotations: SO(3) exponential and logarithm, skew matrices, quaternions.

Every function is vectorised over leading dimensions: a ``(..., 3)`` rotation
vector gives a ``(..., 3, 3)`` matrix, and so on. Rotation vectors are axis *
angle (radians, right-hand rule); quaternions are ROS order ``(x, y, z, w)``.
A matrix ``R`` acts on column vectors, ``v' = R @ v``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from owl_core.errors import InvalidInputError

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "matrix_to_quat_xyzw",
    "quat_xyzw_to_matrix",
    "skew",
    "so3_exp",
    "so3_log",
]

# Below this angle (rad) so3_exp uses Taylor series; their truncation error
# (theta^6 / 5040) is far below float64 resolution there.
_SMALL_ANGLE = 1e-4


def _as_float_array(x: npt.ArrayLike, name: str, tail: tuple[int, ...]) -> FloatArray:
    """Convert to float64 and check the trailing shape, quoting the actual shape."""
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name} must be numeric, got {x!r}") from exc
    if arr.ndim < len(tail) or arr.shape[arr.ndim - len(tail) :] != tail:
        want = "(..., " + ", ".join(str(t) for t in tail) + ")"
        raise InvalidInputError(f"{name} must have shape {want}, got {arr.shape}")
    return arr


def skew(v: npt.ArrayLike) -> FloatArray:
    """Cross-product matrix: ``skew(v) @ u == np.cross(v, u)``.

    Args:
        v: (..., 3) vectors.

    Returns:
        (..., 3, 3) float64 antisymmetric matrices.
    """
    a = _as_float_array(v, "v", (3,))
    out = np.zeros((*a.shape[:-1], 3, 3), dtype=np.float64)
    x, y, z = a[..., 0], a[..., 1], a[..., 2]
    out[..., 0, 1] = -z
    out[..., 0, 2] = y
    out[..., 1, 0] = z
    out[..., 1, 2] = -x
    out[..., 2, 0] = -y
    out[..., 2, 1] = x
    return out


def so3_exp(rotvec: npt.ArrayLike) -> FloatArray:
    """Rotation matrices from rotation vectors (Rodrigues' formula).

    ``R = I + sin(t)/t [w]x + (1 - cos(t))/t^2 [w]x^2`` with ``t = |w|``; Taylor
    series for ``t < 1e-4``, so the result is accurate to float64 resolution
    for every angle.

    Args:
        rotvec: (..., 3) rotation vectors, radians.

    Returns:
        (..., 3, 3) float64 rotation matrices.
    """
    w = _as_float_array(rotvec, "rotvec", (3,))
    theta2 = np.einsum("...i,...i->...", w, w)
    theta = np.sqrt(theta2)
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    half_sin = np.sin(0.5 * safe)
    a = np.where(small, 1.0 - theta2 / 6.0 + theta2**2 / 120.0, np.sin(safe) / safe)
    # 1 - cos(t) = 2 sin^2(t/2), free of cancellation.
    b = np.where(small, 0.5 - theta2 / 24.0 + theta2**2 / 720.0, 2.0 * half_sin**2 / safe**2)
    k = skew(w)
    eye = np.broadcast_to(np.eye(3), k.shape)
    result: FloatArray = eye + a[..., None, None] * k + b[..., None, None] * (k @ k)
    return result


def matrix_to_quat_xyzw(matrix: npt.ArrayLike) -> FloatArray:
    """Unit quaternions ``(x, y, z, w)`` from rotation matrices (Shepperd's method).

    The sign is chosen so that ``w >= 0``. The input should be a rotation
    matrix; a slightly non-orthonormal one gives the quaternion of a nearby
    rotation (the result is normalised).

    Args:
        matrix: (..., 3, 3) rotation matrices.

    Returns:
        (..., 4) float64 unit quaternions, ``w >= 0``.
    """
    m = _as_float_array(matrix, "matrix", (3, 3))
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    # Four candidate forms, each well conditioned when its pivot is largest.
    cand = np.stack(
        [
            np.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 1, 0] - m[..., 0, 1],
                    1.0 + trace,
                ],
                axis=-1,
            ),
            np.stack(
                [
                    1.0 + m00 - m11 - m22,
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 2, 1] - m[..., 1, 2],
                ],
                axis=-1,
            ),
            np.stack(
                [
                    m[..., 0, 1] + m[..., 1, 0],
                    1.0 - m00 + m11 - m22,
                    m[..., 1, 2] + m[..., 2, 1],
                    m[..., 0, 2] - m[..., 2, 0],
                ],
                axis=-1,
            ),
            np.stack(
                [
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1.0 - m00 - m11 + m22,
                    m[..., 1, 0] - m[..., 0, 1],
                ],
                axis=-1,
            ),
        ],
        axis=-2,
    )  # (..., 4, 4): candidate, component
    pivots = np.stack([trace, m00, m11, m22], axis=-1)
    choice = np.argmax(pivots, axis=-1)
    q = np.take_along_axis(cand, choice[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    result: FloatArray = np.where(q[..., 3:4] < 0.0, -q, q)
    return result


def quat_xyzw_to_matrix(quat: npt.ArrayLike) -> FloatArray:
    """Rotation matrices from quaternions ``(x, y, z, w)`` (ROS order).

    The quaternion is normalised first; a zero or non-finite quaternion raises.

    Args:
        quat: (..., 4) quaternions, any non-zero norm.

    Returns:
        (..., 3, 3) float64 rotation matrices.

    Raises:
        InvalidInputError: wrong shape, non-finite values or zero norm.
    """
    q = _as_float_array(quat, "quat", (4,))
    if not np.all(np.isfinite(q)):
        raise InvalidInputError(f"quat must be finite, got {q.tolist()}")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm < 1e-12):
        raise InvalidInputError(f"quat must have non-zero norm, got {q.tolist()}")
    q = q / norm
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty((*q.shape[:-1], 3, 3), dtype=np.float64)
    out[..., 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    out[..., 0, 1] = 2.0 * (x * y - z * w)
    out[..., 0, 2] = 2.0 * (x * z + y * w)
    out[..., 1, 0] = 2.0 * (x * y + z * w)
    out[..., 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    out[..., 1, 2] = 2.0 * (y * z - x * w)
    out[..., 2, 0] = 2.0 * (x * z - y * w)
    out[..., 2, 1] = 2.0 * (y * z + x * w)
    out[..., 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return out


def so3_log(matrix: npt.ArrayLike) -> FloatArray:
    """Rotation vectors from rotation matrices (inverse of :func:`so3_exp`).

    Goes through the quaternion, so it is accurate for every angle including
    near 0 and near pi. The returned angle lies in ``[0, pi]``.

    Args:
        matrix: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) float64 rotation vectors, radians.
    """
    q = matrix_to_quat_xyzw(matrix)
    v = q[..., :3]
    w = q[..., 3]
    nv = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(nv, w)
    tiny = nv < 1e-12
    # For a tiny vector part angle/|v| -> 2/w (w ~ 1 there).
    factor = np.where(tiny, 2.0 / np.where(tiny, w, 1.0), angle / np.where(tiny, 1.0, nv))
    result: FloatArray = v * factor[..., None]
    return result
