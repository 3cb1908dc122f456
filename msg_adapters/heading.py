"""Heading (unit translation direction, camera optical frame) <-> geometry_msgs messages.

- ``owl/heading``: geometry_msgs/Vector3Stamped, the unit direction.
- ``owl/heading_with_covariance``: geometry_msgs/TwistWithCovarianceStamped, the unit
  direction in ``twist.linear`` (dimensionless: the velocity per unit speed) and its
  uncertainty in the linear 3x3 block of the covariance, ``sigma^2 (I - h h^T)`` (an
  isotropic angular error of ``sigma`` rad about the heading: no variance along it, since
  the vector has unit length). ``twist.angular`` is not estimated: zero, with variances
  ``NOT_ESTIMATED_VARIANCE``. Why this type: it is the standard message for a 3-vector
  with a covariance that robot_localization, Foxglove and RViz read; Vector3Stamped has
  no covariance, and a pose would claim an orientation that the heading does not give.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from geometry_msgs.msg import Vector3Stamped

from msg_adapters.errors import FieldError


def heading_to_msg(heading: npt.ArrayLike, header: Any) -> Any:
    """(3,) finite heading -> Vector3Stamped with the given header (frame = camera optical).

    The vector is written as given (the engine publishes a unit vector); a zero or
    non-finite vector is an error, since it would carry no direction.
    """
    vec = np.asarray(heading, dtype=np.float64)
    if vec.shape != (3,):
        raise FieldError(f"heading must have shape (3,), got {vec.shape}")
    if not np.isfinite(vec).all() or not np.any(vec):
        raise FieldError(f"heading must be finite and non-zero, got {vec.tolist()}")
    msg = Vector3Stamped(header=header)
    msg.vector.x, msg.vector.y, msg.vector.z = (float(v) for v in vec)
    return msg


#: variance written for the twist's angular part, which OWL does not estimate, (rad/s)^2.
NOT_ESTIMATED_VARIANCE = 1e6


def heading_covariance(heading: npt.ArrayLike, sigma_rad: float) -> npt.NDArray[np.float64]:
    """(3, 3) covariance of a unit heading with an isotropic angular 1-sigma ``sigma_rad``:
    ``sigma^2 (I - h h^T)`` (h normalised)."""
    h = np.asarray(heading, dtype=np.float64)
    h = h / np.linalg.norm(h)
    return float(sigma_rad) ** 2 * (np.eye(3) - np.outer(h, h))


def heading_to_twist_covariance(heading: npt.ArrayLike, sigma_rad: float, header: Any) -> Any:
    """(3,) heading and its 1-sigma angular uncertainty (rad) -> TwistWithCovarianceStamped
    (see the module docstring). A non-finite sigma is an error."""
    from geometry_msgs.msg import TwistWithCovarianceStamped

    base = heading_to_msg(heading, header)  # checks the vector
    if not np.isfinite(sigma_rad) or sigma_rad < 0:
        raise FieldError(f"heading sigma must be finite and >= 0 rad, got {sigma_rad}")
    msg = TwistWithCovarianceStamped(header=header)
    msg.twist.twist.linear = base.vector
    cov = np.zeros((6, 6))
    cov[:3, :3] = heading_covariance(heading, sigma_rad)
    cov[3:, 3:] = np.eye(3) * NOT_ESTIMATED_VARIANCE
    msg.twist.covariance = cov.ravel().tolist()
    return msg


def msg_to_heading(msg: Any) -> npt.NDArray[np.float64]:
    """Vector3Stamped -> (3,) float64 heading, exactly as stored."""
    return np.array([msg.vector.x, msg.vector.y, msg.vector.z], dtype=np.float64)
