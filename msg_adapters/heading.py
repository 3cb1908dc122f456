"""Heading (unit translation direction, camera optical frame) <-> geometry_msgs/Vector3Stamped."""

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


def msg_to_heading(msg: Any) -> npt.NDArray[np.float64]:
    """Vector3Stamped -> (3,) float64 heading, exactly as stored."""
    return np.array([msg.vector.x, msg.vector.y, msg.vector.z], dtype=np.float64)
