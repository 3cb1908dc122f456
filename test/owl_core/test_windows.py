"""owl_core.windows: fit windows in seconds."""

from __future__ import annotations

import numpy as np
import pytest

from owl_core.errors import InvalidInputError
from owl_core.windows import fit_columns


@pytest.mark.parametrize(("rate", "expected"), [(10, 3), (20, 4), (26, 4), (30, 5), (60, 10)])
def test_a_015_s_window_at_each_camera_rate(rate, expected):
    now = 10**12
    stamps = now - np.round(np.arange(12) * 1e9 / rate).astype(np.int64)
    assert fit_columns(stamps, now, 0.15, 3, 10) == expected


def test_missing_history_and_bad_arguments():
    now = 10**12
    stamps = np.array([now, now - 33_333_333, -1, -1, -1])
    assert fit_columns(stamps, now, 0.15, 3, 10) == 2  # only two frames exist
    assert fit_columns(np.array([-1, -1]), now, 0.15, 3, 10) == 0
    with pytest.raises(InvalidInputError):
        fit_columns(stamps, now, 0.0, 3, 10)
    with pytest.raises(InvalidInputError):
        fit_columns(stamps, now, 0.1, 5, 3)
