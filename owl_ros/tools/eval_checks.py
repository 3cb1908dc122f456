"""What ``owl_eval`` refuses to score, each as one line (:class:`~owl_ros.tools.errors.EvalError`).

A score that looks like a result but is not one is worse than an error:

- an explicitly named points or heading topic that is not in the result bag;
- a points topic named with ``--points-topic`` that has 0 points on every frame (nothing
  to score: ``owl_process`` says why frames were empty; the default topic gets a note,
  since a still camera has headings and a bias to score but no points);
- a result of another bag: no result frame stamp is a truth frame stamp, or the result's
  pixels lie outside the truth images (another image size);
- a gyro-bias error for a run without IMU (the estimate never moved from its start value):
  not scored, and said in a note.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = ["check_against_truth", "check_named_topics", "check_points", "imu_was_used"]


def check_named_topics(
    path: str | Path, topics: Iterable[str], points_topic: str | None, heading_topic: str | None
) -> str | None:
    """One line when a topic named on the command line is not in the result bag."""
    have = set(topics)
    for role, name in (("points", points_topic), ("heading", heading_topic)):
        if name is not None and name not in have:
            return (
                f"{role} topic {name} is not in result bag {path} "
                f"(has: {', '.join(sorted(have)) or 'none'})"
            )
    return None


def check_points(path: str | Path, topic: str | None, sizes: Sequence[int]) -> str | None:
    """One line when the points topic holds frames but no point on any of them."""
    if topic is None or not sizes or any(sizes):
        return None
    return (
        f"points topic {topic} in {path} has 0 points on every frame ({len(sizes)} frames): "
        "nothing to score (owl_process's summary says why frames were empty)"
    )


def imu_was_used(records: Iterable[Mapping[str, str]]) -> bool | None:
    """From the values of the result's ``owl: input`` statuses: whether any IMU sample
    arrived (``imu_total`` > 0); None when the result bag does not say."""
    totals = []
    for values in records:
        try:
            totals.append(int(float(values["imu_total"])))
        except (KeyError, ValueError):
            continue
    return None if not totals else max(totals) > 0


def check_against_truth(
    result_path: str | Path,
    truth_path: str | Path,
    result_stamps: Sequence[int],
    truth_stamps: Sequence[int],
    max_pixel: tuple[float, float] | None,
    truth_size: tuple[int, int] | None,
) -> str | None:
    """One line when the result cannot be of the truth bag's recording.

    Args:
        result_stamps, truth_stamps: image stamps (ns) of the result and truth frames.
        max_pixel: largest (u, v) of the result's points, or None (no points).
        truth_size: (width, height) of the truth images, px.
    """
    if result_stamps and truth_stamps:
        common = np.intersect1d(np.asarray(result_stamps), np.asarray(truth_stamps)).size
        if common == 0:
            return (
                f"no frame of result {result_path} has the stamp of a frame of truth "
                f"{truth_path} (result {_span(result_stamps)}, truth {_span(truth_stamps)}): "
                "a result of another bag"
            )
    if max_pixel is not None and truth_size is not None:
        u, v = max_pixel
        w, h = truth_size
        if u >= w or v >= h:
            return (
                f"result {result_path} has points at pixel ({u:.0f}, {v:.0f}), outside the "
                f"{w}x{h} images of truth {truth_path}: a result of another image size"
            )
    return None


def _span(stamps: Sequence[int]) -> str:
    return f"{len(stamps)} frames {min(stamps) * 1e-9:.3f}..{max(stamps) * 1e-9:.3f} s"
