"""Per-point OWL mathematics, vectorised over N features (see docs/owl-math.md).

Conventions: camera optical frame (x right, y down, z forward); ``e`` unit bearings;
``f = de/dt + Omega x e`` the derotated bearing rate (1/s, tangent to the sphere at ``e``);
``L = (t.e)/r`` looming (1/s); ``omega = f x e = (e x t)/r`` perceived rotation (1/s);
``ToR = (L, omega)`` and ``RoT = ToR^-1 = (L, -omega)/(L^2 + |omega|^2)`` scalar-first
quaternions; ``r/|t| = 1/|ToR|`` (s); scaled point ``e r/|t|`` (s); per-point heading
``(L e + omega x e)/|ToR|``.

Nothing here divides by zero: every function that can be undefined returns a ``valid`` mask
and fills undefined entries with NaN.

The local looming rule: in a gnomonic chart centred on ``e`` (neighbour offset ``d`` on the
tangent plane, relative chart velocity ``dv``), a rigid smooth surface gives
``dv = L d + f (g.d) + c rot90(d)`` to first order, with ``g`` the surface slant and ``c`` a
curl that absorbs any leftover rotation. :func:`fit_local_looming` solves it per feature by
iteratively reweighted least squares (Cauchy weights), batched over all features.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from owl_core.errors import InvalidInputError
from owl_core.types import PointFlag

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: |ToR| (1/s) below which RoT, range_over_speed, the scaled point and the heading are undefined.
DEFAULT_MIN_TOR = 1e-9
#: A normal distribution's sigma per median absolute deviation (robust spreads).
MAD_TO_SIGMA = 1.4826


def cross(a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """Cross product over the last axis (broadcasting), faster than np.cross for small N.

    Args:
        a, b: (..., 3) float64 vectors.

    Returns:
        (..., 3) float64 a x b.
    """
    x = np.asarray(a, dtype=np.float64)
    y = np.asarray(b, dtype=np.float64)
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    y0, y1, y2 = y[..., 0], y[..., 1], y[..., 2]
    return np.stack([x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0], axis=-1)


def row_norms(v: FloatArray) -> FloatArray:
    """Euclidean norms of vectors of 2 or 3 components, ``np.linalg.norm(v, axis=-1)``.

    The same values (the squares summed in the same order), several times faster on such
    short rows than a reduction over the last axis.

    Args:
        v: (..., 2) or (..., 3) float64 vectors.

    Returns:
        (...,) float64 norms.
    """
    squares = v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1]
    if v.shape[-1] == 3:
        squares += v[..., 2] * v[..., 2]
    out: FloatArray = np.sqrt(squares)
    return out


def all_finite(v: FloatArray) -> BoolArray:
    """Whether every component of each vector is finite, ``np.all(np.isfinite(v), axis=-1)``,
    one component at a time (a reduction over a short last axis costs several times more).

    Args:
        v: (..., K) float64 vectors, K >= 1 (a few components).

    Returns:
        (...,) bool.
    """
    out: BoolArray = np.isfinite(v[..., 0])
    for i in range(1, v.shape[-1]):
        out &= np.isfinite(v[..., i])
    return out


def median(values: FloatArray) -> np.float64:
    """:func:`np.median` of a 1-D float64 array, the same value (NaN if any entry is), at a
    fraction of its cost on a frame's arrays (its general machinery for axes, output
    arrays and the NaN check costs more than the partition itself).

    Args:
        values: (N,) float64.

    Returns:
        The median, a float64 scalar: the mean of the two middle values for even N (NaN
        for N = 0, with NumPy's warning).
    """
    n = values.shape[0]
    if n == 0:
        return np.float64(np.median(values))
    mid = n // 2
    if n % 2:
        part = np.partition(values, (mid, -1))  # the largest last: NaN if there is one
        result = part[mid]
    else:
        part = np.partition(values, (mid - 1, mid, -1))
        result = (part[mid - 1] + part[mid]) / 2.0
    last = part[-1]
    return np.float64(last if np.isnan(last) else result)


def _as_vectors(name: str, value: npt.ArrayLike, dim: int = 3) -> FloatArray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise InvalidInputError(f"{name} must have shape (N, {dim}), got {arr.shape}")
    return arr


def _as_scalars(name: str, value: npt.ArrayLike, n: int) -> FloatArray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (n,):
        raise InvalidInputError(f"{name} must have shape ({n},), got {arr.shape}")
    return arr


def _check_same_n(**arrays: FloatArray) -> int:
    sizes = {name: a.shape[0] for name, a in arrays.items()}
    if len(set(sizes.values())) > 1:
        raise InvalidInputError(f"arrays must share the first dimension N, got {sizes}")
    return next(iter(sizes.values())) if sizes else 0


def derotate(
    bearings: npt.ArrayLike, bearing_rates: npt.ArrayLike, angular_velocity: npt.ArrayLike
) -> FloatArray:
    """Remove the camera rotation from bearing rates: ``f = de/dt + Omega x e``.

    Args:
        bearings: (N, 3) float64 unit bearings e, camera frame.
        bearing_rates: (N, 3) float64 de/dt, 1/s (includes the camera rotation).
        angular_velocity: (3,) or (N, 3) float64 camera angular velocity Omega, rad/s.

    Returns:
        (N, 3) float64 derotated bearing rates f, 1/s.
    """
    e = _as_vectors("bearings", bearings)
    de = _as_vectors("bearing_rates", bearing_rates)
    _check_same_n(bearings=e, bearing_rates=de)
    w = np.asarray(angular_velocity, dtype=np.float64)
    if w.shape not in ((3,), e.shape):
        raise InvalidInputError(
            f"angular_velocity must have shape (3,) or {e.shape}, got {w.shape}"
        )
    return de + cross(w, e)


def perceived_rotation(bearings: npt.ArrayLike, derotated: npt.ArrayLike) -> FloatArray:
    """Perceived rotation ``omega = f x e`` (= (e x t)/r), 1/s.

    Args:
        bearings: (N, 3) float64 unit bearings e.
        derotated: (N, 3) float64 derotated bearing rates f, 1/s.

    Returns:
        (N, 3) float64 omega, 1/s, perpendicular to e.
    """
    e = _as_vectors("bearings", bearings)
    f = _as_vectors("derotated", derotated)
    _check_same_n(bearings=e, derotated=f)
    return cross(f, e)


@dataclass(frozen=True)
class OwlQuantities:
    """The quantities built from L and omega, N points.

    Attributes:
        tor: (N, 4) float64 ToR = (L, omega) scalar-first, 1/s.
        rot: (N, 4) float64 RoT = ToR^-1 scalar-first, s (NaN where invalid).
        range_over_speed: (N,) float64 r/|t| = 1/|ToR|, s (NaN where invalid).
        points: (N, 3) float64 scaled points e r/|t|, s (NaN where invalid).
        heading: (N, 3) float64 per-point unit heading t/|t| (NaN where invalid).
        alpha: (N,) float64 angle between heading and bearing, rad (NaN where invalid).
        valid: (N,) bool, False where |ToR| <= min_tor (no translation) or inputs not finite.
    """

    tor: FloatArray
    rot: FloatArray
    range_over_speed: FloatArray
    points: FloatArray
    heading: FloatArray
    alpha: FloatArray
    valid: BoolArray


def owl_quantities(
    bearings: npt.ArrayLike,
    looming: npt.ArrayLike,
    omega: npt.ArrayLike,
    min_tor: float = DEFAULT_MIN_TOR,
) -> OwlQuantities:
    """ToR, RoT, r/|t|, scaled point and per-point heading from L and omega.

    Args:
        bearings: (N, 3) float64 unit bearings e.
        looming: (N,) float64 L, 1/s.
        omega: (N, 3) float64 perceived rotation, 1/s.
        min_tor: |ToR| threshold, 1/s; at or below it the point has no translation signal.

    Returns:
        :class:`OwlQuantities` with a ``valid`` mask; invalid entries are NaN.
    """
    e = _as_vectors("bearings", bearings)
    w = _as_vectors("omega", omega)
    n = _check_same_n(bearings=e, omega=w)
    lo = _as_scalars("looming", looming, n)
    if not min_tor >= 0.0:
        raise InvalidInputError(f"min_tor must be >= 0, got {min_tor}")
    tor = np.concatenate([lo[:, None], w], axis=1)
    norm2 = np.einsum("ij,ij->i", tor, tor)
    finite = np.isfinite(norm2) & all_finite(e)
    valid = finite & (norm2 > min_tor * min_tor)
    safe2 = np.where(valid, norm2, 1.0)
    norm = np.sqrt(safe2)
    rot = np.concatenate([lo[:, None], -w], axis=1) / safe2[:, None]
    range_over_speed = 1.0 / norm
    points = e * range_over_speed[:, None]
    heading = (lo[:, None] * e + cross(w, e)) / norm[:, None]
    alpha = np.arctan2(row_norms(w), lo)
    nan = ~valid
    rot[nan] = np.nan
    range_over_speed[nan] = np.nan
    points[nan] = np.nan
    heading[nan] = np.nan
    alpha[nan] = np.nan
    return OwlQuantities(tor, rot, range_over_speed, points, heading, alpha, valid)


def tangent_basis(bearings: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """An orthonormal tangent basis (u1, u2) at each bearing, with u1 x u2 = e.

    Args:
        bearings: (N, 3) float64 unit bearings.

    Returns:
        u1, u2: (N, 3) float64 each.
    """
    e = _as_vectors("bearings", bearings)
    # Pick the axis least aligned with e as the helper, so the cross product never vanishes.
    least = np.argmin(np.abs(e), axis=1)
    h0, h1, h2 = ((least == i).astype(np.float64) for i in range(3))
    e0, e1, e2 = e[:, 0], e[:, 1], e[:, 2]
    # u1 = helper x e, then normalised; u2 = e x u1 (written out per component: the same
    # operations as cross() on the same values, without its stacking and the norm's
    # reduction over the short last axis)
    a0, a1, a2 = h1 * e2 - h2 * e1, h2 * e0 - h0 * e2, h0 * e1 - h1 * e0
    norm = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    a0, a1, a2 = a0 / norm, a1 / norm, a2 / norm
    u1 = np.stack([a0, a1, a2], axis=1)
    u2 = np.stack([e1 * a2 - e2 * a1, e2 * a0 - e0 * a2, e0 * a1 - e1 * a0], axis=1)
    return u1, u2


def _chart_components(
    bearings: FloatArray,
    derotated: FloatArray,
    neighbour_bearings: FloatArray,
    neighbour_derotated: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`gnomonic_chart` per chart axis: d1, d2, v1, v2 (N, k) (offsets and relative
    velocities) and fa, fb (N,) (the centre's chart velocity), as separate arrays.

    Every product is written out over the (N, k) component arrays (a batched matmul of
    (k, 3) by (3, 2) blocks costs several times more for these small blocks).
    """
    u1, u2 = tangent_basis(bearings)
    nb = np.moveaxis(neighbour_bearings, -1, 0)  # (3, N, k) views, no copy
    nf = np.moveaxis(neighbour_derotated, -1, 0)

    def dot(v: FloatArray, u: FloatArray) -> FloatArray:
        out: FloatArray = v[0] * u[:, 0:1] + v[1] * u[:, 1:2] + v[2] * u[:, 2:3]
        return out

    # (the bearing itself is orthogonal to the basis, so b/(b.e) - e projects as b/(b.e))
    cos = dot(nb, bearings)
    inv = 1.0 / np.where(cos > 1e-6, cos, np.nan)
    p1, p2 = dot(nb, u1), dot(nb, u2)
    fa = np.einsum("nc,nc->n", derotated, u1)
    fb = np.einsum("nc,nc->n", derotated, u2)
    scale = dot(nf, bearings) * inv * inv
    v1 = dot(nf, u1) * inv - p1 * scale - fa[:, None]
    v2 = dot(nf, u2) * inv - p2 * scale - fb[:, None]
    return p1 * inv, p2 * inv, v1, v2, fa, fb


def gnomonic_chart(
    bearings: FloatArray,
    derotated: FloatArray,
    neighbour_bearings: FloatArray,
    neighbour_derotated: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Neighbour offsets and relative velocities in the gnomonic chart centred on each e.

    The chart maps a bearing b to ``b/(b.e) - e`` on the tangent plane at e; its time
    derivative for a point moving with ``db/dt = f_b`` is ``f_b/(b.e) - b (f_b.e)/(b.e)^2``.
    The chart axes are :func:`tangent_basis` (u1, u2).

    Args:
        bearings: (N, 3) unit bearings e (chart centres).
        derotated: (N, 3) derotated rates f at e, 1/s.
        neighbour_bearings: (N, k, 3) unit bearings of the neighbours.
        neighbour_derotated: (N, k, 3) derotated rates of the neighbours, 1/s.

    Returns:
        d: (N, k, 2) chart offsets (tan of the angle, dimensionless), NaN for a neighbour
        90 degrees or more away;
        dv: (N, k, 2) chart velocity of each neighbour minus that of the centre, 1/s;
        f2: (N, 2) chart velocity of the centre (= f in the tangent basis), 1/s.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        d1, d2, v1, v2, fa, fb = _chart_components(
            bearings, derotated, neighbour_bearings, neighbour_derotated
        )
    return np.stack([d1, d2], axis=-1), np.stack([v1, v2], axis=-1), np.stack([fa, fb], axis=-1)


@dataclass(frozen=True)
class LocalFit:
    """Result of the local looming rule for N features.

    Attributes:
        looming: (N,) float64 L, 1/s (NaN where invalid).
        variance: (N,) float64 variance of L, 1/s^2 (inf where invalid).
        slant: (N, 2) float64 g = -grad ln(depth) in the chart basis (NaN where invalid).
        curl: (N,) float64 curl c, rad/s (a leftover rotation about e shows up here).
        residual_rms: (N,) float64 weighted RMS residual of the fit, 1/s.
        quality: (N,) float64 in [0, 1]; 1 = residual at the noise level or below.
        num_used: (N,) int64 neighbours with non-negligible robust weight.
        valid: (N,) bool, False with too few neighbours or an ill-conditioned fit.
    """

    looming: FloatArray
    variance: FloatArray
    slant: FloatArray
    curl: FloatArray
    residual_rms: FloatArray
    quality: FloatArray
    num_used: npt.NDArray[np.int64]
    valid: BoolArray


def _check_neighbours(
    n: int,
    neighbour_bearings: npt.ArrayLike,
    neighbour_derotated: npt.ArrayLike,
    neighbour_mask: npt.ArrayLike | None,
    min_neighbours: int,
    noise: float,
    iterations: int,
) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
    """:func:`fit_local_looming`'s neighbour inputs: bearings and rates (N, k, 3) and the
    (N, k) mask; InvalidInputError quoting a wrong shape or value."""
    nb = np.asarray(neighbour_bearings, dtype=np.float64)
    nf = np.asarray(neighbour_derotated, dtype=np.float64)
    if nb.ndim != 3 or nb.shape[0] != n or nb.shape[2] != 3:
        raise InvalidInputError(f"neighbour_bearings must have shape ({n}, k, 3), got {nb.shape}")
    if nf.shape != nb.shape:
        raise InvalidInputError(f"neighbour_derotated must have shape {nb.shape}, got {nf.shape}")
    k = nb.shape[1]
    if neighbour_mask is None:
        mask = np.ones((n, k), dtype=bool)
    else:
        mask = np.asarray(neighbour_mask, dtype=bool)
        if mask.shape != (n, k):
            raise InvalidInputError(f"neighbour_mask must have shape ({n}, {k}), got {mask.shape}")
    if min_neighbours < 2:
        raise InvalidInputError(f"min_neighbours must be >= 2, got {min_neighbours}")
    if not noise > 0.0:
        raise InvalidInputError(f"noise must be > 0, got {noise}")
    if iterations < 0:
        raise InvalidInputError(f"iterations must be >= 0, got {iterations}")
    return nb, nf, mask


def _local_fit_result(
    x: FloatArray,
    inv00: FloatArray,
    weights: FloatArray,
    resid: FloatArray,
    good: npt.NDArray[np.bool_],
    normal00: FloatArray,
    radius: FloatArray,
    noise: float,
    min_neighbours: int,
    max_l_sigma: float,
) -> LocalFit:
    """The :class:`LocalFit` from the last IRLS solve: x (N, 4) = (L, g1, g2, c), the
    (0, 0) element of the inverse normal matrix (N,), weights and residuals (N, k), the
    (0, 0) element of the normal matrix (N,)."""
    wsum = np.sum(weights, axis=1)
    used = np.sum(weights > 0.5, axis=1)
    dof = np.maximum(2.0 * wsum - 4.0, 1.0)
    rms = np.sqrt(np.sum(weights * resid**2, axis=1) / dof)
    sigma2 = np.maximum(rms, noise) ** 2
    # L and c are observable from the offsets alone (their normal block is sum |d|^2 I).
    valid = good & (used >= min_neighbours) & (normal00 > 0)
    valid &= all_finite(x) & np.isfinite(inv00)
    cov00 = np.where(valid, inv00, 1.0) / radius**2
    variance = np.where(valid, sigma2 * cov00, np.inf)
    valid &= np.sqrt(variance) <= max_l_sigma
    variance = np.where(valid, variance, np.inf)
    quality = np.where(valid, 1.0 / (1.0 + (np.maximum(rms - noise, 0.0) / noise) ** 2), 0.0)
    looming = np.where(valid, x[:, 0], np.nan)
    slant = np.where(valid[:, None], x[:, 1:3], np.nan)
    curl = np.where(valid, x[:, 3], np.nan)
    return LocalFit(looming, variance, slant, curl, rms, quality, used.astype(np.int64), valid)


def _cauchy_weights(
    resid: FloatArray, mask: npt.NDArray[np.bool_], noise: float, robust_scale: float
) -> FloatArray:
    """IRLS weights (N, k) ``1/(1 + (res/(robust_scale * s))^2)``; s per feature = the
    median absolute residual over its used neighbours x ``MAD_TO_SIGMA``, at least ``noise``."""
    ordered = np.sort(np.where(mask, resid, np.inf), axis=1)  # masked last
    mid = np.maximum(mask.sum(axis=1) - 1, 0) // 2
    med = np.take_along_axis(ordered, mid[:, None], axis=1)[:, 0]
    scale = np.maximum(np.where(np.isfinite(med), med, noise) * MAD_TO_SIGMA, noise)
    u = resid / (robust_scale * scale[:, None])
    return np.asarray(mask / (1.0 + u * u), dtype=np.float64)


def _normal_system(
    d1: FloatArray,
    d2: FloatArray,
    v1: FloatArray,
    v2: FloatArray,
    fa: FloatArray,
    fb: FloatArray,
    weights: FloatArray,
) -> tuple[list[FloatArray], list[FloatArray]]:
    """The local rule's weighted normal equations per feature, as (N,) arrays: the lower
    triangle (a00, a10, a11, a20, a21, a22, a30, a31, a32, a33) of the symmetric 4x4
    matrix for x = (L, g1, g2, c) (no slant prior yet) and the right-hand side b0..b3.

    From chart offsets d1, d2, relative velocities v1, v2 and weights (all (N, k)) and the
    feature's chart rate fa, fb (N,). Per neighbour the two rows are
    ``dv_a = L d_a + f_a (g . d) + c rot90(d)_a`` (a = 1, 2), so every entry is a
    combination of the seven weighted sums ``S_ij = sum w d_i d_j`` and
    ``T_ij = sum w d_i v_j``.
    """

    def wsum(a: FloatArray, b: FloatArray) -> FloatArray:
        out: FloatArray = np.einsum("nk,nk->n", a, b)
        return out

    w1, w2 = weights * d1, weights * d2
    s11, s12, s22 = wsum(w1, d1), wsum(w1, d2), wsum(w2, d2)
    t11, t12, t21, t22 = wsum(w1, v1), wsum(w1, v2), wsum(w2, v1), wsum(w2, v2)
    ff = fa * fa + fb * fb
    dd = s11 + s22
    zero = np.zeros_like(dd)
    lower = [
        dd,  # L, L
        fa * s11 + fb * s12,  # g1, L: sum d1 (f.d)
        ff * s11,  # g1, g1: |f|^2 sum d1 d1
        fa * s12 + fb * s22,  # g2, L
        ff * s12,  # g2, g1
        ff * s22,  # g2, g2
        zero,  # c, L: L and c do not couple
        fb * s11 - fa * s12,  # c, g1: -sum d1 (f x d)
        fb * s12 - fa * s22,  # c, g2
        dd,  # c, c
    ]
    rhs = [
        t11 + t22,  # sum d.dv
        fa * t11 + fb * t12,  # sum d1 (f.dv)
        fa * t21 + fb * t22,  # sum d2 (f.dv)
        t12 - t21,  # sum d x dv
    ]
    return lower, rhs


def fit_local_looming(
    bearings: npt.ArrayLike,
    derotated: npt.ArrayLike,
    neighbour_bearings: npt.ArrayLike,
    neighbour_derotated: npt.ArrayLike,
    neighbour_mask: npt.ArrayLike | None = None,
    *,
    noise: float = 1e-3,
    min_neighbours: int = 4,
    iterations: int = 3,
    robust_scale: float = 3.0,
    slant_prior: float = 100.0,
    max_l_sigma: float = np.inf,
) -> LocalFit:
    """Fit ``dv = L d + f (g.d) + c rot90(d)`` per feature (owl-math.md rules 2-4).

    Batched over features: the normal equations of all N features are built from seven
    weighted sums per feature (:func:`_normal_system`) and solved at once by a written-out
    Cholesky factorisation. Cauchy weights ``1/(1 + (res/(robust_scale * s))^2)``, with
    ``s = max(noise, robust residual scale)``, down-weight neighbours across a depth or
    motion boundary.

    Args:
        bearings: (N, 3) unit bearings e.
        derotated: (N, 3) derotated bearing rates f, 1/s.
        neighbour_bearings: (N, k, 3) neighbour bearings.
        neighbour_derotated: (N, k, 3) neighbour derotated rates, 1/s.
        neighbour_mask: (N, k) bool, False for missing neighbours (default all True).
        noise: 1-sigma noise of one neighbour's relative chart velocity, 1/s per axis; floor
            of the residual scale used for weights, variance and quality.
        min_neighbours: fewer usable neighbours than this -> invalid (at least 2).
        iterations: IRLS iterations after the initial least-squares solve.
        robust_scale: Cauchy scale in units of the residual scale.
        slant_prior: 1-sigma prior on each slant component (dimensionless); it keeps the
            fit solvable at the focus of expansion (f = 0), where g is unobservable.
        max_l_sigma: fits whose standard deviation of L exceeds this (1/s) are invalid.

    Returns:
        :class:`LocalFit`.
    """
    e = _as_vectors("bearings", bearings)
    f = _as_vectors("derotated", derotated)
    n = _check_same_n(bearings=e, derotated=f)
    nb, nf, mask = _check_neighbours(
        n,
        neighbour_bearings,
        neighbour_derotated,
        neighbour_mask,
        min_neighbours,
        noise,
        iterations,
    )
    d1, d2, v1, v2, fa, fb = _chart_components(e, f, nb, nf)
    mask = mask & np.isfinite(d1) & np.isfinite(d2) & np.isfinite(v1) & np.isfinite(v2)
    d1, d2 = np.where(mask, d1, 0.0), np.where(mask, d2, 0.0)
    v1, v2 = np.where(mask, v1, 0.0), np.where(mask, v2, 0.0)
    count = mask.sum(axis=1)
    # Normalise by the neighbourhood size so conditioning does not depend on the radius.
    radius = np.sqrt(np.sum(d1 * d1 + d2 * d2, axis=1) / np.maximum(count, 1))
    radius = np.where(radius > 0, radius, 1.0)
    r2 = radius**2
    ridge = np.maximum(noise**2 / (slant_prior**2 * r2), 1e-14)  # slant prior on g1, g2
    ok = count >= min_neighbours
    identity = np.array([1.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])[:, None]  # lower I
    weights = mask.astype(np.float64)
    fa2, fb2 = fa[:, None], fb[:, None]
    for it in range(iterations + 1):
        lower, rhs = _normal_system(d1, d2, v1, v2, fa, fb, weights)
        system = np.array(lower) / r2  # (10, N) lower triangles
        good = ok & np.isfinite(system).all(axis=0)
        # the identity for features without a usable system (their x is discarded)
        a = np.where(good, system, identity)
        a[2] = np.where(good, system[2] + ridge, 1.0)
        a[5] = np.where(good, system[5] + ridge, 1.0)
        x, inv00 = _solve_spd4_lower(list(a), list(np.array(rhs) / r2))
        lo, g1, g2, c = (x[:, j : j + 1] for j in range(4))
        slope = g1 * d1 + g2 * d2
        r_1 = v1 - (lo * d1 + fa2 * slope - c * d2)
        r_2 = v2 - (lo * d2 + fb2 * slope + c * d1)
        resid = np.sqrt(r_1 * r_1 + r_2 * r_2)
        if it == iterations:
            break
        weights = _cauchy_weights(resid, mask, noise, robust_scale)
    return _local_fit_result(
        x, inv00, weights, resid, good, system[0], radius, noise, min_neighbours, max_l_sigma
    )


def _solve_spd4(a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Batched Cholesky solve of symmetric positive-definite 4x4 systems, written out.

    Faster than ``np.linalg.solve`` plus ``np.linalg.inv`` for the many small systems of
    :func:`fit_local_looming` (every step is one operation on (N,) arrays).

    Args:
        a: (N, 4, 4) float64 symmetric positive-definite matrices (lower triangle read).
        b: (N, 4) float64 right-hand sides.

    Returns:
        x: (N, 4) float64 solutions of ``a x = b``; NaN rows where ``a`` is not
        positive definite. inv00: (N,) float64 ``inv(a)[0, 0]`` (NaN likewise).
    """
    lower = [a[:, i, j] for i in range(4) for j in range(i + 1)]
    return _solve_spd4_lower(lower, [b[:, i] for i in range(4)])


def _solve_spd4_lower(a: list[FloatArray], b: list[FloatArray]) -> tuple[FloatArray, FloatArray]:
    """:func:`_solve_spd4` from the lower triangle row by row, a = [a00, a10, a11, a20,
    a21, a22, a30, a31, a32, a33] and b = [b0, b1, b2, b3], each (N,)."""

    def root(v: FloatArray) -> FloatArray:
        out: FloatArray = np.sqrt(np.where(v > 0, v, np.nan))
        return out

    a00, a10, a11, a20, a21, a22, a30, a31, a32, a33 = a
    with np.errstate(invalid="ignore", divide="ignore"):
        l00 = root(a00)
        l10, l20, l30 = a10 / l00, a20 / l00, a30 / l00
        l11 = root(a11 - l10 * l10)
        l21 = (a21 - l20 * l10) / l11
        l31 = (a31 - l30 * l10) / l11
        l22 = root(a22 - l20 * l20 - l21 * l21)
        l32 = (a32 - l30 * l20 - l31 * l21) / l22
        l33 = root(a33 - l30 * l30 - l31 * l31 - l32 * l32)
        y0 = b[0] / l00
        y1 = (b[1] - l10 * y0) / l11
        y2 = (b[2] - l20 * y0 - l21 * y1) / l22
        y3 = (b[3] - l30 * y0 - l31 * y1 - l32 * y2) / l33
        x3 = y3 / l33
        x2 = (y2 - l32 * x3) / l22
        x1 = (y1 - l21 * x2 - l31 * x3) / l11
        x0 = (y0 - l10 * x1 - l20 * x2 - l30 * x3) / l00
        # inv(a)[0, 0] = |z|^2 with low z = e0
        z0 = 1.0 / l00
        z1 = -l10 * z0 / l11
        z2 = -(l20 * z0 + l21 * z1) / l22
        z3 = -(l30 * z0 + l31 * z1 + l32 * z2) / l33
    inv00: FloatArray = z0 * z0 + z1 * z1 + z2 * z2 + z3 * z3
    return np.stack([x0, x1, x2, x3], axis=1), inv00


@dataclass(frozen=True)
class HeadingRoute:
    """L from the heading route for N features.

    Attributes:
        looming: (N,) float64 L = |omega| cot(alpha), 1/s (NaN where invalid).
        variance: (N,) float64 variance of L, 1/s^2 (inf where invalid).
        valid: (N,) bool, False near the focus of expansion (sin(alpha) < min_sin).
    """

    looming: FloatArray
    variance: FloatArray
    valid: BoolArray


def looming_from_heading(
    bearings: npt.ArrayLike,
    omega: npt.ArrayLike,
    heading: npt.ArrayLike,
    *,
    omega_sigma: float | npt.ArrayLike = 1e-3,
    heading_sigma: float = 0.0,
    min_sin: float = 0.05,
) -> HeadingRoute:
    """L by the heading route, signed: ``L = (|t|/r) cos(alpha)``, ``|t|/r`` from omega.

    With ``h`` the unit heading, ``omega = (|t|/r) (e x h)``, so the least-squares speed ratio
    is ``s = omega.(e x h)/|e x h|^2`` and ``L = s (h.e)`` (= |omega| cot(alpha) when omega
    agrees with the heading).

    Args:
        bearings: (N, 3) unit bearings e.
        omega: (N, 3) perceived rotation, 1/s.
        heading: (3,) unit translation direction.
        omega_sigma: scalar or (N,) 1-sigma error of each omega component, 1/s.
        heading_sigma: 1-sigma angular error of the heading, rad.
        min_sin: points with sin(alpha) below this (near the focus of expansion or its
            antipode) get no L from this route.

    Returns:
        :class:`HeadingRoute`.
    """
    e = _as_vectors("bearings", bearings)
    w = _as_vectors("omega", omega)
    _check_same_n(bearings=e, omega=w)
    h = np.asarray(heading, dtype=np.float64)
    if h.shape != (3,) or not np.all(np.isfinite(h)) or np.linalg.norm(h) == 0:
        raise InvalidInputError(f"heading must be a finite non-zero (3,) vector, got {h!r}")
    h = h / np.linalg.norm(h)
    exh = cross(e, h)
    sin2 = np.einsum("ij,ij->i", exh, exh)
    cos = e @ h
    valid = (sin2 > min_sin * min_sin) & all_finite(w)
    safe2 = np.where(valid, sin2, 1.0)
    speed = np.einsum("ij,ij->i", w, exh) / safe2
    looming = speed * cos
    sig = np.broadcast_to(np.asarray(omega_sigma, dtype=np.float64), cos.shape)
    # dL/domega along (e x h) is cos/sin; dL/dalpha = -|t|/r (for fixed |t|/r along e x h).
    variance = sig**2 * cos**2 / safe2 + (speed * heading_sigma) ** 2 / safe2
    return HeadingRoute(np.where(valid, looming, np.nan), np.where(valid, variance, np.inf), valid)


@dataclass(frozen=True)
class FusedLooming:
    """Variance-weighted fusion of the two L routes.

    Attributes:
        looming: (N,) float64 fused L, 1/s (NaN where neither route gave one).
        variance: (N,) float64, 1/s^2 (inf where invalid).
        flags: (N,) uint8 PointFlag.L_LOCAL / L_HEADING bits of the routes used.
        valid: (N,) bool.
    """

    looming: FloatArray
    variance: FloatArray
    flags: npt.NDArray[np.uint8]
    valid: BoolArray


def fuse_looming(
    local: LocalFit | None,
    heading: HeadingRoute | None,
    n: int,
    max_disagreement: float = 4.0,
    local_variance_scale: float = 1.0,
) -> FusedLooming:
    """Fuse L from the local rule and the heading route by inverse variance.

    When both routes exist but disagree by more than ``max_disagreement`` combined sigmas,
    only the local rule is kept (it makes no static-scene assumption).

    Args:
        local: local-rule fit for the N features, or None.
        heading: heading-route L for the N features, or None.
        n: number of features N.
        max_disagreement: gating threshold, in combined standard deviations.
        local_variance_scale: the local rule's variance is taken as its stated variance
            times this (> 0) in the gate, the weights and the fused variance.

    Returns:
        :class:`FusedLooming`.
    """
    zero = np.zeros(n, dtype=bool)
    l_ok = local.valid & np.isfinite(local.variance) if local is not None else zero
    h_ok = heading.valid & np.isfinite(heading.variance) if heading is not None else zero
    l_val = local.looming if local is not None else np.full(n, np.nan)
    l_var = local.variance * local_variance_scale if local is not None else np.full(n, np.inf)
    h_val = heading.looming if heading is not None else np.full(n, np.nan)
    h_var = heading.variance if heading is not None else np.full(n, np.inf)
    both = l_ok & h_ok
    gap = np.abs(np.where(both, l_val - h_val, 0.0))
    agree = gap <= max_disagreement * np.sqrt(np.where(both, l_var + h_var, 1.0))
    h_use = h_ok & (~l_ok | agree)
    wl = np.where(l_ok, 1.0 / np.maximum(np.where(l_ok, l_var, 1.0), 1e-300), 0.0)
    wh = np.where(h_use, 1.0 / np.maximum(np.where(h_use, h_var, 1.0), 1e-300), 0.0)
    wsum = wl + wh
    valid = wsum > 0
    safe = np.where(valid, wsum, 1.0)
    fused = (wl * np.nan_to_num(l_val) + wh * np.nan_to_num(h_val)) / safe
    flags = np.where(l_ok, np.uint8(PointFlag.L_LOCAL), np.uint8(0)) | np.where(
        h_use, np.uint8(PointFlag.L_HEADING), np.uint8(0)
    )
    return FusedLooming(
        np.where(valid, fused, np.nan),
        np.where(valid, 1.0 / safe, np.inf),
        flags.astype(np.uint8),
        valid,
    )
