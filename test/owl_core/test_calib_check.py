"""owl_core.calib_check: which judge decides (the end-to-end cases are in test_process)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from owl_core.calib_check import CalibrationMonitor, MonitorOptions
from owl_core.camera import CameraModel
from owl_core.errors import InvalidInputError
from owl_core.time_offset import OnlineCalibration
from owl_core.types import GyroSamples

GYRO = GyroSamples(np.array([0, 10**9], dtype=np.int64), np.zeros((2, 3)))


def _online(
    updates: int,
    rejected: int,
    phi_deg: tuple[float, ...] = (0, 0, 0),
    phi_sigma_deg: tuple[float, ...] = (0.05, 0.05, 0.05),
    offset: float = 0.0,
    offset_sigma: float = 0.0005,
) -> OnlineCalibration:
    return OnlineCalibration(
        offset,
        offset_sigma,
        np.radians(phi_deg),
        np.diag(np.radians(phi_sigma_deg) ** 2),
        updates,
        rejected,
    )


def _monitor() -> CalibrationMonitor:
    camera = CameraModel.pinhole(320, 240, 250.0, 250.0, 159.5, 119.5)
    return CalibrationMonitor(camera, np.eye(3), 0.0, MonitorOptions(check_every=1))


def test_the_online_estimate_judges_while_its_gate_keeps_most_frames() -> None:
    mon = _monitor()
    assert mon.update(None, GYRO, online=_online(3, 0)) is None  # too few frames yet
    ok = mon.update(None, GYRO, online=_online(9, 1))
    assert ok is not None and ok.source == "online" and not ok.disagrees
    # 4 deg about camera x, determined: beyond the 3 deg threshold and its sigma
    off = mon.update(None, GYRO, online=_online(12, 1, (4.0, 0, 0)))
    assert off is not None and off.disagrees and off.angle_deg == pytest.approx(4.0)
    # 4 deg about an axis it does not determine (its prior, 5.7 deg): no claim
    free = mon.update(None, GYRO, online=_online(15, 1, (0, 4.0, 0), (0.05, 5.7, 0.05)))
    assert free is not None and not free.disagrees and free.angle_deg < 1e-9
    assert "not determined about camera axis [0.00, 1.00, 0.00]" in free.message
    # an offset 6 ms off with a 0.5 ms sigma; then the same with a 3 ms sigma: not judged
    late = mon.update(None, GYRO, online=_online(18, 1, offset=0.006))
    assert late is not None and late.disagrees and late.offset_sigma_s == 0.0005
    vague = mon.update(None, GYRO, online=_online(21, 1, offset=0.006, offset_sigma=0.003))
    assert vague is not None and not vague.disagrees and "not determined" in vague.message
    # since the last check the gate dropped 3 of 4: the window judges (it has no fits yet)
    assert mon.update(None, GYRO, online=_online(22, 4)) is None
    assert mon.last is vague
    # nothing offered since the last check (no translation): the window again
    assert mon.update(None, GYRO, online=_online(22, 4)) is None
    back = mon.update(None, GYRO, online=_online(25, 4))
    assert back is not None and back.source == "online"


def test_options_are_checked() -> None:
    with pytest.raises(InvalidInputError, match="filter_min_updates"):
        MonitorOptions(filter_min_updates=0)
    with pytest.raises(InvalidInputError, match="filter_angle_threshold_deg"):
        MonitorOptions(filter_angle_threshold_deg=math.nan)
