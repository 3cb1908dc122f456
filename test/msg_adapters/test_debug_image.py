"""owl_ros.debug_legend: the debug image carries the key to its colours."""

from __future__ import annotations

import numpy as np

from owl_ros.debug_legend import BAR_H, BAR_W, FAR_S, NEAR_S, draw_legend, ros_colours


def test_legend_bar_shows_the_dot_colours_from_near_to_far() -> None:
    img = np.full((240, 320, 3), 128, dtype=np.uint8)
    draw_legend(img)
    y = 240 - 6 - BAR_H // 2
    bar = img[y, 6 : 6 + BAR_W]
    np.testing.assert_array_equal(bar[0], ros_colours([NEAR_S])[0])  # red end
    np.testing.assert_array_equal(bar[-1], ros_colours([FAR_S])[0])  # blue end
    assert tuple(bar[0]) == (0, 0, 128) and bar[-1][0] > 100 and bar[-1][2] == 0  # BGR
    assert (img[y, 6 + BAR_W + 12] == (255, 0, 255)).all()  # the "moving" dot
    # text was written (white pixels above the bar); the rest of the image untouched
    assert (img[200:226, 6:200] == 255).all(axis=2).sum() > 50
    assert (img[:180] == 128).all()
    small = np.full((30, 100, 3), 7, dtype=np.uint8)
    assert (draw_legend(small) == 7).all()  # too small for a legend: left alone
