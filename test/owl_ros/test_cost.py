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
    assert cost.image_size("640x480") == (640, 480)
    with pytest.raises(argparse.ArgumentTypeError, match="WxH"):
        cost.image_size("640")


def test_median_rows_per_setting_and_stage() -> None:
    def row(total: float, tracked: float) -> dict:
        ms = dict.fromkeys(cost.STAGES, 1.0) | {"total": total}
        return {"size": "64x48", "features": 10, "tracked_per_frame": tracked, "ms_per_frame": ms}

    runs = [[row(30.0, 9), row(5.0, 1)], [row(10.0, 7), row(6.0, 3)], [row(20.0, 8), row(4.0, 2)]]
    med = cost.median_rows(runs)
    assert [r["ms_per_frame"]["total"] for r in med] == [20.0, 5.0]
    assert [r["tracked_per_frame"] for r in med] == [8.0, 2.0]
    assert med[0]["runs"] == 3 and med[0]["ms_per_frame"]["lk"] == 1.0
