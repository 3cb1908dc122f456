"""The parameters that ``launch/owl.launch.py`` builds from its arguments (testable without
``launch``): the camera-IMU rotation and the IMU time offset, each set only when given, so
that an unset argument leaves the parameter file's value (or TF) in charge."""

from __future__ import annotations

from typing import Any

__all__ = ["node_parameters"]


def _floats(name: str, text: str, count: int) -> list[float]:
    items = [v for v in text.strip().strip("[]").replace(",", " ").split() if v]
    try:
        values = [float(v) for v in items]
    except ValueError:
        raise ValueError(
            f"launch argument {name}: expected {count} numbers, got {text!r}"
        ) from None
    if len(values) != count:
        raise ValueError(f"launch argument {name}: expected {count} numbers, got {text!r}")
    return values


def node_parameters(rotation_xyzw: str, imu_time_offset: str) -> dict[str, Any]:
    """Launch-argument texts -> parameter overrides of node ``owl`` ({} when both unset).

    Args:
        rotation_xyzw: ``"x,y,z,w"`` or ``"[x, y, z, w]"`` or "" (not given).
        imu_time_offset: seconds as text, or "" (not given).

    Raises:
        ValueError: a text that is not the right count of numbers (names the argument).
    """
    out: dict[str, Any] = {}
    if rotation_xyzw.strip():
        out["camera_to_imu_rotation_xyzw"] = _floats(
            "camera_to_imu_rotation_xyzw", rotation_xyzw, 4
        )
    if imu_time_offset.strip():
        out["imu_time_offset"] = _floats("imu_time_offset", imu_time_offset, 1)[0]
    return out
