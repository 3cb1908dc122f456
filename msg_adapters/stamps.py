"""builtin_interfaces/Time <-> integer nanoseconds, in one place.

ROS time is ``sec`` (int32, may be negative) plus ``nanosec`` (uint32, always in
[0, 1e9)); the integer-nanosecond form is ``sec * 1e9 + nanosec`` exactly (no floats).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from builtin_interfaces.msg import Time
from std_msgs.msg import Header

from msg_adapters.errors import FieldError

NS_PER_S = 1_000_000_000
_INT32_MIN = -(2**31)
_INT32_MAX = 2**31 - 1


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (or anything with ``sec``/``nanosec``) -> int nanoseconds."""
    sec = int(stamp.sec)
    nanosec = int(stamp.nanosec)
    if not 0 <= nanosec < NS_PER_S:
        raise FieldError(f"stamp.nanosec must be in [0, 1e9), got {nanosec}")
    return sec * NS_PER_S + nanosec


def ns_to_stamp(ns: int) -> Any:
    """int nanoseconds -> builtin_interfaces/Time (floor division: nanosec is never negative)."""
    sec, nanosec = divmod(int(ns), NS_PER_S)
    if not _INT32_MIN <= sec <= _INT32_MAX:
        raise FieldError(f"stamp {ns} ns does not fit builtin_interfaces/Time (int32 seconds)")
    return Time(sec=sec, nanosec=nanosec)


def stamps_to_ns(secs: npt.ArrayLike, nanosecs: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """Vectorised: (N,) seconds and (N,) nanoseconds -> (N,) int64 nanoseconds."""
    sec = np.asarray(secs, dtype=np.int64)
    nsec = np.asarray(nanosecs, dtype=np.int64)
    bad = (nsec < 0) | (nsec >= NS_PER_S)
    if bad.any():
        raise FieldError(f"stamp.nanosec must be in [0, 1e9), got {int(nsec[bad][0])}")
    return sec * NS_PER_S + nsec


def make_header(stamp_ns: int, frame_id: str) -> Any:
    """std_msgs/Header with the given stamp (int ns) and frame_id."""
    return Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


def header_to_ns(header: Any) -> int:
    """The stamp of a std_msgs/Header in int nanoseconds."""
    return stamp_to_ns(header.stamp)
