"""owl_ros.tools.cost: one small measurement and the plot (CPU time per stage is measured)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from owl_ros.tools import cost


def test_measure_and_plot(tmp_path: Path) -> None:
    row = cost.measure("street", 160, 120, 100, 0.4, None)
    assert row["size"] == "160x120" and row["frames"] >= 12
    assert 0 < row["tracked_per_frame"] <= 100
    ms = row["ms_per_frame"]
    assert set(ms) == set(cost.STAGES)
    assert all(v >= 0 for v in ms.values())
    # the stages are parts of the total, the tracker's two parts are parts of "track"
    assert ms["track"] + ms["integrate"] + ms["heading"] + ms["looming"] <= ms["total"] * 1.001
    assert ms["lk"] + ms["detect"] <= ms["track"] * 1.001
    out = tmp_path / "cost.png"
    cost.plot([row], [dict(row)], out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_size_argument() -> None:
    assert cost._size("640x480") == (640, 480)
    with pytest.raises(argparse.ArgumentTypeError, match="WxH"):
        cost._size("640")
