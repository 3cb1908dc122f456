"""Fit windows in seconds, not frames: which track-history columns a fit uses.

A fixed number of frames spans 0.4 s at 10 Hz and 0.07 s at 60 Hz; the motion over a
window (and the lag of a straight-line fit, half the window) then depends on the camera
rate. :func:`fit_columns` picks the columns of the track history within ``window_s`` of
the current image instead, between a floor and a ceiling of frames.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from owl_core.errors import InvalidInputError

__all__ = ["fit_columns"]


def fit_columns(
    stamps_ns: npt.ArrayLike,
    stamp_ns: int,
    window_s: float,
    min_frames: int,
    max_frames: int,
    tolerance_s: float = 1e-3,
) -> int:
    """Number of leading history columns whose frames lie within ``window_s`` of now.

    Args:
        stamps_ns: (W,) int64 frame stamps of the history, column 0 = the current frame,
            negative = no frame.
        stamp_ns: the current stamp, ns.
        window_s: the window, s (> 0); a frame ``window_s + tolerance_s`` or more before
            now is outside.
        min_frames: at least this many columns (>= 2) when the history has them.
        max_frames: at most this many columns (>= min_frames).
        tolerance_s: slack for stamp jitter, s.

    Returns:
        The column count k (columns 0..k-1 are used), <= the valid columns available.
    """
    s = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    if not (math.isfinite(window_s) and window_s > 0):
        raise InvalidInputError(f"window_s must be positive, got {window_s!r}")
    if min_frames < 2 or max_frames < min_frames:
        raise InvalidInputError(
            f"need 2 <= min_frames <= max_frames, got {min_frames}, {max_frames}"
        )
    valid = s >= 0
    # the valid prefix (a reset leaves -1 behind the newest frames)
    n_valid = int(np.argmin(valid)) if not valid.all() else s.size
    age = (int(stamp_ns) - s[:n_valid]) * 1e-9
    inside = int(np.count_nonzero(age <= window_s + tolerance_s))
    return int(min(max(inside, min_frames), max_frames, n_valid)) if n_valid else 0
