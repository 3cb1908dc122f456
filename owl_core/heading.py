"""Fused heading, leftover rotation (gyro bias) and independently moving points.

For a static scene every derotated bearing rate satisfies the coplanarity constraint
``t . (e_i x f_i) = 0``. When the derotation used a slightly wrong rate (gyro bias), the
measured ``f_i`` misses ``delta x e_i`` where ``delta`` is the leftover camera-frame rotation
rate (rad/s): ``f_true = f_i + delta x e_i``, so the constraint becomes

    h . (e_i x f_i) + delta . (h - (h.e_i) e_i) = 0,        h = t/|t|,

five unknowns (two for ``h``, three for ``delta``), bilinear. :func:`estimate_motion` solves
it robustly: a 2-point RANSAC for ``h`` (vectorised over hypotheses), then Gauss-Newton with
Cauchy weights on (h, delta) with a Gaussian prior on ``delta`` (the bias filter's
uncertainty plus the gyro noise), and reports the 1-sigma heading uncertainty. When the flow
is explained by a rotation alone (the camera does not translate) it returns no heading and
reads ``delta`` directly from the flow. :class:`GyroBiasFilter` filters the bias over time
(random walk), in the IMU frame.

The residual used throughout is ``h.(e x f_true)/|h x e|``: the component of ``f_true`` across
the epipolar great circle through ``e``, in 1/s, whose noise equals the per-axis noise of f.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from owl_core.errors import InvalidInputError
from owl_core.motion import MAD_TO_SIGMA, all_finite, cross, median, row_norms

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: Range of the robust residual scale of ``HeadingOptions.adaptive_scale``, in modelled
#: flow-noise sigmas.
SCALE_RANGE = (0.1, 1.0)


@dataclass(frozen=True)
class HeadingOptions:
    """Settings of :func:`estimate_motion`.

    Attributes:
        ransac_hypotheses: number of 2-point heading hypotheses scored at once.
        starts: Gauss-Newton refinements run from this many of the best distinct hypotheses.
        warm_starts: ... when an initial heading is given (it is refined too), this many.
        confirmed_warm_start: when the best-scoring hypothesis lies within 2 deg of the
            initial heading, refine the initial heading alone (the data confirm it: the
            extra start guards against a heading that jumped, and costs a refinement,
            about 2 ms at 1000 points); False: refine ``warm_starts`` more in any case.
        inlier_sigma: a point is an inlier (static) when its coplanarity residual is below
            this many of its standard deviations.
        irls_iterations: Gauss-Newton / reweighting iterations on (heading, rotation).
        cauchy_sigma: Cauchy robust-loss scale, in residual standard deviations.
        min_points: fewer usable points than this -> no estimate.
        min_sin: residual normaliser floor for |h x e| (points near the focus of expansion).
        still_ratio: the camera is declared not translating when the robust RMS of the
            flow left after a rotation-only fit is below ``still_ratio`` times the flow noise.
        min_translation_snr: ... or when the median translational flow across all points is
            below this many noise sigmas (too little parallax for a heading).
        max_points: the estimate uses at most this many points (an even subsample); the
            residuals and inlier flags are still computed for every point.
        adaptive_scale: the Cauchy scale and the final inlier gate follow the residuals'
            own robust spread (1.4826 x their median absolute value, kept within
            :data:`SCALE_RANGE` of the modelled noise: never wider than the model) instead
            of the modelled flow noise alone. The model's noise is a setting
            (``pixel_noise_px``); a tracker on a sharp texture does several times better,
            and then a few wrong tracks (an occlusion edge, an aliased patch) sit inside a
            gate three modelled sigmas wide and tilt the heading. The covariance still uses
            the modelled noise.
    """

    ransac_hypotheses: int = 64
    starts: int = 4
    warm_starts: int = 1
    confirmed_warm_start: bool = True
    inlier_sigma: float = 3.0
    irls_iterations: int = 4
    cauchy_sigma: float = 2.5
    min_points: int = 8
    min_sin: float = 0.05
    still_ratio: float = 1.5
    min_translation_snr: float = 3.0
    max_points: int = 1000
    adaptive_scale: bool = True

    def __post_init__(self) -> None:
        if self.ransac_hypotheses < 1:
            raise InvalidInputError(
                f"ransac_hypotheses must be >= 1, got {self.ransac_hypotheses}"
            )
        if self.min_points < 3:
            raise InvalidInputError(f"min_points must be >= 3, got {self.min_points}")
        for name in ("inlier_sigma", "cauchy_sigma", "min_sin", "still_ratio"):
            if not getattr(self, name) > 0:
                raise InvalidInputError(f"{name} must be > 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class MotionEstimate:
    """What the flow of one frame says about the camera motion. N = number of points.

    Attributes:
        heading: (3,) unit translation direction t/|t| (camera frame), or None when the
            camera does not translate or there are too few points.
        heading_sigma_rad: 1-sigma (RMS) angular uncertainty of ``heading``, rad; inf if None.
        rotation_error: (3,) leftover rotation rate delta, camera frame, rad/s
            (f_true = f + delta x e); the gyro bias estimate should move by -delta.
        rotation_cov: (3, 3) posterior covariance of ``rotation_error`` (it includes the
            prior), (rad/s)^2.
        translating: False when a rotation alone explains the flow, or when the flow is too
            weak to separate translation from rotation (then ``rotation_error`` is zero with
            the prior covariance: no information).
        inliers: (N,) bool, points consistent with the static-scene motion.
        residuals: (N,) float64 normalised coplanarity residuals (in standard deviations);
            NaN for points not used.
        reason: empty, or why there is no heading.
    """

    heading: FloatArray | None
    heading_sigma_rad: float
    rotation_error: FloatArray
    rotation_cov: FloatArray
    translating: bool
    inliers: BoolArray
    residuals: FloatArray
    reason: str = ""


def _orthonormal(h: FloatArray) -> tuple[FloatArray, FloatArray]:
    x, y, z = float(h[0]), float(h[1]), float(h[2])
    if abs(x) <= abs(y) and abs(x) <= abs(z):  # helper (1, 0, 0): u1 = helper x h
        u1 = np.array([0.0, -z, y])
    elif abs(y) <= abs(z):  # helper (0, 1, 0)
        u1 = np.array([z, 0.0, -x])
    else:  # helper (0, 0, 1)
        u1 = np.array([-y, x, 0.0])
    u1 /= math.sqrt(float(u1 @ u1))
    u2 = np.array([y * u1[2] - z * u1[1], z * u1[0] - x * u1[2], x * u1[1] - y * u1[0]])
    return u1, u2


def coplanarity_residuals(
    heading: npt.ArrayLike,
    bearings: npt.ArrayLike,
    derotated: npt.ArrayLike,
    rotation_error: npt.ArrayLike | None = None,
    min_sin: float = 0.05,
) -> FloatArray:
    """Coplanarity residuals ``h.(e x (f + delta x e))/max(|h x e|, min_sin)``, 1/s.

    Args:
        heading: (3,) unit heading, or (M, 3) for M hypotheses at once.
        bearings: (N, 3) unit bearings.
        derotated: (N, 3) derotated bearing rates, 1/s.
        rotation_error: (3,) leftover rotation delta, rad/s (default zero).
        min_sin: floor of the normaliser |h x e|.

    Returns:
        (N,) or (M, N) float64 residuals, 1/s (zero for a static point and exact data).
    """
    e = np.asarray(bearings, dtype=np.float64)
    f = np.asarray(derotated, dtype=np.float64)
    if e.ndim != 2 or e.shape[1] != 3 or f.shape != e.shape:
        raise InvalidInputError(
            f"bearings and derotated must both have shape (N, 3), got {e.shape} and {f.shape}"
        )
    h = np.asarray(heading, dtype=np.float64)
    if h.shape[-1:] != (3,) or h.ndim > 2:
        raise InvalidInputError(f"heading must have shape (3,) or (M, 3), got {h.shape}")
    if rotation_error is not None:
        f = f + cross(np.asarray(rotation_error, dtype=np.float64), e)
    return _coplanarity(h, e, cross(e, f), min_sin)


def _coplanarity(h: FloatArray, e: FloatArray, n: FloatArray, min_sin: float) -> FloatArray:
    """:func:`coplanarity_residuals` of the headings ``h`` (3,) or (M, 3) from the bearings
    ``e`` (N, 3) and their ``n = e x f`` (N, 3): (N,) or (M, N), 1/s."""
    num = h @ n.T
    hn = h / np.linalg.norm(h, axis=-1, keepdims=True)
    # sin = |h x e| for unit e, floored at min_sin; in place (M x N for M hypotheses)
    sin = hn @ e.T
    np.square(sin, out=sin)
    np.subtract(1.0, sin, out=sin)
    np.maximum(sin, 0.0, out=sin)
    np.sqrt(sin, out=sin)
    np.maximum(sin, min_sin, out=sin)
    return np.asarray(np.divide(num, sin, out=num), dtype=np.float64)


def _rotation_only(
    e: FloatArray, f: FloatArray, sigma: FloatArray, prior_inv: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Fit f = e x delta' (no translation; delta' = -delta) robustly. Returns delta, cov, res."""
    # e x d = skew(e) d; skew(e)^T skew(e) = I - e e^T and skew(e)^T f = f x e (unit e).
    fxe = cross(f, e)
    w = 1.0 / sigma**2
    delta_p = np.zeros(3)
    res = np.zeros(e.shape[0])
    cov: FloatArray = np.eye(3)
    for _ in range(4):
        normal = np.eye(3) * np.sum(w) - (e * w[:, None]).T @ e + prior_inv
        rhs = w @ fxe
        cov = np.asarray(np.linalg.inv(normal), dtype=np.float64)
        delta_p = cov @ rhs
        r = f - cross(e, delta_p)
        res = np.sqrt(np.einsum("na,na->n", r, r)) / sigma
        w = 1.0 / sigma**2 / (1.0 + (res / 3.0) ** 2)
    # f_true = f + delta x e = 0  <=>  f = e x delta, so delta = delta'.
    return delta_p, cov, res


def _with_hidden_translation(
    delta: FloatArray, cov: FloatArray, prior_inv: FloatArray, hidden: float
) -> tuple[FloatArray, FloatArray]:
    """A rotation read from a flow judged still, with the translation it may hide.

    A translational flow at or below the residual's level is not detected, and the part of
    it that looks like a rotation is absorbed into ``delta`` (a slowly translating camera
    read as a rotating one: its bias error is systematic over all points, far above the
    noise's share). The measurement's own covariance (the posterior ``cov`` (3, 3) less the
    prior ``prior_inv`` (3, 3)) grows by ``hidden**2 I`` (hidden: residual flow level,
    1/s); returns the posterior (delta (3,), cov (3, 3)) with it, rad/s.
    """
    info_post = np.linalg.inv(cov)
    info_meas = info_post - prior_inv
    meas_cov = np.linalg.inv(info_meas + 1e-30 * np.eye(3))
    meas = meas_cov @ (info_post @ delta)
    info_wide = np.linalg.inv(meas_cov + hidden**2 * np.eye(3))
    post = np.asarray(np.linalg.inv(info_wide + prior_inv), dtype=np.float64)
    return np.asarray(post @ (info_wide @ meas), dtype=np.float64), post


def _refine(
    h0: FloatArray,
    eu: FloatArray,
    fu: FloatArray,
    su: FloatArray,
    nvec: FloatArray,
    prior_inv: FloatArray,
    opts: HeadingOptions,
    estimate_rotation: bool,
) -> tuple[float, FloatArray, FloatArray, FloatArray]:
    """Gauss-Newton on (h, delta) from h0: Cauchy weights, then two hard-inlier iterations.

    Returns (robust cost, h, delta, 5x5 covariance of (two heading angles, delta)).
    """
    h = h0 / np.linalg.norm(h0)
    if np.sum(fu @ h) > 0:  # f = -t_perp/r: f . t < 0 for static points in front
        h = -h
    delta = np.zeros(3)
    normal = np.eye(5)
    jac = np.zeros((eu.shape[0], 5))
    for it in range(opts.irls_iterations + 2):
        u1, u2 = _orthonormal(h)
        # projections of every bearing (and of n = e x f) on h, delta, u1, u2 at once
        ep = eu @ np.stack([h, delta, u1, u2], axis=1)  # (N, 4)
        npj = nvec @ np.stack([h, u1, u2], axis=1)  # (N, 3)
        cos, ed = ep[:, 0], ep[:, 1]
        sin_raw = np.sqrt(np.maximum(1.0 - cos * cos, 0.0))
        sin = np.maximum(sin_raw, opts.min_sin)
        inv_scale = 1.0 / (sin * su)
        # raw residual h.n + tperp.delta with tperp = h - (h.e) e (d raw / d delta)
        raw = npj[:, 0] + h @ delta - cos * ed
        res = raw * inv_scale
        k = 1.0
        if opts.adaptive_scale:
            k = min(max(MAD_TO_SIGMA * float(median(np.abs(res))), SCALE_RANGE[0]), SCALE_RANGE[1])
        if it < opts.irls_iterations:
            w = 1.0 / (1.0 + (res / (k * opts.cauchy_sigma)) ** 2)
        else:
            w = (np.abs(res) < k * opts.inlier_sigma).astype(np.float64)
        # d raw / d h = n + delta - (e.delta) e, along u1 and u2
        jac[:, 0] = (npj[:, 1] + delta @ u1 - ed * ep[:, 2]) * inv_scale
        jac[:, 1] = (npj[:, 2] + delta @ u2 - ed * ep[:, 3]) * inv_scale
        if estimate_rotation:
            jac[:, 2:] = (h[None, :] - cos[:, None] * eu) * inv_scale[:, None]
        wj = jac * w[:, None]
        normal = wj.T @ jac
        normal[2:, 2:] += prior_inv
        # The gradient also carries the normaliser's own derivative (above its floor),
        # d(1/sin)/du_k = cos (e.u_k) / sin^3; the step's matrix leaves it out (the term
        # is the size of the residual). Without it in the gradient the iteration stops
        # where the noise's share of the residuals pulls it: a bias of order sigma^2
        # that more points do not shrink (0.46 deg of heading on a cube-scene frame
        # with the noise at its claimed level).
        rhs = -(wj.T @ res)
        grow = np.where(sin_raw > opts.min_sin, raw * cos / (sin * sin), 0.0) * inv_scale
        rhs[:2] -= (w * res * grow) @ ep[:, 2:4]
        rhs[2:] -= prior_inv @ delta
        step = np.linalg.solve(normal + 1e-12 * np.eye(5), rhs)
        h = h + step[0] * u1 + step[1] * u2
        h /= np.linalg.norm(h)
        delta = delta + step[2:]
    # covariance from the last iteration's normal matrix
    cov: FloatArray = np.asarray(np.linalg.inv(normal + 1e-12 * np.eye(5)), dtype=np.float64)
    cos = eu @ h
    sin = np.maximum(np.sqrt(np.maximum(1.0 - cos * cos, 0.0)), opts.min_sin)
    res = (nvec @ h + (h[None, :] - cos[:, None] * eu) @ delta) / (sin * su)
    cost = float(np.sum(np.log1p((res / opts.cauchy_sigma) ** 2)) + delta @ prior_inv @ delta)
    return cost, h, delta, cov


def _heading_starts(
    es: FloatArray,
    fs: FloatArray,
    ss: FloatArray,
    nvec: FloatArray,
    prior: FloatArray,
    opts: HeadingOptions,
    rng: np.random.Generator,
    initial_heading: npt.ArrayLike | None,
) -> list[FloatArray]:
    """RANSAC (MSAC score) on the heading with delta = 0, h = n_a x n_b for two random
    points: the starts for the refinement, best first, at least 2 deg apart; the
    ``initial_heading`` (3,) first when given. ``nvec`` (M, 3) = e x f."""
    m = opts.ransac_hypotheses
    pairs = rng.integers(0, es.shape[0], size=(m, 2))
    hyp = cross(nvec[pairs[:, 0]], nvec[pairs[:, 1]])
    hn = row_norms(hyp)
    hyp = hyp[hn > 0] / hn[hn > 0, None]
    if hyp.shape[0] == 0:
        hyp = np.array([[0.0, 0.0, 1.0]])
    res_h = _coplanarity(hyp, es, nvec, opts.min_sin)  # (hypotheses, M), 1/s
    # Prior rotation uncertainty widens the gate: delta moves each residual by up to |delta|.
    gate = opts.inlier_sigma + np.sqrt(np.trace(prior)) / median(ss)
    # MSAC: sum of min((res / ss / gate)^2, 1), in place
    res_h /= ss
    res_h /= gate
    np.square(res_h, out=res_h)
    score = np.minimum(res_h, 1.0, out=res_h).sum(axis=1)
    order = np.argsort(score)
    starts: list[FloatArray] = []
    if initial_heading is not None:
        h_init = np.asarray(initial_heading, dtype=np.float64)
        if h_init.shape != (3,) or not np.all(np.isfinite(h_init)) or not np.any(h_init):
            raise InvalidInputError(f"initial_heading must be a finite (3,) vector, got {h_init}")
        starts.append(h_init / np.linalg.norm(h_init))
    # Greedy, best score first: a hypothesis within 2 deg of a chosen start is skipped
    # (at least the best hypothesis is considered, as a candidate next to a warm start).
    wanted = opts.starts if initial_heading is None else 1 + opts.warm_starts
    cands = hyp[order]
    cos_lim = np.cos(np.radians(2.0))
    free = np.ones(cands.shape[0], dtype=bool)
    for s0 in starts:
        free &= np.abs(cands @ s0) < cos_lim
    if starts and opts.confirmed_warm_start and not free[0]:
        return starts
    pos = 0
    while pos < cands.shape[0]:
        nxt = np.flatnonzero(free[pos:])
        if nxt.size == 0 or (len(starts) >= wanted and nxt[0] > 0):
            break
        pos += int(nxt[0])
        starts.append(cands[pos])
        free &= np.abs(cands @ cands[pos]) < cos_lim
        pos += 1
        if len(starts) >= wanted:
            break
    return starts


def _refine_best(
    starts: list[FloatArray],
    es: FloatArray,
    fs: FloatArray,
    ss: FloatArray,
    nvec: FloatArray,
    prior_inv: FloatArray,
    opts: HeadingOptions,
    estimate_rotation: bool,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Gauss-Newton from each start, keeping the lowest robust cost (the bilinear problem
    has local minima): heading h (3,), rotation delta (3,), rad/s, and the (5, 5)
    covariance scaled by the inliers' residual variance when it exceeds the model's."""
    best: tuple[float, FloatArray, FloatArray, FloatArray] | None = None
    for h0 in starts:
        cost, h, delta, cov = _refine(h0, es, fs, ss, nvec, prior_inv, opts, estimate_rotation)
        if best is None or cost < best[0]:
            best = (cost, h, delta, cov)
    if best is None:  # pragma: no cover - starts always has one entry
        raise InvalidInputError("no heading hypothesis")
    _, h, delta, cov = best
    # (a 3-sigma gate keeps 97.3 % of a unit normal, whose truncated variance is 0.9733)
    res_s = coplanarity_residuals(h, es, fs, delta, opts.min_sin) / ss
    inl_res = res_s[np.abs(res_s) < opts.inlier_sigma]
    chi2 = float(np.sum(inl_res**2)) / max(inl_res.size - 5.0, 1.0) / 0.9733
    return h, delta, cov * max(chi2, 1.0)


def _final_inliers(
    h: FloatArray,
    delta: FloatArray,
    eu: FloatArray,
    fu: FloatArray,
    su: FloatArray,
    opts: HeadingOptions,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Final residuals (M,), in sigmas, and inlier flags (M,) for every usable point (M, 3
    bearings ``eu``, rates ``fu``, sigmas ``su``), and h (3,) signed so that the inliers
    lie in front (f_true . h < 0, noise allowed)."""
    res = coplanarity_residuals(h, eu, fu, delta, opts.min_sin) / su
    sin = np.maximum(np.sqrt(np.maximum(1.0 - (eu @ h) ** 2, 0.0)), opts.min_sin)
    inl_u = np.abs(res) < opts.inlier_sigma
    f_true = fu + cross(delta, eu)
    inl_u &= (f_true @ h) < opts.inlier_sigma * su * sin
    if np.sum(f_true[inl_u] @ h) > 0:
        h = -h
    return h, res, inl_u


def _check_motion_inputs(
    bearings: npt.ArrayLike,
    derotated: npt.ArrayLike,
    flow_sigma: float | npt.ArrayLike,
    rotation_prior_cov: npt.ArrayLike,
    fit_weights: npt.ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`estimate_motion`'s inputs as float64 arrays: e (N, 3), f (N, 3), sigma (N,),
    prior (3, 3), weights (N,); InvalidInputError quoting a wrong shape or value."""
    e = np.asarray(bearings, dtype=np.float64)
    f = np.asarray(derotated, dtype=np.float64)
    if e.ndim != 2 or e.shape[1] != 3 or f.shape != e.shape:
        raise InvalidInputError(
            f"bearings and derotated must both have shape (N, 3), got {e.shape} and {f.shape}"
        )
    sigma = np.broadcast_to(np.asarray(flow_sigma, dtype=np.float64), (e.shape[0],)).copy()
    prior = np.asarray(rotation_prior_cov, dtype=np.float64)
    if prior.shape != (3, 3):
        raise InvalidInputError(f"rotation_prior_cov must have shape (3, 3), got {prior.shape}")
    weights = np.ones(e.shape[0])
    if fit_weights is not None:
        weights = np.broadcast_to(np.asarray(fit_weights, dtype=np.float64), (e.shape[0],))
        if not np.all((weights > 0) & (weights <= 1)):
            raise InvalidInputError("fit_weights must lie in (0, 1]")
    return e, f, sigma, prior, weights


def estimate_motion(
    bearings: npt.ArrayLike,
    derotated: npt.ArrayLike,
    flow_sigma: float | npt.ArrayLike,
    rotation_prior_cov: npt.ArrayLike,
    *,
    options: HeadingOptions | None = None,
    rng: np.random.Generator | None = None,
    estimate_rotation: bool = True,
    initial_heading: npt.ArrayLike | None = None,
    fit_weights: npt.ArrayLike | None = None,
) -> MotionEstimate:
    """Robust joint estimate of the heading and the leftover rotation from N flows.

    Args:
        bearings: (N, 3) unit bearings e, camera frame.
        derotated: (N, 3) derotated bearing rates f, 1/s (gyro, minus current bias, removed).
        flow_sigma: scalar or (N,) 1-sigma noise of each component of f, 1/s.
        rotation_prior_cov: (3, 3) prior covariance of the leftover rotation delta (zero
            mean), (rad/s)^2, camera frame: bias uncertainty plus gyro noise.
        options: :class:`HeadingOptions`.
        rng: random generator for RANSAC (default: seeded, deterministic).
        estimate_rotation: False fixes delta = 0 (heading only, 2 unknowns).
        initial_heading: (3,) optional extra start (e.g. the previous frame's heading).
        fit_weights: (N,) optional weights in (0, 1] of the points in the heading fit
            (RANSAC and Gauss-Newton see the noise ``flow_sigma / sqrt(weight)``); whether
            the camera translates, the residuals and the inlier flags use ``flow_sigma``.

    Returns:
        :class:`MotionEstimate`.
    """
    opts = options or HeadingOptions()
    e, f, sigma, prior, weights = _check_motion_inputs(
        bearings, derotated, flow_sigma, rotation_prior_cov, fit_weights
    )
    n = e.shape[0]
    rng = rng or np.random.default_rng(0)
    usable = all_finite(e) & all_finite(f)
    usable &= np.isfinite(sigma) & (sigma > 0)
    residuals = np.full(n, np.nan)
    none_inliers = np.zeros(n, dtype=bool)
    zero3 = np.zeros(3)
    if int(usable.sum()) < opts.min_points:
        return MotionEstimate(
            None, np.inf, zero3, prior.copy(), False, none_inliers, residuals,
            f"too few points with flow for a heading: {int(usable.sum())} < {opts.min_points}",
        )  # fmt: skip
    eu, fu, su, wu = e[usable], f[usable], sigma[usable], weights[usable]
    # the estimate runs on an even subsample; residuals and flags cover every usable point
    sub = np.linspace(0, eu.shape[0] - 1, min(opts.max_points, eu.shape[0])).astype(np.int64)
    es, fs, ss, ws = eu[sub], fu[sub], su[sub], wu[sub]
    prior_inv: FloatArray = (
        np.asarray(np.linalg.inv(prior + 1e-18 * np.eye(3)), dtype=np.float64)
        if estimate_rotation
        else np.eye(3) * 1e18
    )

    # 1. Does a rotation alone explain the flow?
    rot_delta, rot_cov, rot_res = _rotation_only(es, fs, ss, prior_inv)
    robust_rms = float(median(rot_res)) / 1.1774  # median of a chi(2) variable
    flow_snr = float(median(row_norms(fs) / ss))
    if robust_rms < opts.still_ratio:
        r_all = fu - cross(eu, rot_delta)
        inl = np.zeros(n, dtype=bool)
        inl[usable] = np.sqrt(np.einsum("na,na->n", r_all, r_all)) / su < opts.inlier_sigma * 1.5
        hidden = robust_rms * float(median(ss))
        rot_delta, rot_cov = _with_hidden_translation(rot_delta, rot_cov, prior_inv, hidden)
        why = f"(residual {robust_rms:.2f} sigma, flow {flow_snr:.1f} sigma)"
        return MotionEstimate(
            None, np.inf, rot_delta, rot_cov, False, inl, residuals,
            "no translation: the flow is explained by a rotation alone " + why,
        )  # fmt: skip
    if flow_snr < opts.min_translation_snr:
        # Some flow is left after removing a rotation, but too little to tell translation
        # from rotation: no heading, and no information on the rotation either.
        return MotionEstimate(
            None, np.inf, zero3, prior.copy(), False, none_inliers, residuals,
            f"too little flow for a heading (median {flow_snr:.1f} sigma, rotation-only "
            f"residual {robust_rms:.2f} sigma): the translation is too slow or too far",
        )  # fmt: skip

    # 2. RANSAC on the heading with delta = 0: h = n_a x n_b for two random points.
    nvec = cross(es, fs)
    sw = ss / np.sqrt(ws)  # the fit's noise per point (fit_weights)
    starts = _heading_starts(es, fs, sw, nvec, prior, opts, rng, initial_heading)
    # 3. Gauss-Newton with Cauchy weights on (h, delta), prior on delta, from each start.
    h, delta, cov = _refine_best(starts, es, fs, sw, nvec, prior_inv, opts, estimate_rotation)
    h, res, inl_u = _final_inliers(h, delta, eu, fu, su, opts)
    residuals[usable] = res
    inliers = np.zeros(n, dtype=bool)
    inliers[usable] = inl_u
    if int(inl_u.sum()) < opts.min_points:
        return MotionEstimate(
            None, np.inf, zero3, prior.copy(), True, inliers, residuals,
            f"too few static points agree on a heading: {int(inl_u.sum())} < {opts.min_points}",
        )  # fmt: skip
    heading_sigma = float(np.sqrt(cov[0, 0] + cov[1, 1]))
    rot_cov = cov[2:, 2:] if estimate_rotation else prior.copy()
    return MotionEstimate(h, heading_sigma, delta, rot_cov, True, inliers, residuals)


def depth_edge_weights(
    pixels: npt.ArrayLike,
    bearings: npt.ArrayLike,
    rates: npt.ArrayLike,
    rate_sigma: float | npt.ArrayLike,
    heading: npt.ArrayLike | None,
    radius_px: float,
    log_scale: float,
    neighbours: int = 8,
    min_sin: float = 0.05,
    spread_factor: float = 1.4,
    neighbourhood: tuple[FloatArray, npt.NDArray[np.intp]] | None = None,
) -> FloatArray:
    """Heading-fit weights that set aside tracks near a depth edge.

    A Lucas-Kanade window across a depth edge holds two surfaces that move differently, and
    its track follows a mix of them: against exact reprojections on the cube scene, the
    tracks along the cube's outline read their flow 27 % long. The error stays with the
    feature while the edge crosses its window and is shared by every track along the edge,
    so it neither averages out over frames nor shows as a large coplanarity residual; it is
    absorbed into the leftover rotation, which the bias filter then accumulates (0.15
    mrad/s of bias on the cube scene, 0.06 deg of heading).

    A static point's translational flow has the magnitude ``|f| = |t| |h x e| / r``, so
    ``log(|f| / |h x e|) = log(|t| / r)``: the difference of that between two tracks is the
    log of their range ratio, whatever their distance to the focus of expansion. A track's
    edge score ``s`` is the largest such difference over its ``neighbours`` nearest tracks
    within ``radius_px``, and its weight ``1 / (1 + (s / log_scale)^4)``: 1 on a smooth
    surface, falling steeply across an edge. A track whose flow is within three times its
    noise, or which lies within ``min_sin`` of the focus of expansion, has no measurable
    range: it is neither judged nor judges its neighbours (weight 1 unless another pair
    says otherwise). Without a heading ``|h x e|`` is taken as 1 (neighbours near the
    focus of expansion then differ as their distances to it do).

    Where the flow is noisy the differences between neighbours on one surface exceed
    ``log_scale`` too, and the weights become noise (on a handheld real recording 46 % of
    the tracks fell below 1/2, and the heading moved 6 deg further from the two-view
    estimates). So the scale is ``max(log_scale, spread_factor * spread)``, ``spread`` the
    frame's typical neighbour difference (1.4826 times the median over all measured
    pairs): 0.04 to 0.07 on the synthetic scenes, where the scale stays ``log_scale``,
    0.14 on that recording.

    Args:
        pixels: (N, 2) pixel positions of the tracks, pixels.
        bearings: (N, 3) unit bearings e.
        rates: (N, 3) derotated bearing rates f, 1/s.
        rate_sigma: scalar or (N,) 1-sigma noise of each rate component, 1/s.
        heading: (3,) unit heading h (e.g. the last frame's), or None.
        radius_px: the neighbourhood's radius, pixels (about the LK window's side).
        log_scale: the change of log range at which the weight is 1/2.
        neighbours: the nearest tracks compared, besides the track itself.
        min_sin: floor of ``|h x e|``.
        spread_factor: the scale follows this many of the frame's neighbour spreads when
            that is larger than ``log_scale`` (0: always ``log_scale``).
        neighbourhood: the (N, K) distances (pixels, inf beyond the search radius) and
            indices of the K >= ``neighbours`` + 1 nearest of ``pixels`` to each of them
            (itself first), searched within at least ``radius_px``: a k-d tree query that
            another stage already made (its first ``neighbours`` + 1 columns within
            ``radius_px`` are the query this function makes without it).

    Returns:
        (N,) float64 weights in (0, 1].
    """
    px = np.asarray(pixels, dtype=np.float64)
    e = np.asarray(bearings, dtype=np.float64)
    f = np.asarray(rates, dtype=np.float64)
    n = px.shape[0]
    if px.shape != (n, 2) or e.shape != (n, 3) or f.shape != (n, 3):
        raise InvalidInputError(
            f"pixels must have shape (N, 2), bearings and rates (N, 3), got {px.shape}, "
            f"{e.shape} and {f.shape}"
        )
    if not (
        radius_px > 0 and log_scale > 0 and neighbours >= 1 and min_sin > 0 and spread_factor >= 0
    ):
        raise InvalidInputError(
            f"radius_px, log_scale and min_sin must be > 0, neighbours >= 1 and "
            f"spread_factor >= 0, got {radius_px}, {log_scale}, {min_sin}, {neighbours}, "
            f"{spread_factor}"
        )
    if n < 2:
        return np.ones(n)
    sigma = np.broadcast_to(np.asarray(rate_sigma, dtype=np.float64), (n,))
    mag = row_norms(f)
    measured = mag > 3.0 * sigma
    log_q = np.log(np.maximum(mag, 1e-300))
    if heading is not None:
        sin = row_norms(cross(np.asarray(heading, dtype=np.float64), e))
        measured &= sin > min_sin
        log_q -= np.log(np.maximum(sin, 1e-300))
    k = min(neighbours + 1, n)
    if neighbourhood is None:
        dist, nb = cKDTree(px).query(px, k=k, distance_upper_bound=radius_px)
    else:
        dist, nb = neighbourhood[0][:, :k], neighbourhood[1][:, :k]
        if dist.shape != (n, k):
            raise InvalidInputError(
                f"neighbourhood must have N = {n} rows and at least {k} columns, got "
                f"{neighbourhood[0].shape}"
            )
    itself = np.arange(n)[:, None]
    # missing (none within radius_px, as the query's strict bound): the point itself
    nb = np.where(dist < radius_px, nb, itself)
    pair = measured[:, None] & measured[nb]
    diff = np.where(pair, np.abs(log_q[nb] - log_q[:, None]), 0.0)
    scale = log_scale
    others = pair & (nb != itself)
    if spread_factor > 0 and others.any():
        scale = max(log_scale, spread_factor * MAD_TO_SIGMA * float(median(diff[others])))
    score = np.nan_to_num(diff.max(axis=1), nan=0.0)
    return np.asarray(1.0 / (1.0 + (score / scale) ** 4), dtype=np.float64)


def point_heading_disagreement(
    point_headings: npt.ArrayLike, heading: npt.ArrayLike
) -> FloatArray:
    """Angle between each per-point heading and the fused heading, rad (NaN where undefined).

    Args:
        point_headings: (N, 3) unit per-point headings (NaN rows allowed).
        heading: (3,) unit fused heading.

    Returns:
        (N,) float64 angles in [0, pi], rad.
    """
    ph = np.asarray(point_headings, dtype=np.float64)
    h = np.asarray(heading, dtype=np.float64)
    sin = np.linalg.norm(cross(ph, h), axis=-1)
    return np.asarray(np.arctan2(sin, ph @ h), dtype=np.float64)


class GyroBiasFilter:
    """Kalman filter on the gyro bias (IMU frame, rad/s) with a random-walk model.

    Args:
        camera_to_imu: (3, 3) rotation taking camera-frame vectors into the IMU frame
            (default identity).
        initial_sigma: 1-sigma of the initial bias, rad/s per axis.
        random_walk: bias random-walk density, rad/s/sqrt(s).
        initial_bias: (3,) initial bias, IMU frame, rad/s.
        adaptive_window: number of recent innovations from which the filter measures the
            frame-to-frame scatter its measurement covariances leave out (0 disables it);
            see :attr:`model_variance`.

    The measurement covariance a frame reports covers the flow noise only. On real
    recordings the leftover rotation of one frame also carries what the model leaves out
    (a residual time offset times the angular acceleration, rolling shutter, a slightly
    wrong extrinsic or focal length): on a handheld walk the frames scattered by 0.03 rad/s
    around a common value while each claimed 0.001. Trusting the claim, the first frame
    sets the bias and the gate then rejects every frame that disagrees. The filter
    therefore measures that extra scatter from its own innovations (covariance matching on
    a window of them, median based) and adds it to every measurement; where the claims
    hold, as on the synthetic scenes, it stays 0 and the filter is the plain one.
    """

    #: median of chi-square with 1 degree of freedom: median(z^2) = this x var(z)
    _CHI2_1_MEDIAN = 0.4549364231195724

    def __init__(
        self,
        camera_to_imu: npt.ArrayLike | None = None,
        initial_sigma: float = 0.02,
        random_walk: float = 1e-4,
        initial_bias: npt.ArrayLike = (0.0, 0.0, 0.0),
        adaptive_window: int = 30,
    ) -> None:
        cam_to_imu = (
            np.eye(3) if camera_to_imu is None else np.asarray(camera_to_imu, dtype=np.float64)
        )
        if cam_to_imu.shape != (3, 3):
            raise InvalidInputError(
                f"camera_to_imu must have shape (3, 3), got {cam_to_imu.shape}"
            )
        if not initial_sigma > 0 or not random_walk >= 0:
            raise InvalidInputError(
                f"initial_sigma must be > 0 and random_walk >= 0, got {initial_sigma}, "
                f"{random_walk}"
            )
        b0 = np.asarray(initial_bias, dtype=np.float64)
        if b0.shape != (3,):
            raise InvalidInputError(f"initial_bias must have shape (3,), got {b0.shape}")
        self._cam_to_imu = cam_to_imu
        self._initial_sigma = float(initial_sigma)
        self._random_walk = float(random_walk)
        if not (isinstance(adaptive_window, int) and adaptive_window >= 0):
            raise InvalidInputError(
                f"adaptive_window must be an int >= 0, got {adaptive_window!r}"
            )
        self._initial_bias = b0.copy()
        self._window = adaptive_window
        self.bias = b0.copy()
        self.cov = np.eye(3) * initial_sigma**2
        self.updates = 0
        self.rejected = 0
        self._excess: list[FloatArray] = []  # per frame: z^2 / median - 2 s, per direction
        self._claimed = 0.0  # running per-direction claimed measurement variance, (rad/s)^2
        self.model_variance = 0.0

    def reset(self) -> None:
        """Back to the initial bias and uncertainty."""
        self.bias = self._initial_bias.copy()
        self.cov = np.eye(3) * self._initial_sigma**2
        self.updates = 0
        self.rejected = 0
        self._excess = []
        self._claimed = 0.0
        self.model_variance = 0.0

    @property
    def bias_camera(self) -> FloatArray:
        """(3,) bias in the camera frame, rad/s."""
        return np.asarray(self._cam_to_imu.T @ self.bias, dtype=np.float64)

    @property
    def cov_camera(self) -> FloatArray:
        """(3, 3) bias covariance in the camera frame, (rad/s)^2."""
        return np.asarray(self._cam_to_imu.T @ self.cov @ self._cam_to_imu, dtype=np.float64)

    def predict(self, dt_s: float) -> None:
        """Grow the uncertainty by the random walk over ``dt_s`` seconds (>= 0)."""
        if not dt_s >= 0:
            raise InvalidInputError(f"dt_s must be >= 0, got {dt_s}")
        self.cov = self.cov + np.eye(3) * self._random_walk**2 * dt_s

    def update(
        self,
        rotation_error_cam: npt.ArrayLike,
        posterior_cov_cam: npt.ArrayLike,
        prior_cov_cam: npt.ArrayLike,
        inflation: float = 1.0,
        gate: float = 16.3,
        max_sigma: float = math.inf,
    ) -> bool:
        """Apply one frame's leftover-rotation estimate (camera frame, relative to ``bias``).

        :func:`estimate_motion` returns a posterior that already includes its prior
        ``prior_cov_cam`` (zero mean); the information the frame added is
        ``inv(posterior) - inv(prior)``. It is divided by ``inflation`` (>= 1; consecutive
        frames share tracks, so their errors are correlated) and fused with the current
        state. A leftover rotation delta means the true bias is ``bias - delta`` (rotated
        into the IMU frame).

        Args:
            rotation_error_cam: (3,) posterior delta, camera frame, rad/s.
            posterior_cov_cam: (3, 3) its posterior covariance, (rad/s)^2.
            prior_cov_cam: (3, 3) the prior covariance the estimate used, (rad/s)^2.
            inflation: measurement-information divisor, >= 1.
            gate: innovation gate: a posterior delta whose squared Mahalanobis distance under
                the prior exceeds this (chi-square, 3 dof; 16.3 = 99.9 %) is rejected as an
                outlier (e.g. translation mistaken for rotation). inf disables the gate.
            max_sigma: observability gate, rad/s: only the directions of the rotation in
                which this one frame determines it to better than ``max_sigma`` (1-sigma,
                before ``inflation``) update the bias; the others (e.g. a rotation the
                frame cannot tell from a translation) leave it where it is. inf: every
                direction.

        Returns:
            True when the measurement was applied, False when the gate rejected it.
        """
        d = np.asarray(rotation_error_cam, dtype=np.float64)
        c = np.asarray(posterior_cov_cam, dtype=np.float64)
        p = np.asarray(prior_cov_cam, dtype=np.float64)
        if d.shape != (3,) or c.shape != (3, 3) or p.shape != (3, 3) or not np.all(np.isfinite(d)):
            raise InvalidInputError(
                f"rotation error must be finite (3,) with (3, 3) covariances, got {d}, "
                f"{c.shape}, {p.shape}"
            )
        if not inflation >= 1.0:
            raise InvalidInputError(f"inflation must be >= 1, got {inflation}")
        info_post = np.linalg.inv(c)
        info_prior = np.linalg.inv(p)
        info_meas = info_post - info_prior
        vals, vecs = np.linalg.eigh(0.5 * (info_meas + info_meas.T))
        if self._window:
            self._match_scatter(vals, vecs, info_post @ d, inflation)
        if float(d @ info_prior @ d) > gate:
            self.rejected += 1
            return False
        q = self.model_variance
        if q > 0.0:  # the measurement, per eigen-direction, with the scatter added
            keep = vals > (1.0 / max_sigma**2 if math.isfinite(max_sigma) else 0.0)
            if not keep.any():
                return False
            vk, r = vecs[:, keep], inflation / vals[keep]
            z = (vk.T @ (info_post @ d)) / vals[keep]
            info_meas = (vk / (r + q)) @ vk.T
            y = vk @ (z / (r + q))
            return self._fuse(info_meas, y)
        if math.isfinite(max_sigma):
            keep = vals > 1.0 / max_sigma**2
            if not keep.any():
                return False
            vk = vecs[:, keep]
            info_meas = (vk * vals[keep]) @ vk.T / inflation
            # the frame's information vector, projected on the directions kept
            y = vk @ (vk.T @ (info_post @ d)) / inflation
        else:
            info_meas = (vecs * np.maximum(vals, 0.0)) @ vecs.T / inflation
            y = info_post @ d / inflation
        return self._fuse(info_meas, y)

    def _fuse(self, info_meas: FloatArray, y: FloatArray) -> bool:
        """Fuse a measurement given as information matrix (3, 3) and vector (3,) in the
        camera frame, delta space (the state's own mean there is 0); True."""
        cov_cam = self.cov_camera
        info_state = np.linalg.inv(cov_cam)
        new_cov_cam = np.linalg.inv(info_state + info_meas)
        delta = new_cov_cam @ y
        self.bias = self.bias - self._cam_to_imu @ delta
        self.cov = self._cam_to_imu @ new_cov_cam @ self._cam_to_imu.T
        self.cov = 0.5 * (self.cov + self.cov.T)
        self.updates += 1
        return True

    def _match_scatter(
        self, vals: FloatArray, vecs: FloatArray, info_vector: FloatArray, inflation: float
    ) -> None:
        """Update :attr:`model_variance` from this frame's innovation (every frame, the
        gated ones too: they are the evidence).

        Per eigen-direction j of the frame's information (``vals`` (3,), ``vecs`` (3, 3)
        columns), the measurement ``z_j`` (rad/s, relative to the state) has the claimed
        variance ``s_j = inflation / vals_j + v_j' P v_j``; where the claims hold,
        ``median(z^2) = 0.455 s``. The model variance is the median over the window of
        ``z^2 / 0.455 - 2 s`` (0 when negative): 0 while the claims hold up to a factor 2,
        the extra scatter when it dominates. When it grows, the state's covariance is
        scaled by ``(s + q_new) / (s + q_old)``: the measurements behind it had that
        scatter too. It is never scaled down (a few calm frames in the window do not make
        the earlier ones better than they were: scaling down after the first frames of a
        handheld walk left the filter as sure of its first reading as before).
        """
        ok = vals > 1e-12
        if not ok.any():
            return
        v = vecs[:, ok]
        z = (v.T @ info_vector) / vals[ok]
        s = inflation / vals[ok] + np.einsum("ij,ik,kj->j", v, self.cov_camera, v)
        self._excess.append(z**2 / self._CHI2_1_MEDIAN - 2.0 * s)
        self._excess = self._excess[-self._window :]
        claimed = float(np.mean(inflation / vals[ok]))
        self._claimed = claimed if self._claimed == 0.0 else 0.9 * self._claimed + 0.1 * claimed
        old = self.model_variance
        new = max(float(median(np.concatenate(self._excess))), 0.0)
        if new > old:  # never shrink: a window of calm frames proves less than the rest
            self.cov = self.cov * ((self._claimed + new) / (self._claimed + old))
        self.model_variance = new
