"""Feature tracker: grid-bucketed corners, pyramidal Lucas-Kanade, persistent ids.

Every frame the tracker

1. tracks the live features from the previous image into the new one with
   Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``), starting from the positions given by
   the optional ``predict`` callable (e.g. the gyro-predicted rotation; fast rotations
   are then tracked even beyond the pyramid's reach) plus each track's translational
   displacement of the last frame (``lk_predict_velocity``; a new track takes its
   neighbours'): from such a start one pyramid level (``lk_predicted_levels``)
   converges; the points it does not serve are tracked with the full pyramid;
2. tracks the results back into the previous image (starting at the forward start,
   with ``lk_backward_levels`` pyramid levels: a consistent track needs no reach
   there) and drops features whose round trip misses the start by more than
   ``fb_threshold_px``
   (forward-backward check), whose window differs from the previous one by more
   than ``max_patch_error`` grey levels on average (occlusion, changed content:
   a wrong match can pass the round trip), that LK reports as failed, or that
   leave the image; of two features that converge to within
   ``merge_distance_px`` (e.g. while the camera backs away) the younger is dropped;
3. detects new corners (``cv2.goodFeaturesToTrack``, Shi-Tomasi) away from the
   surviving features (``min_distance_px``) whenever fewer than
   ``redetect_below * max_features`` remain, spread over a ``grid_cols x
   grid_rows`` grid so each cell gets about its share. With ``background_detection``
   this runs on a helper thread after :meth:`FeatureTracker.track` returns, and the
   corners join the tracks at the start of the next call (before the history shifts,
   so they are tracked from this image exactly as before): a new corner has one
   position, no flow, so nothing computed for this frame would have used it.

Bookkeeping (ids, ages, the history of the last ``history_len`` positions) is
vectorised numpy; there is no Python loop over features.

Pixel coordinates follow OpenCV: ``(u, v)``, centre of the top-left pixel at 0.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TypeVar

import cv2
import numpy as np
import numpy.typing as npt
from numpy.lib.stride_tricks import sliding_window_view
from scipy.spatial import cKDTree

from owl_core.errors import InvalidInputError, TimeError
from owl_core.motion import all_finite, row_norms
from owl_core.os_thread import name_os_thread

FloatArray = npt.NDArray[np.float64]
Predictor = Callable[[FloatArray], npt.ArrayLike]

__all__ = ["LOST_REASONS", "FeatureTracker", "TrackerOptions", "Tracks"]

#: Keys of :attr:`Tracks.lost_by_reason`.
LOST_REASONS = (
    "lk_failed",
    "fb_check",
    "patch_error",
    "left_image",
    "merged",
    "crowded",
    "reset",
)


@dataclass(frozen=True)
class TrackerOptions:
    """Tracker settings (all sizes in pixels of the input image).

    Attributes:
        max_features: number of features the tracker keeps alive (> 0).
        grid_cols: detection grid columns; each cell gets about
            ``max_features / (grid_cols * grid_rows)`` features.
        grid_rows: detection grid rows.
        min_distance_px: minimum distance between a new corner and any other
            feature, pixels.
        quality_level: Shi-Tomasi threshold relative to the strongest corner of
            the image, in (0, 1).
        block_size: Shi-Tomasi structure-tensor window, pixels (odd, >= 3).
        detect_level: pyramid level whose image the corner search runs on (0: the input
            image; 1: ``cv2.pyrDown`` of it, a quarter of the pixels, with the distances
            halved and the corners mapped back to the input's pixels), >= 0.
        border_px: features closer than this to the image border are not
            detected and are dropped when they get there, pixels.
        lk_window_px: Lucas-Kanade window side, pixels (odd, >= 5).
        lk_levels: pyramid levels above the full image (0 = no pyramid). The
            reach without a prediction is about ``lk_window_px / 2 * 2**lk_levels``.
        lk_predicted_levels: pyramid levels of the first forward pass of the points whose
            start includes their translational displacement (``lk_predict_velocity``, or
            the gyro's rotation alone without it). Points that fail a check (LK,
            forward-backward, patch), that this pass moved farther than
            ``lk_predicted_gate_px`` from their start, or without a translation
            prediction are tracked again with ``lk_levels`` from the gyro start.
            ``>= lk_levels`` tracks every point with the full pyramid in one pass. LK's
            cost is per point, level and iteration: from a start within a fraction of a
            pixel, one level converges in one or two iterations to within 0.004 px of
            the full pyramid's answer (97 % of the points on the street scenario;
            measured against exact reprojections the two have the same error
            distribution on the cube scenario), where the pyramid from the gyro start
            spends three coarse levels and more iterations (1000 features, 640x480:
            forward pass 1.8 against 10.5 ms). With the gyro's rotation alone a shallow
            pass can lock onto a wrong match where the translational flow is large.
        lk_predict_velocity: add to the gyro prediction each track's translational
            displacement of the previous frame (its flow minus the rotational part the
            gyro predicted then, scaled by the ratio of the frame intervals); a track
            without one (new) takes the median of its ``predict_neighbours`` nearest
            tracks' within ``predict_radius_px`` (at least three), else it has no
            translation prediction.
        lk_predicted_gate_px: a point that the shallow pass moved farther than this from its
            start is tracked again with the full pyramid, pixels (the prediction missed:
            the shallow pass may have converged to a wrong match).
        lk_shallow_max_miss: when more than this fraction of the predicted points failed
            or moved beyond the gate in a frame (speed or turn rate changing fast between
            frames: a car at 10 Hz), the next frame tracks every point with the full
            pyramid at once (the retries would cost more than they save); it returns to
            the shallow pass once the prediction holds again, in [0, 1].
        predict_neighbours: neighbours whose displacement a new track takes (>= 3; fewer:
            new tracks get no translation prediction), count.
        predict_radius_px: those neighbours lie within this distance, pixels.
        lk_deformation_correction: remove from each tracked position the first-order
            error that translation-only LK makes on a window whose content deforms
            between the frames (:func:`deformation_bias`; the flow gradient fitted to
            the ``deformation_neighbours`` nearest tracks' flows within
            ``deformation_radius_px``). Without it a track drifts off its scene point
            towards the window's gradient-weighted centroid as the surface looms.
        deformation_neighbours: tracks (besides the point itself) whose flows give a
            point's flow gradient (>= 5), count.
        deformation_radius_px: those tracks lie within this distance, pixels.
        deformation_max_px: a predicted error larger than this is not applied (the fit
            straddles a depth edge or a moving object), pixels.
        deformation_robust_px: the flow-gradient fit is redone once with Cauchy weights
            of this scale on the neighbours' misfits (0: plain least squares), pixels.
        lk_backward_levels: pyramid levels of the backward (forward-backward check)
            pass (capped at ``lk_levels``). It starts at the forward start, where a
            consistent track returns to within ``fb_threshold_px``, so it needs little
            reach (1000 features, 640x480: 0 levels 1.8 ms, 1 level 4.2 ms).
        lk_backward_window_px: window side of the backward pass, pixels (odd, >= 5; 0:
            ``lk_window_px``). The check asks for the round trip to within
            ``fb_threshold_px``, not for the forward pass's precision, and the pass's cost
            is per window pixel.
        lk_max_iterations: LK iterations per level.
        lk_epsilon_px: LK stops when an update is smaller than this, pixels.
        lk_min_eigenvalue: LK rejects points whose normalised minimum eigenvalue
            of the gradient matrix is below this (flat texture).
        fb_threshold_px: maximum forward-backward round-trip error, pixels.
        max_patch_error: maximum mean absolute grey-level difference between the
            LK windows in the two images (uint8 grey levels, 0..255).
        merge_distance_px: tracked features closer than this are duplicates; the
            younger one is dropped, pixels (0 disables; keep it below
            ``min_distance_px``).
        redetect_below: detect new corners when fewer than
            ``redetect_below * max_features`` features survive, in (0, 1].
        max_cell_share: a grid cell holding more than this many times its share
            (``max_features / (grid_cols * grid_rows)``) retires its youngest extra
            features (reason ``crowded``), so features that converge (receding
            camera) make room for new ones where the image emptied; 0 disables.
        history_len: number of positions kept per track (current one included, >= 2).
        background_detection: detect new corners on a helper thread, overlapping the
            caller's work on this frame; they appear in the next frame's tracks (the
            tracks of every later frame are the same as without it). For a live node
            with a second core; the CPU time is the same.
    """

    max_features: int = 1000
    grid_cols: int = 8
    grid_rows: int = 6
    min_distance_px: float = 8.0
    quality_level: float = 0.01
    block_size: int = 5
    detect_level: int = 0
    border_px: float = 8.0
    lk_window_px: int = 15
    lk_levels: int = 3
    lk_predicted_levels: int = 0
    lk_backward_levels: int = 0
    lk_backward_window_px: int = 0
    lk_max_iterations: int = 30
    lk_epsilon_px: float = 0.01
    lk_min_eigenvalue: float = 1e-4
    fb_threshold_px: float = 0.5
    max_patch_error: float = 20.0
    merge_distance_px: float = 2.0
    redetect_below: float = 0.95
    max_cell_share: float = 3.0
    history_len: int = 8
    background_detection: bool = False
    lk_predict_velocity: bool = True
    lk_predicted_gate_px: float = 1.0
    lk_shallow_max_miss: float = 0.25
    predict_neighbours: int = 6
    predict_radius_px: float = 48.0
    lk_deformation_correction: bool = True
    deformation_neighbours: int = 8
    deformation_radius_px: float = 48.0
    deformation_max_px: float = 0.6
    deformation_robust_px: float = 0.1

    def __post_init__(self) -> None:
        ints = {
            "max_features": (self.max_features, 1),
            "grid_cols": (self.grid_cols, 1),
            "grid_rows": (self.grid_rows, 1),
            "block_size": (self.block_size, 3),
            "detect_level": (self.detect_level, 0),
            "lk_window_px": (self.lk_window_px, 5),
            "lk_levels": (self.lk_levels, 0),
            "lk_predicted_levels": (self.lk_predicted_levels, 0),
            "lk_backward_levels": (self.lk_backward_levels, 0),
            "lk_backward_window_px": (self.lk_backward_window_px, 0),
            "lk_max_iterations": (self.lk_max_iterations, 1),
            "history_len": (self.history_len, 2),
            "predict_neighbours": (self.predict_neighbours, 0),
            "deformation_neighbours": (self.deformation_neighbours, 5),
        }
        for name, (value, low) in ints.items():
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InvalidInputError(
                    f"TrackerOptions.{name} must be an int >= {low}, got {value!r}"
                )
        for name in ("block_size", "lk_window_px"):
            if getattr(self, name) % 2 == 0:
                raise InvalidInputError(
                    f"TrackerOptions.{name} must be odd, got {getattr(self, name)}"
                )
        if self.lk_backward_window_px and (
            self.lk_backward_window_px < 5 or self.lk_backward_window_px % 2 == 0
        ):
            raise InvalidInputError(
                "TrackerOptions.lk_backward_window_px must be 0 or odd and >= 5, got "
                f"{self.lk_backward_window_px}"
            )
        floats: dict[str, tuple[float, float, float, bool]] = {
            "min_distance_px": (self.min_distance_px, 0.0, math.inf, True),
            "quality_level": (self.quality_level, 0.0, 1.0, False),
            "border_px": (self.border_px, 0.0, math.inf, True),
            "lk_epsilon_px": (self.lk_epsilon_px, 0.0, math.inf, False),
            "lk_min_eigenvalue": (self.lk_min_eigenvalue, 0.0, math.inf, True),
            "fb_threshold_px": (self.fb_threshold_px, 0.0, math.inf, False),
            "max_cell_share": (self.max_cell_share, 0.0, math.inf, True),
            "max_patch_error": (self.max_patch_error, 0.0, 255.0, False),
            "lk_predicted_gate_px": (self.lk_predicted_gate_px, 0.0, math.inf, False),
            "predict_radius_px": (self.predict_radius_px, 0.0, math.inf, False),
            "deformation_radius_px": (self.deformation_radius_px, 0.0, math.inf, False),
            "deformation_max_px": (self.deformation_max_px, 0.0, math.inf, False),
            "deformation_robust_px": (self.deformation_robust_px, 0.0, math.inf, True),
            "lk_shallow_max_miss": (self.lk_shallow_max_miss, 0.0, 1.0, True),
            "merge_distance_px": (self.merge_distance_px, 0.0, math.inf, True),
            "redetect_below": (self.redetect_below, 0.0, 1.0, False),
        }
        for name, (fvalue, lo, hi, lo_ok) in floats.items():
            ok = (
                isinstance(fvalue, int | float)
                and math.isfinite(fvalue)
                and (fvalue >= lo if lo_ok else fvalue > lo)
                and fvalue <= hi
            )
            if not ok:
                bound = "[" if lo_ok else "("
                raise InvalidInputError(
                    f"TrackerOptions.{name} must be in {bound}{lo}, {hi}], got {fvalue!r}"
                )


@dataclass(frozen=True)
class Tracks:
    """The live features after one frame. N = number of tracks, H = history_len.

    Arrays are read-only snapshots.

    Attributes:
        ids: (N,) uint32 persistent track ids (unique, increasing with creation).
        pixels: (N, 2) float64 current positions (u, v), pixels.
        ages: (N,) int32 frames each feature has been tracked (0 = detected in
            this frame); ``history[i, :ages[i] + 1]`` is valid (up to H).
        history: (N, H, 2) float64 past positions, ``[:, 0]`` = current,
            ``[:, k]`` = k frames ago; NaN where the track did not exist.
        stamps_ns: (H,) int64 stamps of those frames, nanoseconds (-1 if none).
        num_detected: features that started a track in this frame (with
            ``background_detection``: detected in the previous image, joining now).
        num_lost: features lost in this frame.
        lost_ids: (num_lost,) uint32 ids of the features lost in this frame.
        lost_by_reason: counts of lost features per reason (``LOST_REASONS``):
            LK failure, forward-backward check, patch difference, leaving the
            image, merged into an older feature, retired from a crowded grid cell,
            reset (image size change).
        timings: seconds spent in ``"lk"`` (both directions) and ``"detect"``.
    """

    ids: npt.NDArray[np.uint32]
    pixels: FloatArray
    ages: npt.NDArray[np.int32]
    history: FloatArray
    stamps_ns: npt.NDArray[np.int64]
    num_detected: int = 0
    num_lost: int = 0
    lost_ids: npt.NDArray[np.uint32] = field(default_factory=lambda: np.zeros(0, dtype=np.uint32))
    lost_by_reason: dict[str, int] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def num_tracks(self) -> int:
        """N, the number of live tracks."""
        return int(self.ids.shape[0])

    @property
    def stamp_ns(self) -> int:
        """Stamp of the current frame, nanoseconds."""
        return int(self.stamps_ns[0])


class FeatureTracker:
    """Tracks corners through a sequence of grey images (see module doc).

    Args:
        options: tracker settings.
    """

    def __init__(self, options: TrackerOptions | None = None) -> None:
        self.options = options if options is not None else TrackerOptions()
        #: clock of :attr:`Tracks.timings`, s (``time.thread_time`` for CPU time)
        self.clock: Callable[[], float] = time.perf_counter
        self._next_id = 0
        self._executor: ThreadPoolExecutor | None = None
        self.reset()

    def reset(self) -> None:
        """Forget all tracks and the previous image; ids keep increasing."""
        h = self.options.history_len
        self._prev: npt.NDArray[np.uint8] | None = None
        self._shape: tuple[int, int] | None = None
        self._ids = np.zeros(0, dtype=np.uint32)
        self._ages = np.zeros(0, dtype=np.int32)
        self._history = np.zeros((0, h, 2), dtype=np.float64)
        self._stamps = np.full(h, -1, dtype=np.int64)
        # per track: the rotational part of the last frame's predicted displacement (NaN
        # where there was no prediction), pixels
        self._rot_disp = np.zeros((0, 2), dtype=np.float64)
        # whether the next frame's predicted points take the shallow pass first
        self._shallow_next = True
        # background_detection: corners (K, 2) of the previous image being detected, and
        # the seconds it took (a detection still running is discarded: pure function)
        self._pending: Future[tuple[FloatArray, float]] | None = None

    @property
    def num_tracks(self) -> int:
        """Number of live tracks."""
        return int(self._ids.shape[0])

    def track(
        self, image: npt.ArrayLike, stamp_ns: int, predict: Predictor | None = None
    ) -> Tracks:
        """Track the live features into ``image`` and replenish them.

        Args:
            image: (H, W) uint8 grey image.
            stamp_ns: its stamp, nanoseconds; must increase from frame to frame.
            predict: optional map from previous-frame pixels (M, 2) float64 to
                predicted current pixels (M, 2) (LK starts there). Non-finite
                predictions fall back to the previous position.

        Returns:
            The live tracks after this frame.

        Raises:
            InvalidInputError: not a 2-D uint8 image, or a malformed prediction.
            TimeError: ``stamp_ns`` not after the previous frame's stamp.
        """
        img = np.asarray(image)
        if img.ndim != 2 or img.dtype != np.uint8:
            raise InvalidInputError(
                f"image must be a 2-D uint8 array, got shape {img.shape} dtype {img.dtype}"
            )
        img = np.ascontiguousarray(img)
        stamp = int(stamp_ns)
        opts = self.options
        lost_by_reason = dict.fromkeys(LOST_REASONS, 0)
        timings = {"lk": 0.0, "detect": 0.0}
        lost_ids = np.zeros(0, dtype=np.uint32)
        if self._prev is not None and stamp <= int(self._stamps[0]):
            raise TimeError(
                f"image stamp {stamp} ns is not after the previous one {int(self._stamps[0])} ns"
            )
        if self._shape is not None and img.shape != self._shape:
            lost_ids = self._ids.copy()
            lost_by_reason["reset"] = lost_ids.shape[0]
            self.reset()
        num_detected = 0
        if self._pending is not None:  # the previous image's corners join before the shift
            corners, timings["detect"] = self._pending.result()
            self._pending = None
            num_detected = self._add_features(corners)

        # Shift the history by one frame; column 0 is filled below.
        self._stamps = np.concatenate([[stamp], self._stamps[:-1]])
        self._history = np.concatenate(
            [np.full((self._history.shape[0], 1, 2), np.nan), self._history[:, :-1]], axis=1
        )
        if self._prev is not None and self._ids.shape[0] > 0:
            prev = self._history[:, 1]
            t0 = self.clock()
            new_pos, reason = self._flow(self._prev, img, prev, predict)
            if opts.lk_deformation_correction:
                alive = np.flatnonzero(reason == 0)
                bias, has = deformation_bias(
                    self._prev,
                    prev[alive],
                    new_pos[alive] - prev[alive],
                    opts.lk_window_px,
                    opts.deformation_neighbours,
                    opts.deformation_radius_px,
                    opts.deformation_robust_px,
                )
                use = has & (row_norms(bias) <= opts.deformation_max_px)
                new_pos[alive[use]] -= bias[use]
            timings["lk"] = self.clock() - t0
            if opts.merge_distance_px > 0:
                alive = np.flatnonzero(reason == 0)
                pairs = cKDTree(new_pos[alive]).query_pairs(
                    opts.merge_distance_px, output_type="ndarray"
                )
                # ids grow with creation time: the larger index is the younger track.
                reason[alive[pairs.max(axis=1)]] = 5
            if opts.max_cell_share > 0:
                # Features converge when the camera recedes (or turns away from them):
                # a cell holding more than max_cell_share x its share retires its
                # youngest extras, so the total drops and the emptied cells get new ones.
                alive = np.flatnonzero(reason == 0)  # ascending ids: oldest first
                cells = self._cells(new_pos[alive], img.shape[1], img.shape[0])
                cap = math.ceil(opts.max_cell_share * self._share())
                reason[alive[_rank_within(cells, self._ncells()) >= cap]] = 6
            keep = reason == 0
            for code, name in enumerate(LOST_REASONS[:6], start=1):
                lost_by_reason[name] = int(np.count_nonzero(reason == code))
            lost_ids = np.concatenate([lost_ids, self._ids[~keep]])
            self._history[:, 0] = new_pos
            self._history = self._history[keep]
            self._rot_disp = self._rot_disp[keep]
            self._ids = self._ids[keep]
            self._ages = self._ages[keep] + 1

        if self._ids.shape[0] < opts.redetect_below * opts.max_features:
            existing = self._history[:, 0].copy()
            if opts.background_detection:
                if self._executor is None:
                    self._executor = ThreadPoolExecutor(
                        1, thread_name_prefix="owl-detect", initializer=name_os_thread
                    )
                self._pending = self._executor.submit(self._timed_detect, img, existing)
            else:
                corners, timings["detect"] = self._timed_detect(img, existing)
                num_detected = self._add_features(corners)

        self._prev = img
        self._shape = (int(img.shape[0]), int(img.shape[1]))
        return self._snapshot(num_detected, lost_ids, lost_by_reason, timings)

    # ---------------------------------------------------------------- helpers

    def _timed_detect(
        self, img: npt.NDArray[np.uint8], existing: FloatArray
    ) -> tuple[FloatArray, float]:
        """New corners (K, 2) of ``img`` away from ``existing`` (M, 2), and the seconds
        it took (this thread's clock)."""
        t0 = self.clock()
        corners = self._detect(img, existing)
        return corners, self.clock() - t0

    def _add_features(self, corners: FloatArray) -> int:
        """Start a track at each corner (K, 2) of the current image; returns K."""
        k = int(corners.shape[0])
        new_hist = np.full((k, self.options.history_len, 2), np.nan)
        new_hist[:, 0] = corners
        self._history = np.concatenate([self._history, new_hist])
        new_ids = (self._next_id + np.arange(k)).astype(np.uint32)
        self._next_id += k
        self._ids = np.concatenate([self._ids, new_ids])
        self._rot_disp = np.concatenate([self._rot_disp, np.full((k, 2), np.nan)])
        self._ages = np.concatenate([self._ages, np.zeros(k, dtype=np.int32)])
        return k

    def _snapshot(
        self,
        num_detected: int,
        lost_ids: npt.NDArray[np.uint32],
        lost_by_reason: dict[str, int],
        timings: dict[str, float],
    ) -> Tracks:
        return Tracks(
            ids=_frozen(self._ids),
            pixels=_frozen(self._history[:, 0]),
            ages=_frozen(self._ages),
            history=_frozen(self._history),
            stamps_ns=_frozen(self._stamps),
            num_detected=num_detected,
            num_lost=int(lost_ids.shape[0]),
            lost_ids=_frozen(lost_ids.astype(np.uint32)),
            lost_by_reason=lost_by_reason,
            timings=timings,
        )

    def _flow(
        self,
        prev_img: npt.NDArray[np.uint8],
        cur_img: npt.NDArray[np.uint8],
        prev: FloatArray,
        predict: Predictor | None,
    ) -> tuple[FloatArray, npt.NDArray[np.int8]]:
        """Forward LK from ``prev`` (M, 2), backward check; new positions and a
        reason code per point (0 = kept, else 1 + index into LOST_REASONS)."""
        opts = self.options
        m = prev.shape[0]
        init = prev.copy()
        # points whose start includes their translational displacement, and that start
        predicted = np.zeros(m, dtype=bool)
        start = init
        if predict is not None:
            guess = np.asarray(predict(prev.copy()), dtype=np.float64)
            if guess.shape != (m, 2):
                raise InvalidInputError(
                    f"predict must return shape ({m}, 2) for ({m}, 2) input, got {guess.shape}"
                )
            ok = all_finite(guess)
            init[ok] = guess[ok]
            rot_disp = np.where(ok[:, None], guess - prev, np.nan)
            if opts.lk_predict_velocity and self._history.shape[1] > 2:
                trans, predicted = self._translation_prediction(prev, ok)
                start = init.copy()
                start[predicted] += trans[predicted]
            self._rot_disp = rot_disp
        else:
            self._rot_disp = np.full((m, 2), np.nan)
        p0 = prev.astype(np.float32).reshape(-1, 1, 2)
        p_init = init.astype(np.float32).reshape(-1, 1, 2)
        full = opts.lk_levels
        if predict is None or opts.lk_predicted_levels >= full:
            if predicted.any():  # the full pyramid, from the start with the translation
                p_init[predicted, 0] = start[predicted]
            return self._lk_pass(prev_img, cur_img, prev, p0, p_init, full)
        if not opts.lk_predict_velocity:
            predicted = np.ones(m, dtype=bool)
            p_start = p_init
        else:
            p_start = p_init.copy()
            p_start[predicted, 0] = start[predicted]
        # A start that already includes the translational flow leaves a fraction of a
        # pixel to find: a shallow pass converges there (to within 0.004 px of the full
        # pyramid's answer for 97 % of the points); points that fail a check, whose pass
        # moved them farther than lk_predicted_gate_px from that start, or without a
        # translation prediction are tracked with the full pyramid from the gyro start
        # (VINS-Fusion does the same). When the last frame's prediction missed more than
        # lk_shallow_max_miss of its points (a fast change of speed or turn: a car at
        # 10 Hz), every point takes the full pyramid.
        new_pos = np.full((m, 2), np.nan)
        reason = np.ones(m, dtype=np.int8)
        first = np.flatnonzero(predicted) if self._shallow_next else np.zeros(0, dtype=np.intp)
        if first.size:
            pos1, reason1 = self._lk_pass(
                prev_img, cur_img, prev[first], p0[first], p_start[first], opts.lk_predicted_levels
            )
            new_pos[first], reason[first] = pos1, reason1
            moved = row_norms(pos1 - p_start[first, 0])
            bad = ((reason1 >= 1) & (reason1 <= 3)) | ~(moved <= opts.lk_predicted_gate_px)
            redo = np.concatenate([np.flatnonzero(~predicted), first[bad]])
        else:
            redo = np.arange(m)
        if redo.size:
            redo.sort()
            pos2, reason2 = self._lk_pass(
                prev_img, cur_img, prev[redo], p0[redo], p_init[redo], full
            )
            new_pos[redo] = pos2
            reason[redo] = reason2
        if opts.lk_predict_velocity and predicted.any():
            miss = (reason[predicted] != 0) | ~(
                row_norms(new_pos[predicted] - p_start[predicted, 0]) <= opts.lk_predicted_gate_px
            )
            self._shallow_next = float(np.mean(miss)) <= opts.lk_shallow_max_miss
        return new_pos, reason

    def _translation_prediction(
        self, prev: FloatArray, ok: npt.NDArray[np.bool_]
    ) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
        """Each track's expected translational displacement in this frame, px (M, 2), and
        which tracks have one (M,): the last frame's displacement less the rotational part
        the gyro predicted then, scaled by the ratio of the frame intervals; a track without
        one (new) takes the median of its ``predict_neighbours`` nearest tracks' within
        ``predict_radius_px`` of ``prev`` (M, 2), when at least three are there. ``ok``
        (M,): tracks with a gyro prediction this frame."""
        opts = self.options
        m = prev.shape[0]
        trans = np.full((m, 2), np.nan)
        have = np.zeros(m, dtype=bool)
        dt_now = float(self._stamps[0] - self._stamps[1])
        dt_last = float(self._stamps[1] - self._stamps[2])
        if not (self._stamps[2] >= 0 and dt_last > 0):
            return trans, have
        last = (self._history[:, 1] - self._history[:, 2]) - self._rot_disp
        have = ok & all_finite(last)
        trans[have] = last[have] * (dt_now / dt_last)
        need = np.flatnonzero(ok & ~have)
        donors = np.flatnonzero(have)
        if need.size and donors.size >= 3 and opts.predict_neighbours >= 3:
            k = min(opts.predict_neighbours, donors.size)
            dist, nb = cKDTree(prev[donors]).query(
                prev[need], k=k, distance_upper_bound=opts.predict_radius_px
            )
            found = np.isfinite(dist)
            count = found.sum(axis=1)
            enough = count >= 3
            fill = need[enough]
            # the median over the found neighbours (np.nanmedian's values, without its
            # masked-array overhead): sorted with the missing ones (NaN) last, the mean of
            # the two middle entries (one entry twice for an odd count)
            vals = trans[donors[np.where(found, nb, 0)]][enough]  # (n_fill, k, 2)
            vals[~found[enough]] = np.nan
            vals.sort(axis=1)
            count = count[enough, None, None]
            low = np.take_along_axis(vals, (count - 1) // 2, axis=1)[:, 0]
            high = np.take_along_axis(vals, count // 2, axis=1)[:, 0]
            trans[fill] = (low + high) / 2.0
            have[fill] = True
        return trans, have

    def _lk_pass(
        self,
        prev_img: npt.NDArray[np.uint8],
        cur_img: npt.NDArray[np.uint8],
        prev: FloatArray,
        p0: npt.NDArray[np.float32],
        p_init: npt.NDArray[np.float32],
        levels: int,
    ) -> tuple[FloatArray, npt.NDArray[np.int8]]:
        """One forward LK pass (``levels`` pyramid levels) from ``prev`` (M, 2) (``p0``:
        the same as (M, 1, 2) float32) starting at ``p_init`` (M, 1, 2) float32, with the
        backward check; new positions (M, 2) and reason codes (M,) as :meth:`_flow`."""
        opts = self.options
        m = prev.shape[0]
        criteria = (
            cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
            opts.lk_max_iterations,
            opts.lk_epsilon_px,
        )
        win = (opts.lk_window_px, opts.lk_window_px)
        back_side = opts.lk_backward_window_px or opts.lk_window_px
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        # Each call builds both pyramids (~0.3 ms at 640x480); the Python binding does
        # not accept buildOpticalFlowPyramid's output (opencv/opencv#4777), so they are
        # not reused across calls. The cost is per point and level (window sampling).
        p1, st1, err = (
            np.asarray(a)
            for a in cv2.calcOpticalFlowPyrLK(
                prev_img,
                cur_img,
                p0,
                p_init.copy(),  # OpenCV writes its result into this array
                winSize=win,
                maxLevel=levels,
                criteria=criteria,
                flags=flags,
                minEigThreshold=opts.lk_min_eigenvalue,
            )
        )
        back, st2, _ = (
            np.asarray(a)
            for a in cv2.calcOpticalFlowPyrLK(
                cur_img,
                prev_img,
                p1,
                p0.copy(),
                winSize=(back_side, back_side),
                maxLevel=min(opts.lk_backward_levels, opts.lk_levels),
                criteria=criteria,
                flags=flags,
                minEigThreshold=opts.lk_min_eigenvalue,
            )
        )
        new_pos = p1.reshape(-1, 2).astype(np.float64)
        fb = row_norms(back.reshape(-1, 2).astype(np.float64) - prev)
        height, width = cur_img.shape
        b = opts.border_px
        inside = (
            (new_pos[:, 0] >= b - 0.5)
            & (new_pos[:, 0] <= width - 0.5 - b)
            & (new_pos[:, 1] >= b - 0.5)
            & (new_pos[:, 1] <= height - 0.5 - b)
        )
        lk_ok = (st1.reshape(-1) == 1) & all_finite(new_pos)
        reason = np.zeros(m, dtype=np.int8)
        reason[~inside] = 4
        reason[~(err.reshape(-1) <= opts.max_patch_error)] = 3
        reason[~((st2.reshape(-1) == 1) & (fb <= opts.fb_threshold_px))] = 2
        reason[~lk_ok] = 1
        return new_pos, reason

    def _detect(self, img: npt.NDArray[np.uint8], existing: FloatArray) -> FloatArray:
        """New corners (K, 2), grid-balanced, away from ``existing`` (M, 2) features: on
        the ``detect_level`` image, and where that finds too few (texture finer than its
        pixels) the rest on the input image."""
        found = self._detect_at(img, existing, self.options.detect_level)
        if self.options.detect_level > 0 and existing.shape[0] + found.shape[0] < (
            self.options.max_features
        ):
            more = self._detect_at(img, np.concatenate([existing, found]), 0)
            found = np.concatenate([found, more])
        return found

    def _detect_at(
        self, img: npt.NDArray[np.uint8], existing: FloatArray, level: int
    ) -> FloatArray:
        """:meth:`_detect` on pyramid level ``level`` of ``img`` alone."""
        opts = self.options
        needed = opts.max_features - existing.shape[0]
        if needed <= 0:
            return np.zeros((0, 2))
        height, width = img.shape
        search = img
        scale = 1.0
        for _ in range(level):  # pixel i of level l+1 is centred on 2i of l
            search = np.asarray(cv2.pyrDown(search), dtype=np.uint8)
            scale *= 2.0
        s_h, s_w = search.shape
        mask = np.zeros((s_h, s_w), dtype=np.uint8)
        b = math.ceil(opts.border_px / scale)
        if 2 * b >= s_h or 2 * b >= s_w:
            return np.zeros((0, 2))
        mask[b : s_h - b, b : s_w - b] = 255
        min_distance = opts.min_distance_px / scale
        if existing.shape[0] > 0 and min_distance > 0:
            # Forbid disks of radius min_distance around the live features:
            # mark their pixels, dilate with a disk, clear those pixels.
            occupied = np.zeros((s_h, s_w), dtype=np.uint8)
            ij = np.rint(existing / scale).astype(np.int64)
            ij[:, 0] = np.clip(ij[:, 0], 0, s_w - 1)
            ij[:, 1] = np.clip(ij[:, 1], 0, s_h - 1)
            occupied[ij[:, 1], ij[:, 0]] = 255
            r = math.ceil(min_distance)
            disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
            cv2.subtract(mask, cv2.dilate(occupied, disk), dst=mask)  # 255 - 255 = 0
        corners = cv2.goodFeaturesToTrack(
            search,
            maxCorners=3 * needed + 10 * opts.grid_cols * opts.grid_rows,
            qualityLevel=opts.quality_level,
            minDistance=min_distance,
            mask=mask,
            blockSize=opts.block_size,
        )
        if corners is None:
            return np.zeros((0, 2))
        pts = corners.reshape(-1, 2).astype(np.float64) * scale  # strongest first
        # Grid bucketing: each cell may add up to its share minus what it holds.
        ncells = self._ncells()
        cell_new = self._cells(pts, width, height)
        cell_old = self._cells(existing, width, height)
        room = self._share() - np.bincount(cell_old, minlength=ncells)
        first = _rank_within(cell_new, ncells) < room[cell_new]  # strongest first within
        chosen = np.flatnonzero(first)[:needed]
        if chosen.shape[0] < needed:  # cells without texture: fill with the strongest rest
            rest = np.flatnonzero(~first)[: needed - chosen.shape[0]]
            chosen = np.sort(np.concatenate([chosen, rest]))
        result: FloatArray = pts[chosen]
        return result

    def _ncells(self) -> int:
        return self.options.grid_cols * self.options.grid_rows

    def _share(self) -> int:
        """Features per grid cell when the image is evenly covered."""
        return math.ceil(self.options.max_features / self._ncells())

    def _cells(self, pts: FloatArray, width: int, height: int) -> npt.NDArray[np.int64]:
        opts = self.options
        col = np.clip((pts[:, 0] + 0.5) * opts.grid_cols // width, 0, opts.grid_cols - 1)
        row = np.clip((pts[:, 1] + 0.5) * opts.grid_rows // height, 0, opts.grid_rows - 1)
        result: npt.NDArray[np.int64] = (row * opts.grid_cols + col).astype(np.int64)
        return result


_CHUNK = 64  # windows per step in deformation_bias


def deformation_bias(
    image: npt.NDArray[np.uint8],
    centres: FloatArray,
    flow: FloatArray,
    window_px: int,
    neighbours: int,
    radius_px: float,
    robust_px: float = 0.0,
) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """First-order error of translation-only Lucas-Kanade on a deforming window.

    A window of ``image`` centred on ``c`` whose content appears in the next image as
    ``x -> c' + A (x - c)`` is tracked by translation-only LK to ``c' + e`` with, to first
    order in ``A - I``,

        e = G^-1 sum_d g g^T (A - I) d,        G = sum_d g g^T,

    over the window's offsets ``d`` and the image gradients ``g`` at ``c + d`` (the
    linearised LK normal equations; ``e`` pulls the track towards the window's
    gradient-weighted centroid as the surface looms). ``A - I`` is each point's flow
    gradient: an affine flow fitted by least squares to the flows of the point and its
    ``neighbours`` nearest points within ``radius_px``. Measured against exact
    reprojections on the street scene (20 000 tracked positions), subtracting ``e``
    takes the LK error from 0.098 / 0.082 to 0.077 / 0.058 px RMS (x / y).

    Args:
        image: (H, W) uint8, the image the windows are taken from (LK's first image).
        centres: (N, 2) float64 window centres in ``image``, pixels.
        flow: (N, 2) float64 each centre's tracked displacement to the next image, pixels.
        window_px: LK window side (odd), pixels.
        neighbours: points besides itself whose flows give a point's flow gradient.
        radius_px: those points lie within this distance, pixels.
        robust_px: > 0: the fit is redone once with Cauchy weights of this scale on each
            neighbour's misfit (another surface across a depth edge counts less), pixels.

    Returns:
        (N, 2) float64 error ``e`` to subtract from the tracked positions, pixels, and
        (N,) bool: which points have one (at least 5 of the neighbours found, a
        well-conditioned fit and window).
    """
    n = centres.shape[0]
    bias = np.zeros((n, 2))
    if n < 6:
        return bias, np.zeros(n, dtype=bool)
    # flow gradient D = A - I per point: flow(x) ~ f0 + D (x - c) over the neighbours
    k = min(neighbours + 1, n)
    dist, nb = cKDTree(centres).query(centres, k=k, distance_upper_bound=radius_px)
    found = np.isfinite(dist)
    nb = np.where(found, nb, 0)
    xf = np.concatenate([centres, flow], axis=1)[nb]  # (N, k, 4): neighbour, its flow
    xf[..., :2] -= centres[:, None]
    dx, fn = xf[..., :2], xf[..., 2:]  # (N, k, 2) offsets and flows
    d, mean_x, mean_f, cov = _affine_gradient(found.astype(np.float64), xf)
    # the neighbours must spread in both directions: the smaller eigenvalue of their
    # offsets' covariance at least (2 px)^2
    cxx, cxy, cyy = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    lam_min = 0.5 * (cxx + cyy - np.sqrt((cxx - cyy) ** 2 + 4 * cxy**2))
    has = (found.sum(axis=1) >= 6) & (lam_min >= 4.0)
    if robust_px > 0:
        # one reweighting: neighbours off the point's affine flow (another surface across
        # a depth edge, a moving object) count less (Cauchy weights, scale robust_px)
        res = fn - mean_f[:, None, :] - (dx - mean_x[:, None, :]) @ np.transpose(d, (0, 2, 1))
        res_x, res_y = res[..., 0], res[..., 1]
        cauchy = found / (1.0 + (res_x * res_x + res_y * res_y) / robust_px**2)
        d = _affine_gradient(cauchy, xf)[0]
    sums = _window_moments(image, centres, window_px)
    g11, g12, g22 = sums[:, 0, 0], sums[:, 1, 0], sums[:, 2, 0]
    # rhs_i = sum_jk D_jk sum g_i g_j d_k
    rx = (
        sums[:, 0, 1] * d[:, 0, 0]
        + sums[:, 0, 2] * d[:, 0, 1]
        + sums[:, 1, 1] * d[:, 1, 0]
        + sums[:, 1, 2] * d[:, 1, 1]
    )
    ry = (
        sums[:, 1, 1] * d[:, 0, 0]
        + sums[:, 1, 2] * d[:, 0, 1]
        + sums[:, 2, 1] * d[:, 1, 0]
        + sums[:, 2, 2] * d[:, 1, 1]
    )
    sol, solved = _solve_sym2(g11, g12, g22, np.stack([rx, ry], axis=1), trace_floor=1.0)
    ok = has & solved
    bias[ok] = sol[ok]
    return bias, ok


def _window_moments(
    image: npt.NDArray[np.uint8], centres: FloatArray, window_px: int
) -> FloatArray:
    """Gradient moments of each LK window: (N, 3, 3) ``[g_x g_x, g_x g_y, g_y g_y] x [sum,
    sum * d_x, sum * d_y]`` over the window's offsets ``d`` (pixels) about each of
    ``centres`` (N, 2), with the gradients ``g`` (Scharr, as OpenCV's LK takes them)
    sampled bilinearly at ``c + d`` as LK samples them, from the (win + 1)^2 block of
    each gradient image at each point (float32 sums of exact int16 gradients)."""
    n = centres.shape[0]
    w = window_px
    s = w + 1  # block side
    # exact in int16 (|Scharr| <= 16 * 255) and a tenth of the float32 filter's time
    grads = np.empty((2, *image.shape), np.int16)  # d/dx, d/dy
    for c in (0, 1):
        cv2.Scharr(image, cv2.CV_16S, 1 - c, c, dst=grads[c])
    blocks = sliding_window_view(grads, (s, s), axis=(1, 2))  # (2, H - w, W - w, s, s)
    half = (w - 1) // 2
    corner = centres - half
    base = np.floor(corner)
    frac = (corner - base).astype(np.float32)
    iu = np.clip(base[:, 0].astype(np.intp), 0, blocks.shape[2] - 1)
    iv = np.clip(base[:, 1].astype(np.intp), 0, blocks.shape[1] - 1)
    off = np.arange(-half, half + 1, dtype=np.float32)
    basis = np.stack([np.ones(w * w, np.float32), np.tile(off, w), np.repeat(off, w)], axis=1)
    # (win^2, 3): 1, x offset (columns), y offset (rows)
    sums = np.empty((n, 3, 3))
    # in chunks of points, into buffers allocated once: the temporaries stay small enough
    # to stay in cache (whole-array temporaries of 1000 windows cost more in page faults
    # than in arithmetic). The bilinear weights are applied along x over all w + 1 rows,
    # then along y (the same operations on the same values as the 2x2 formula, so the same
    # sums), each as one operation on the flattened chunk: entry k and entry k + 1 (x) or
    # k + s (y); the entries that mix a block's last column or row with the next are not
    # used. (Operations on whole contiguous blocks run several times faster than on the
    # (w + 1, w) sub-blocks.)
    chunk = min(_CHUNK, n)
    blk = np.empty((chunk, 2, s, s), np.float32)  # gradient blocks, then weighted
    tmp = np.empty((chunk, 2, s, s), np.float32)  # the other weighted term
    g = np.empty((chunk, 2, s, s), np.float32)  # interpolated: [:, :, :w, :w] valid
    packed = np.empty((chunk, 2, w, w), np.float32)  # that part, contiguous
    prods = np.empty((chunk, 3, w * w), np.float32)
    for lo in range(0, n, chunk):
        m = min(chunk, n - lo)
        sl = slice(lo, lo + m)
        bk, tm, gg, pk, pr = blk[:m], tmp[:m], g[:m], packed[:m], prods[:m]
        bk_flat, tm_flat, gg_flat = bk.reshape(-1), tm.reshape(-1), gg.reshape(-1)
        bk.transpose(1, 0, 2, 3)[...] = blocks[:, iv[sl], iu[sl]]
        a, b = frac[sl, 0, None, None, None], frac[sl, 1, None, None, None]
        np.multiply(bk, a, out=tm)
        bk *= 1 - a
        np.add(bk_flat[:-1], tm_flat[1:], out=gg_flat[:-1])  # along x: columns j, j + 1
        gg_flat[-1] = 0.0  # (not written above; read, unused, by the pass along y)
        np.multiply(gg, b, out=tm)
        gg *= 1 - b
        np.add(gg_flat[:-s], tm_flat[s:], out=gg_flat[:-s])  # along y: rows i, i + 1
        pk[...] = gg[:, :, :w, :w]
        gx, gy = pk[:, 0].reshape(m, w * w), pk[:, 1].reshape(m, w * w)
        np.multiply(gx, gx, out=pr[:, 0])
        np.multiply(gx, gy, out=pr[:, 1])
        np.multiply(gy, gy, out=pr[:, 2])
        sums[sl] = (pr.reshape(-1, w * w) @ basis).reshape(m, 3, 3)
    return sums


def _affine_gradient(
    w: FloatArray, xf: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Weighted least-squares affine fit ``f ~ f0 + D x`` per point, in closed form.

    Args:
        w: (N, k) weights; xf: (N, k, 4) offsets ``x`` (``[..., :2]``), pixels, and values
            ``f`` (``[..., 2:]``, flows), pixels (one array: their means and moments are
            computed together).

    Returns:
        ``D`` (N, 2, 2) with ``D[n, j, k] = d f_j / d x_k`` (zero where the offsets do not
        span two directions), the weighted means of ``x`` and of ``f`` (N, 2) (the fit
        passes through them), and the weighted covariance of ``x`` (N, 2, 2), pixels^2:
        the centred normal equations ``Cxx D^T = Cxf``.
    """
    sw = np.maximum(w.sum(axis=1), 1e-300)
    means = np.einsum("nk,nka->na", w, xf) / sw[:, None]  # (N, 4): of x, of f
    centred = xf - means[:, None, :]
    wxc_t = np.transpose(centred[..., :2] * w[..., None], (0, 2, 1))  # (N, 2, k)
    moments = wxc_t @ centred  # (N, 2, 4): Cxx [a, b] and Cxf [a, j]
    cxx, cxf = moments[..., :2], moments[..., 2:]
    # D^T = Cxx^-1 Cxf, so D = (Cxx^-1 Cxf)^T (zero where Cxx is singular)
    dt_, _ = _solve_sym2(cxx[:, 0, 0], cxx[:, 0, 1], cxx[:, 1, 1], cxf, trace_floor=1e-300)
    d = np.transpose(dt_, (0, 2, 1))
    return d, means[:, :2], means[:, 2:], cxx / sw[:, None, None]


def _solve_sym2(
    a00: FloatArray, a01: FloatArray, a11: FloatArray, rhs: FloatArray, trace_floor: float
) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Batched solve of symmetric 2x2 systems ``[[a00, a01], [a01, a11]] x = rhs`` in closed
    form: ``a..`` (N,), ``rhs`` (N, 2) or (N, 2, K); the solution (same shape as ``rhs``,
    zero where singular) and (N,) bool: solved (``det > 1e-12 max(trace, trace_floor)^2``)."""
    det = a00 * a11 - a01 * a01
    ok = det > 1e-12 * np.maximum(a00 + a11, trace_floor) ** 2
    inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    col = (slice(None),) + (None,) * (rhs.ndim - 2)  # (N,) coefficients against rhs[:, i]
    c00, c01, c11, scale = (v[col] for v in (a00, a01, a11, inv_det))
    out = np.empty_like(rhs)
    out[:, 0] = (c11 * rhs[:, 0] - c01 * rhs[:, 1]) * scale
    out[:, 1] = (c00 * rhs[:, 1] - c01 * rhs[:, 0]) * scale
    return out, ok


def _rank_within(groups: npt.NDArray[np.int64], ngroups: int) -> npt.NDArray[np.int64]:
    """Rank (0, 1, ...) of each element within its group, in input order.

    Args:
        groups: (N,) int64 group index of each element, in [0, ngroups).
        ngroups: number of groups.

    Returns:
        (N,) int64: element i is the rank[i]-th element of group groups[i].
    """
    order = np.argsort(groups, kind="stable")
    counts = np.bincount(groups, minlength=ngroups)
    starts = np.cumsum(counts) - counts
    rank = np.empty(groups.shape[0], dtype=np.int64)
    rank[order] = np.arange(groups.shape[0]) - np.repeat(starts, counts)
    return rank


_T = TypeVar("_T", bound=np.ndarray)


def _frozen(a: _T) -> _T:
    """A read-only copy."""
    out = a.copy()
    out.setflags(write=False)
    return out
