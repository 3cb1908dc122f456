"""The ``owl/debug_image`` picture: a FrameResult drawn over the grey image it came from.

:func:`draw_debug` colours each point by r/|t| and marks the heading; :func:`draw_legend`
adds the key in the bottom-left corner: a bar with the dot colours of r/|t| (red near at
0.5 s, blue far at 20 s, log scale, the same look-up as the dots), labelled, and a
magenta dot with "moving". Drawn with a few OpenCV calls (no loop over pixels or points);
the legend is skipped on images too small to hold it.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

from owl_core.camera import CameraModel
from owl_core.types import FrameResult, PointFlag

__all__ = ["FAR_S", "NEAR_S", "draw_debug", "draw_legend", "range_colours"]

#: the r/|t| range of the dot colours, s (clipped outside).
NEAR_S, FAR_S = 0.5, 20.0
#: bar size, px.
BAR_W, BAR_H = 96, 8


def range_colours(range_over_speed: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    """(N,) r/|t| (s) -> (N, 3) BGR dot colours: JET, red at NEAR_S, blue at FAR_S (log)."""
    r = np.clip(np.asarray(range_over_speed, dtype=np.float64), NEAR_S, FAR_S)
    level = np.log(r / NEAR_S) / math.log(FAR_S / NEAR_S)  # 0 near .. 1 far
    grey = np.round(255 * (1.0 - level)).astype(np.uint8).reshape(-1, 1)
    return np.asarray(cv2.applyColorMap(grey, cv2.COLORMAP_JET), np.uint8).reshape(-1, 3)


def draw_legend(img: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """Draw the legend into the (H, W, 3) BGR ``img`` in place and return it."""
    h, w = img.shape[:2]
    if w < BAR_W + 120 or h < 40:
        return img
    x0, y0 = 6, h - 6 - BAR_H
    cv2.rectangle(img, (x0 - 4, y0 - 18), (x0 + BAR_W + 112, h - 2), (0, 0, 0), -1)
    bar = NEAR_S * (FAR_S / NEAR_S) ** (np.arange(BAR_W) / (BAR_W - 1))
    img[y0 : y0 + BAR_H, x0 : x0 + BAR_W] = range_colours(bar)[None, :, :]
    font, white = cv2.FONT_HERSHEY_PLAIN, (255, 255, 255)
    cv2.putText(img, f"r/|t| {NEAR_S:g}..{FAR_S:g} s (log)", (x0, y0 - 5), font, 0.8, white)
    cx = x0 + BAR_W + 12
    cv2.circle(img, (cx, y0 + BAR_H // 2), 3, (255, 0, 255), -1)
    cv2.putText(img, "moving", (cx + 7, y0 + BAR_H), font, 0.8, white)
    return img


def draw_debug(
    grey: npt.NDArray[np.uint8], result: FrameResult, camera: CameraModel | None
) -> npt.NDArray[np.uint8]:
    """The owl/debug_image picture: (H, W, 3) uint8 BGR.

    Each point is a 5x5 dot coloured by r/|t| (red near, blue far, on a log scale between
    0.5 and 20 s); suspected moving points are magenta with a white centre; the heading
    (focus of expansion) is a green cross in a circle when it lies in front of the camera
    and inside the picture; a colour legend sits in the bottom-left corner. Drawing is
    vectorised (no loop over points).

    Args:
        grey: (H, W) uint8 image the engine tracked on.
        result: that frame's FrameResult.
        camera: the camera model (to place the heading), or None (no heading drawn).
    """
    img = np.asarray(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), np.uint8)
    h, w = grey.shape
    if result.num_points:
        lut = range_colours(result.range_over_speed)
        moving = (result.flags & np.uint8(PointFlag.MOVING)) != 0
        lut[moving] = (255, 0, 255)
        uv = np.rint(result.pixels).astype(np.int64)
        offs = np.arange(-2, 3)
        du, dv = np.meshgrid(offs, offs)
        us = np.clip(uv[:, 0, None] + du.reshape(1, -1), 0, w - 1)
        vs = np.clip(uv[:, 1, None] + dv.reshape(1, -1), 0, h - 1)
        img[vs, us] = lut[:, None, :]
        img[np.clip(uv[moving, 1], 0, h - 1), np.clip(uv[moving, 0], 0, w - 1)] = (255, 255, 255)
    if result.heading is not None and camera is not None and result.heading[2] > 0:
        foe = camera.bearing_to_pixel(np.asarray(result.heading, dtype=np.float64)[None])[0]
        # only where the picture shows it (a heading near 90 deg off the axis projects
        # beyond what cv2 can draw: its coordinates overflow int32)
        if np.all(np.isfinite(foe)) and 0 <= foe[0] < w and 0 <= foe[1] < h:
            c = (round(float(foe[0])), round(float(foe[1])))
            size = max(6, min(h, w) // 20)
            cv2.circle(img, c, size, (0, 255, 0), 2)
            cv2.drawMarker(img, c, (0, 255, 0), cv2.MARKER_CROSS, 2 * size, 2)
    return draw_legend(img)
