"""The colour legend drawn on ``owl/debug_image`` (bottom-left corner).

A bar with the dot colours of r/|t| (red near at 0.5 s, blue far at 20 s, log scale, the
same look-up as the dots), labelled, and a magenta dot with "moving". Drawn with a few
OpenCV calls (no loop over pixels); skipped on images too small to hold it.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

__all__ = ["FAR_S", "NEAR_S", "draw_legend", "ros_colours"]

#: the r/|t| range of the dot colours, s (clipped outside).
NEAR_S, FAR_S = 0.5, 20.0
#: bar size, px.
BAR_W, BAR_H = 96, 8


def ros_colours(ros: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    """(N,) r/|t| (s) -> (N, 3) BGR dot colours: JET, red at NEAR_S, blue at FAR_S (log)."""
    r = np.clip(np.asarray(ros, dtype=np.float64), NEAR_S, FAR_S)
    level = np.log(r / NEAR_S) / math.log(FAR_S / NEAR_S)  # 0 near .. 1 far
    grey = np.round(255 * (1.0 - level)).astype(np.uint8).reshape(-1, 1)
    return cv2.applyColorMap(grey, cv2.COLORMAP_JET).reshape(-1, 3)


def draw_legend(img: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """Draw the legend into the (H, W, 3) BGR ``img`` in place and return it."""
    h, w = img.shape[:2]
    if w < BAR_W + 120 or h < 40:
        return img
    x0, y0 = 6, h - 6 - BAR_H
    cv2.rectangle(img, (x0 - 4, y0 - 18), (x0 + BAR_W + 112, h - 2), (0, 0, 0), -1)
    ros = NEAR_S * (FAR_S / NEAR_S) ** (np.arange(BAR_W) / (BAR_W - 1))
    img[y0 : y0 + BAR_H, x0 : x0 + BAR_W] = ros_colours(ros)[None, :, :]
    font, white = cv2.FONT_HERSHEY_PLAIN, (255, 255, 255)
    cv2.putText(img, f"r/|t| {NEAR_S:g}..{FAR_S:g} s (log)", (x0, y0 - 5), font, 0.8, white)
    cx = x0 + BAR_W + 12
    cv2.circle(img, (cx, y0 + BAR_H // 2), 3, (255, 0, 255), -1)
    cv2.putText(img, "moving", (cx + 7, y0 + BAR_H), font, 0.8, white)
    return img
