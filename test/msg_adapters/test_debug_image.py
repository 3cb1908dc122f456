"""msg_adapters.debug_image: the owl/debug_image picture and the key to its colours."""

from __future__ import annotations

import dataclasses

import numpy as np

from msg_adapters.debug_image import (
    BAR_H,
    BAR_W,
    FAR_S,
    NEAR_S,
    draw_debug,
    draw_legend,
    range_colours,
)
from owl_core.camera import CameraModel
from owl_core.types import FrameResult, PointFlag


def test_legend_bar_shows_the_dot_colours_from_near_to_far() -> None:
    img = np.full((240, 320, 3), 128, dtype=np.uint8)
    draw_legend(img)
    y = 240 - 6 - BAR_H // 2
    bar = img[y, 6 : 6 + BAR_W]
    np.testing.assert_array_equal(bar[0], range_colours([NEAR_S])[0])  # red end
    np.testing.assert_array_equal(bar[-1], range_colours([FAR_S])[0])  # blue end
    assert tuple(bar[0]) == (0, 0, 128) and bar[-1][0] > 100 and bar[-1][2] == 0  # BGR
    assert (img[y, 6 + BAR_W + 12] == (255, 0, 255)).all()  # the "moving" dot
    # text was written (white pixels above the bar); the rest of the image untouched
    assert (img[200:226, 6:200] == 255).all(axis=2).sum() > 50
    assert (img[:180] == 128).all()
    small = np.full((30, 100, 3), 7, dtype=np.uint8)
    assert (draw_legend(small) == 7).all()  # too small for a legend: left alone


def _result(pixels: np.ndarray, range_over_speed: np.ndarray, flags: np.ndarray) -> FrameResult:
    n = pixels.shape[0]
    return FrameResult(
        stamp_ns=0,
        pixels=pixels,
        bearings=np.tile([0.0, 0.0, 1.0], (n, 1)),
        looming=np.zeros(n),
        omega=np.zeros((n, 3)),
        rot=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        range_over_speed=range_over_speed,
        points=np.zeros((n, 3)),
        quality=np.ones(n),
        ids=np.arange(n, dtype=np.uint32),
        flags=flags,
        heading=np.array([0.0, 0.0, 1.0]),
        heading_sigma_rad=0.01,
        gyro_bias=np.zeros(3),
    )


def test_draw_debug_dots_coloured_by_range_moving_magenta_heading_green() -> None:
    k = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    camera = CameraModel(320, 240, k, np.zeros(5), "plumb_bob")
    grey = np.full((240, 320), 90, dtype=np.uint8)
    pixels = np.array([[40.0, 40.0], [280.0, 40.0], [100.0, 60.0]])
    moving = np.uint8(PointFlag.MOVING)
    result = _result(pixels, np.array([0.5, 20.0, 3.0]), np.array([0, 0, moving], np.uint8))
    picture = draw_debug(grey, result, camera)
    assert picture.shape == (240, 320, 3) and picture.dtype == np.uint8
    colours = range_colours([0.5, 20.0])
    # a 5x5 dot in the point's colour, centred on its pixel
    assert (picture[38:43, 38:43] == colours[0]).all()
    assert (picture[38:43, 278:283] == colours[1]).all()
    # a moving point: magenta with a white centre
    assert tuple(picture[60, 100]) == (255, 255, 255)
    assert tuple(picture[58, 98]) == (255, 0, 255)
    # the heading (0, 0, 1) lies at the principal point: a green cross there
    assert tuple(picture[120, 160]) == (0, 255, 0)
    assert (picture[5:30, 150:170] == 90).all()  # the rest is the grey image
    grey_only = draw_debug(grey, result, None)  # no camera: no heading drawn
    assert tuple(grey_only[120, 160]) == (90, 90, 90)


def test_heading_outside_the_picture_is_not_drawn() -> None:
    """A heading in front of the camera but nearly at 90 deg projects far outside the image
    (beyond int32 for a distortion-free camera): nothing is drawn and nothing raises."""
    k = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    camera = CameraModel(320, 240, k, np.zeros(0), "none")  # no validity limit
    grey = np.full((240, 320), 90, dtype=np.uint8)
    result = _result(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.uint8))
    for heading in ([1.0, 0.0, 1e-9], [0.0, -1.0, 1e-3], [1.0, 0.0, 0.6]):
        h = np.array(heading) / np.linalg.norm(heading)
        picture = draw_debug(grey, dataclasses.replace(result, heading=h), camera)
        assert (picture[:180] == 90).all()  # only the legend was drawn
