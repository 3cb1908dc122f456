"""PNG figures of OWL results (matplotlib, Agg backend; no display needed).

Each function takes arrays / owl_core FrameResults and writes one PNG, returning its path:

- :func:`shape_constancy`: the cube's RoT point cloud at several times overlaid (paper:
  the cloud keeps its shape while the images change), raw and moved back along the heading.
- :func:`complex_domain`: OWL's complex domain rotated 90 degrees (heading up): each point at
  ``(signed |omega|, L)``, with per-track trajectories over time; circles of constant r/|t|,
  rays of constant angle from the heading.
- :func:`heading_error`: heading error over time, OWL and the baselines.
- :func:`range_scatter`: estimated vs true r/|t| (log-log), one panel per method.
- :func:`scaled_cloud`: one frame's scaled points (seconds) from two viewpoints, coloured by L.
- :func:`fields`: L and omega over the image.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, ParamSpec, TypeVar

import matplotlib
import numpy as np
import numpy.typing as npt
from matplotlib.collections import LineCollection
from matplotlib.colors import Normalize, PowerNorm
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle

from owl_core.types import FrameResult, PointFlag

FloatArray = npt.NDArray[np.float64]
DPI = 110
COLORS = {"OWL": "#d62728", "cv-5pt": "#1f77b4", "cv-gyro": "#2ca02c"}

#: The figures' style, applied only while a figure is drawn (no process-wide rcParams).
STYLE = {
    "figure.facecolor": "white",
    "axes.grid": True,
    "grid.alpha": 0.3,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "font.size": 10,
}

_P = ParamSpec("_P")
_R = TypeVar("_R")


def _styled(draw: Callable[_P, _R]) -> Callable[_P, _R]:
    """Run a figure function under :data:`STYLE` (matplotlib.rc_context)."""

    @functools.wraps(draw)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with matplotlib.rc_context(STYLE):
            return draw(*args, **kwargs)

    return wrapper


def _save(fig: Any, path: str | Path) -> Path:
    """Write ``fig`` (a matplotlib Figure without pyplot: no backend is chosen or changed)."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=DPI, bbox_inches="tight")
    return out


def _l_scale(lv: FloatArray) -> dict[str, Any]:
    """Colour settings for L: sequential when (almost) all points approach, else diverging."""
    if lv.size == 0:
        return {"cmap": "plasma", "norm": PowerNorm(0.5, vmin=0.0, vmax=1.0)}
    hi = float(np.nanpercentile(lv, 98))
    if float(np.nanpercentile(lv, 5)) >= 0:
        # square-root scale: L spans decades (far walls to the ground at the feet)
        return {"cmap": "plasma", "norm": PowerNorm(0.5, vmin=0.0, vmax=max(hi, 1e-6))}
    lim = float(np.nanpercentile(np.abs(lv), 98))
    return {"cmap": "coolwarm", "vmin": -lim, "vmax": lim}


def _l_label(scale: Mapping[str, Any], text: str) -> str:
    """Colour-bar label for L, saying when the colour scale is not linear."""
    if isinstance(scale.get("norm"), PowerNorm):
        return f"{text} (square-root colour scale)"
    return f"{text} (linear colour scale)"


def _static(res: FrameResult) -> npt.NDArray[np.bool_]:
    return (np.asarray(res.flags) & int(PointFlag.MOVING)) == 0


@_styled
def shape_constancy(
    results: Sequence[FrameResult],
    selections: Sequence[npt.NDArray[np.bool_]],
    times_s: Sequence[float],
    images: Sequence[npt.NDArray[np.uint8]],
    path: str | Path,
    truth_points: Sequence[FloatArray] | None = None,
) -> Path:
    """The cube's RoT cloud at several times: the images change, the cloud's shape does not.

    Args:
        results: FrameResults at the chosen times (K of them).
        selections: per result, (N,) bool: the points on the cube.
        times_s: (K,) time of each result, seconds.
        images: (K,) the grey images at those times (crops around the cube along the top).
        path: output PNG.
        truth_points: per result, (N,) true scaled points (N, 3) (bearing * true r/|t|,
            seconds) of the same points, drawn in grey under the estimates.
    """
    k = len(results)
    cmap = matplotlib.colormaps.get_cmap("viridis")
    # up to 0.8 of viridis: its light yellow end is unreadable as title text on white
    colors = [cmap(0.8 * i / max(k - 1, 1)) for i in range(k)]
    fig = Figure(figsize=(15, 8.6))
    grid = fig.add_gridspec(2, 12 * k, height_ratios=[1, 2.1])
    allpx = np.concatenate([r.pixels[sel] for r, sel in zip(results, selections, strict=True)])
    if allpx.size:
        (u0, v0), (u1, v1) = allpx.min(axis=0), allpx.max(axis=0)
        pad = 0.35 * max(u1 - u0, v1 - v0) + 10
        box = (u0 - pad, u1 + pad, v1 + pad, v0 - pad)
    for i, (img, t) in enumerate(zip(images, times_s, strict=True)):
        ax = fig.add_subplot(grid[0, 12 * i : 12 * (i + 1)])
        ax.imshow(img, cmap="gray")
        res, sel = results[i], selections[i]
        ax.scatter(*res.pixels[sel].T, s=5, color=colors[i])
        if allpx.size:
            ax.set_xlim(max(box[0], 0), min(box[1], img.shape[1] - 1))
            ax.set_ylim(min(box[2], img.shape[0] - 1), max(box[3], 0))
        ax.set_title(f"t = {t:.1f} s: {int(sel.sum())} points", color=colors[i])
        ax.set_axis_off()
    # the three views in a row of their own, spaced so that each keeps its axis labels
    bottom = grid[1, :].subgridspec(1, 3, wspace=0.32)
    raw = fig.add_subplot(bottom[0, 0])
    moved = fig.add_subplot(bottom[0, 1])
    front = fig.add_subplot(bottom[0, 2])
    t0 = times_s[0]
    every: list[FloatArray] = []
    for i, res in enumerate(results):
        sel = selections[i] & _static(res)
        pts = res.points[sel]
        h = res.heading if res.heading is not None else np.zeros(3)
        # under constant velocity the scaled cloud moves by -heading per second
        shift = h * (times_s[i] - t0)
        if truth_points is not None:
            tp = truth_points[i][sel]
            kw = {"s": 14, "color": "0.8", "zorder": 1}
            raw.scatter(tp[:, 0], tp[:, 2], **kw, label="truth" if i == 0 else None)
            moved.scatter(tp[:, 0] + shift[0], tp[:, 2] + shift[2], **kw)
            front.scatter(tp[:, 0] + shift[0], -(tp[:, 1] + shift[1]), **kw)
        back = pts + shift
        raw.scatter(
            pts[:, 0],
            pts[:, 2],
            s=7,
            color=colors[i],
            alpha=0.75,
            zorder=2,
            label=f"t = {times_s[i]:.1f} s",
        )
        moved.scatter(back[:, 0], back[:, 2], s=7, color=colors[i], alpha=0.75, zorder=2)
        front.scatter(back[:, 0], -back[:, 1], s=7, color=colors[i], alpha=0.75, zorder=2)
        every += [pts, back]
    if every:
        allp = np.concatenate(every)
        lo = np.nanpercentile(allp, 3, axis=0)
        hi = np.nanpercentile(allp, 97, axis=0)
        span = max(hi[0] - lo[0], hi[2] - lo[2]) * 0.6 + 0.2
        cx, cz = (lo[0] + hi[0]) / 2, (lo[2] + hi[2]) / 2
        cy = -(lo[1] + hi[1]) / 2
        for ax in (raw, moved):
            ax.set_xlim(cx - span, cx + span)
            ax.set_ylim(cz - span, cz + span)
        front.set_xlim(cx - span / 2, cx + span / 2)
        front.set_ylim(cy - span / 2, cy + span / 2)
    raw.set_title("top view, as measured", fontsize=10)
    moved.set_title(f"top view, moved back along the heading to t = {t0:.1f} s", fontsize=10)
    front.set_title("front view, moved back: the face keeps its shape", fontsize=10)
    for ax in (raw, moved):
        ax.set_xlabel("x = e_x * r/|t|  (s)")
        ax.set_ylabel("z = e_z * r/|t|  (s, forward)")
    front.set_xlabel("x (s)")
    front.set_ylabel("up = -e_y * r/|t|  (s)")
    for ax in (raw, moved, front):
        ax.set_aspect("equal")
    raw.legend(loc="upper left", fontsize=8, markerscale=2)
    fig.suptitle(
        "Shape constancy: the cube's image grows, its RoT point cloud (e * r/|t|, seconds) "
        "keeps its shape",
        fontsize=13,
    )
    return _save(fig, path)


def _signed_omega(res: FrameResult) -> FloatArray:
    """|omega| signed by the side of the heading the point is on (right = +)."""
    h = res.heading if res.heading is not None else np.array([0.0, 0.0, 1.0])
    right = np.array([1.0, 0.0, 0.0]) - h[0] * h
    right /= max(np.linalg.norm(right), 1e-12)
    side = np.sign(res.bearings @ right)
    side[side == 0] = 1.0
    return np.linalg.norm(res.omega, axis=1) * side


@_styled
def complex_domain(
    results: Sequence[FrameResult], path: str | Path, max_tracks: int = 80, title: str = ""
) -> Path:
    """OWL's complex domain ``L + j omega`` rotated 90 degrees, with per-track trajectories.

    Each point sits at (signed |omega|, L) (1/s): its angle from the vertical is the angle
    between its bearing and the heading, its distance from the origin is |ToR| = |t|/r.
    A point approaching the camera spirals outwards and sideways as it passes.
    """
    t0 = results[0].stamp_ns
    tracks: dict[int, list[tuple[float, float, float]]] = {}
    for res in results:
        t = (res.stamp_ns - t0) * 1e-9
        xs = _signed_omega(res)
        keep = _static(res)
        for i in np.flatnonzero(keep):
            tracks.setdefault(int(res.ids[i]), []).append((t, float(xs[i]), float(res.looming[i])))
    long = sorted(tracks.values(), key=len, reverse=True)
    long = [np.array(v) for v in long if len(v) >= 5]
    # spread the chosen tracks over the domain: take every k-th of the longest ones
    step = max(1, len(long) // max_tracks)
    chosen = long[::step][:max_tracks]
    t_end = max((res.stamp_ns - t0) * 1e-9 for res in results) or 1.0
    fig = Figure(figsize=(9, 8))
    ax = fig.subplots()
    last = results[-1]
    ax.scatter(
        _signed_omega(last),
        last.looming,
        s=5,
        color="0.75",
        zorder=1,
        label="all points, last frame",
    )
    segs, cols = [], []
    for tr in chosen:
        pts = tr[:, 1:]
        segs += [pts[i : i + 2] for i in range(len(pts) - 1)]
        cols += list(tr[1:, 0])
        ax.plot(
            *pts[-1],
            "o",
            ms=3.5,
            color=matplotlib.colormaps.get_cmap("plasma")(tr[-1, 0] / t_end),
            zorder=3,
        )
    lc = LineCollection(segs, cmap="plasma", norm=Normalize(0, t_end), linewidths=1.6, zorder=2)
    lc.set_array(np.asarray(cols))
    ax.add_collection(lc)
    fig.colorbar(lc, ax=ax, label="time (s)", shrink=0.6)
    xs = np.concatenate([tr[:, 1] for tr in chosen]) if chosen else _signed_omega(last)
    ys = np.concatenate([tr[:, 2] for tr in chosen]) if chosen else last.looming
    lim = float(np.nanpercentile(np.hypot(xs, ys), 98)) * 1.15 if xs.size else 1.0
    for rr in _nice_levels(lim):
        circ = Circle((0, 0), 1 / rr, fill=False, ls=":", color="0.5", lw=0.8)
        ax.add_patch(circ)
        a = math.radians(-75)
        ax.annotate(
            f"r/|t| = {rr:g} s",
            (math.sin(a) / rr, math.cos(a) / rr),
            fontsize=7,
            color="0.35",
            ha="right",
            va="center",
            bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.8},
        )
    for deg in (15, 30, 45, 60, 90, 120):
        a = math.radians(deg)
        for sgn in (-1, 1):
            ax.plot(
                [0, sgn * 2 * lim * math.sin(a)],
                [0, 2 * lim * math.cos(a)],
                color="0.85",
                lw=0.7,
                zorder=0,
            )
        ax.annotate(
            f"{deg} deg",
            (lim * 0.97 * math.sin(a), lim * 0.97 * math.cos(a)),
            fontsize=7,
            color="0.5",
        )
    ax.set_xlim(-lim, lim)
    ax.set_ylim(min(-0.1 * lim, float(np.nanmin(ys)) if ys.size else 0.0), lim)
    ax.set_aspect("equal")
    ax.axhline(0, color="0.3", lw=0.8)
    ax.axvline(0, color="0.3", lw=0.8)
    ax.set_xlabel("perceived rotation |omega| (1/s), signed: right of the heading > 0")
    ax.set_ylabel("looming L (1/s)")
    ax.set_title(
        title
        or f"OWL complex domain (rotated 90 deg: heading up), {len(chosen)} point trajectories"
    )
    ax.legend(loc="lower left", fontsize=8)
    return _save(fig, path)


def _nice_levels(lim: float) -> list[float]:
    """A few round r/|t| values (s) whose circles 1/(r/|t|) fall inside radius lim."""
    out: list[float] = []
    for v in (0.5, 1, 2, 3, 5, 10, 20, 50):
        if 1 / v < 0.95 * lim and (not out or 1 / out[-1] - 1 / v > 0.12 * lim):
            out.append(v)
    return out


@_styled
def heading_error(
    times_s: npt.ArrayLike, series: Mapping[str, npt.ArrayLike], path: str | Path, title: str = ""
) -> Path:
    """Heading error (degrees) over time per method; NaN = no heading in that frame."""
    t = np.asarray(times_s, dtype=np.float64)
    fig = Figure(figsize=(10, 4.2))
    ax = fig.subplots()
    for name, values in series.items():
        v = np.asarray(values, dtype=np.float64)
        med = np.nanmedian(v) if np.isfinite(v).any() else math.nan
        ax.plot(
            t,
            v,
            "-o",
            ms=2.5,
            lw=1.3,
            color=COLORS.get(name),
            label=f"{name} (median {med:.2f} deg)",
        )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("heading error (deg)")
    ax.set_ylim(bottom=0)
    ax.set_title(title or "Heading error over time")
    ax.legend()
    return _save(fig, path)


@_styled
def range_scatter(
    pairs: Mapping[str, tuple[npt.ArrayLike, npt.ArrayLike]], path: str | Path, title: str = ""
) -> Path:
    """Estimated vs true r/|t| (s) per method (log-log) with the 10 % band."""
    n = len(pairs)
    fig = Figure(figsize=(4.6 * n, 4.6))
    axes = fig.subplots(1, n, squeeze=False)
    allv = np.concatenate(
        [np.asarray(v, dtype=np.float64) for tr, es in pairs.values() for v in (tr, es)]
    )
    allv = allv[np.isfinite(allv) & (allv > 0)]
    lo, hi = np.percentile(allv, [0.5, 99.5]) if allv.size else (0.1, 10.0)
    lo, hi = lo / 1.5, hi * 1.5
    line = np.array([lo, hi])
    for ax, (name, (true, est)) in zip(axes[0], pairs.items(), strict=True):
        tr = np.asarray(true, dtype=np.float64)
        es = np.asarray(est, dtype=np.float64)
        ok = np.isfinite(tr) & np.isfinite(es) & (tr > 0) & (es > 0)
        rel = np.abs(es[ok] / tr[ok] - 1)
        ax.fill_between(line, line * 0.9, line * 1.1, color="0.85", label="+-10 %")
        ax.plot(line, line, color="0.3", lw=1)
        ax.scatter(tr[ok], es[ok], s=2, alpha=0.25, color=COLORS.get(name), rasterized=True)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
        ax.set_aspect("equal")
        med = float(np.median(rel)) if rel.size else math.nan
        within = float(np.mean(rel < 0.1)) if rel.size else math.nan
        ax.set_title(
            f"{name}: median error {med:.1%}\n{within:.0%} of {rel.size} points within 10 %",
            fontsize=10,
        )
        ax.set_xlabel("true r/|t| (s)")
        ax.set_ylabel("estimated r/|t| (s)")
        ax.legend(loc="upper left", fontsize=8)
    fig.suptitle(title or "Range over speed: estimated vs true (static points)", fontsize=12)
    return _save(fig, path)


@_styled
def scaled_cloud(res: FrameResult, path: str | Path, title: str = "") -> Path:
    """One frame's scaled 3D points (seconds) from two viewpoints, coloured by L (1/s).

    Left: an oblique 3D view; right: the view from above (x across, z forward). Axes span
    the central 96 % of the points (a few far outliers would otherwise flatten the cloud).
    """
    keep = _static(res) & np.isfinite(res.points).all(axis=1)
    pts = res.points[keep]
    lv = res.looming[keep]
    scale = _l_scale(lv)
    if pts.size:
        lo = np.percentile(pts, 2, axis=0)
        hi = np.percentile(pts, 98, axis=0)
        inside = np.all((pts >= lo) & (pts <= hi), axis=1)
    else:
        lo, hi, inside = np.zeros(3), np.ones(3), np.zeros(0, dtype=bool)
    fig = Figure(figsize=(11, 6.2), layout="constrained")
    grid = fig.add_gridspec(1, 2, width_ratios=[2.2, 1])
    ax = fig.add_subplot(grid[0, 0], projection="3d")
    p, c = pts[inside], lv[inside]
    sc = ax.scatter(p[:, 0], p[:, 2], -p[:, 1], c=c, s=6, depthshade=False, **scale)
    ax.scatter([0], [0], [0], marker="^", s=90, color="k")
    if res.heading is not None:
        h = res.heading * 0.4 * float(hi[2])
        ax.plot([0, h[0]], [0, h[2]], [0, -h[1]], color="k", lw=2.5)
    ax.set_xlabel("x right (s)")
    ax.set_ylabel("z forward (s)")
    ax.set_zlabel("up (s)")
    dx, dz, dy = (float(hi[i] - lo[i]) + 1e-3 for i in (0, 2, 1))
    ax.set_box_aspect((dx, dz, max(dy, 0.35 * max(dx, dz))))
    ax.view_init(elev=22, azim=-58)
    ax.set_title("oblique view")
    top = fig.add_subplot(grid[0, 1])
    top.scatter(p[:, 0], p[:, 2], c=c, s=6, **scale)
    top.plot([0], [0], marker="^", ms=11, color="k", ls="none", label="camera")
    if res.heading is not None:
        h = res.heading * 0.4 * float(hi[2])
        top.plot([0, h[0]], [0, h[2]], color="k", lw=2.5, label="heading")
    top.set_aspect("equal")
    top.set_xlabel("x right (s)")
    top.set_ylabel("z forward (s)")
    top.set_title("from above")
    # below the axes: inside, it covered the camera marker at the origin
    top.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, fontsize=8)
    fig.colorbar(sc, ax=[ax, top], shrink=0.75, label=_l_label(scale, "looming L (1/s)"))
    fig.suptitle(
        title or f"Scaled point cloud e * r/|t| in seconds ({pts.shape[0]} points), coloured by L",
        fontsize=12,
    )
    return _save(fig, path)


@_styled
def fields(
    image: npt.NDArray[np.uint8], res: FrameResult, path: str | Path, camera: Any = None
) -> Path:
    """L (colour) and omega (arrows of its image-plane part, colour = |omega|) over the image.

    With ``camera`` (owl_core CameraModel) the heading is marked where it meets the image
    (the focus of expansion).
    """
    keep = _static(res)
    px = res.pixels[keep]
    lv = res.looming[keep]
    om = res.omega[keep]
    fig = Figure(figsize=(15, 5.2), layout="constrained")
    axes = fig.subplots(1, 2)
    axes[0].imshow(image, cmap="gray", alpha=0.55)
    lscale = _l_scale(lv)
    s0 = axes[0].scatter(*px.T, c=lv, s=16, edgecolors="none", **lscale)
    fig.colorbar(s0, ax=axes[0], shrink=0.8, label=_l_label(lscale, "L (1/s)"))
    axes[0].set_title("looming L = (t.e)/r: how fast each point approaches")
    axes[1].imshow(image, cmap="gray", alpha=0.55)
    mag = np.linalg.norm(om, axis=1)
    ref = float(np.nanpercentile(mag, 90)) if mag.size else 1.0
    # the longest arrows are about 1/12 of the image width
    scale = max(ref, 1e-9) / (image.shape[1] / 12)
    q = axes[1].quiver(
        px[:, 0],
        px[:, 1],
        om[:, 0],
        om[:, 1],
        mag,
        cmap="viridis",
        angles="xy",
        scale_units="xy",
        scale=scale,
        width=0.0035,
        headwidth=3.5,
        clim=(0, float(np.nanpercentile(mag, 98)) if mag.size else 1),
    )
    fig.colorbar(q, ax=axes[1], shrink=0.8, label="|omega| (1/s) (linear colour scale)")
    # arrow-length key: an arrow of the 90th-percentile length, labelled in 1/s
    axes[1].quiverkey(
        q, 0.09, 0.045, max(ref, 1e-9), f"arrow length = {ref:.2g} 1/s", labelpos="E",
        coordinates="axes", color="k", labelcolor="k", zorder=5,
        fontproperties={"size": 9},
    )  # fmt: skip
    key_box = {"facecolor": "white", "alpha": 0.8, "edgecolor": "none"}
    axes[1].add_patch(
        Rectangle((0.0, 0.0), 0.4, 0.09, transform=axes[1].transAxes, zorder=4, **key_box)
    )
    axes[1].set_title("perceived rotation omega = (e x t)/r, x-y part")
    foe = None
    if camera is not None and res.heading is not None and res.heading[2] > 0:
        foe = np.asarray(camera.bearing_to_pixel(res.heading[None]))[0]
    for ax in axes:
        ax.set_xlim(0, image.shape[1] - 1)
        ax.set_ylim(image.shape[0] - 1, 0)
        ax.set_axis_off()
        if foe is not None and np.isfinite(foe).all():
            ax.plot(*foe, marker="+", ms=18, mew=2.5, color="k")
            ax.annotate("heading", foe, xytext=(8, -10), textcoords="offset points")
    fig.suptitle("OWL fields over the image", fontsize=12)
    return _save(fig, path)
