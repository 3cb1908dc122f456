"""owl_ros.tools.plots: the figures say what their colours and arrows mean, and nothing
covers what they show (checked on the matplotlib figure before it is saved)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import rgb_to_hsv

from owl_core.types import FrameResult
from owl_ros.tools import plots


def _result(n: int = 300, seed: int = 0, stamp: int = 0) -> FrameResult:
    rng = np.random.default_rng(seed)
    e = rng.normal(size=(n, 3)) * [0.3, 0.2, 0.0] + [0, 0, 1]
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    ros = rng.uniform(1.0, 8.0, n)
    t = np.array([0.0, 0.0, 1.0])
    lv, om = e @ t / ros, np.cross(e, t) / ros[:, None]
    return FrameResult(
        stamp_ns=stamp, pixels=160 + 400 * e[:, :2] / e[:, 2:], bearings=e, looming=lv,
        omega=om, rot=np.zeros((n, 4)), range_over_speed=ros, points=e * ros[:, None],
        quality=np.ones(n), ids=np.arange(n, dtype=np.uint32), flags=np.zeros(n, np.uint8),
        heading=t, heading_sigma_rad=0.01, gyro_bias=np.zeros(3),
    )  # fmt: skip


@pytest.fixture
def figures(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The figures the plot functions build, kept open instead of saved (on an Agg canvas:
    plots builds pyplot-free Figures, whose base canvas has no renderer)."""
    kept: list[Any] = []

    def keep(fig: Any, path: Any) -> Any:
        FigureCanvasAgg(fig)
        kept.append(fig)
        return path

    monkeypatch.setattr(plots, "_save", keep)
    return kept


def _colorbar_labels(fig: Any) -> list[str]:
    return [ax.get_ylabel() for ax in fig.axes if ax.get_label() == "<colorbar>"]


def test_colour_bars_say_their_scale_and_arrows_have_a_key(figures, tmp_path) -> None:
    res = _result()
    plots.scaled_cloud(res, tmp_path / "c.png")
    plots.fields(np.zeros((240, 320), np.uint8), res, tmp_path / "f.png")
    cloud, fields = figures
    # every L here is >= 0: the square-root scale, and the bar says so
    assert _colorbar_labels(cloud) == ["looming L (1/s) (square-root colour scale)"]
    assert _colorbar_labels(fields) == [
        "L (1/s) (square-root colour scale)",
        "|omega| (1/s) (linear colour scale)",
    ]
    keys = [a for a in fields.axes[1].get_children() if type(a).__name__ == "QuiverKey"]
    assert len(keys) == 1 and "1/s" in keys[0].text.get_text()


def test_top_view_legend_leaves_the_camera_marker_visible(figures, tmp_path) -> None:
    res = _result()
    res.points[:, 0] = -np.abs(res.points[:, 0])  # all left of the camera: it is bottom right
    plots.scaled_cloud(res, tmp_path / "c.png")
    (fig,) = figures
    fig.canvas.draw()
    top = fig.axes[1]
    legend = top.get_legend().get_window_extent()
    cam = top.transData.transform((0.0, 0.0))
    assert not legend.contains(*cam)


def test_shape_constancy_titles_readable_and_panels_apart(figures, tmp_path) -> None:
    results = [_result(seed=i, stamp=i) for i in range(3)]
    sel = [np.ones(r.num_points, bool) for r in results]
    images = [np.zeros((240, 320), np.uint8)] * 3
    plots.shape_constancy(results, sel, [0.0, 0.5, 1.0], images, tmp_path / "s.png")
    (fig,) = figures
    fig.canvas.draw()
    titles = [ax.title for ax in fig.axes[:3]]
    # no light-yellow title: not both bright and saturated
    for t in titles:
        _, s, v = rgb_to_hsv(np.asarray(t.get_color())[:3])
        assert v < 0.9 or s < 0.3, t.get_color()
    raw, moved, front = fig.axes[3:6]
    renderer = fig.canvas.get_renderer()
    # the right panel's y label lies right of the middle panel
    assert front.yaxis.label.get_window_extent(renderer).x0 > moved.get_window_extent().x1
    assert moved.yaxis.label.get_window_extent(renderer).x0 > raw.get_window_extent().x1
