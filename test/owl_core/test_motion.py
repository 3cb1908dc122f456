"""Properties of owl_core.motion on exact synthetic motion fields (planes seen by a camera).

The motion field is exact: de/dt = -(t - (t.e)e)/r - Omega x e, so everything the first-order
local rule does not model is second order in the neighbourhood radius (0.01 rad here).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from owl_core import motion
from owl_core.errors import InvalidInputError
from owl_core.types import PointFlag

RNG_SEED = 7


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def plane_scene(
    t: np.ndarray, omega_cam: np.ndarray, n_points: int = 50, k: int = 12, radius: float = 0.01
) -> dict[str, np.ndarray]:
    """Features and neighbours on the plane z + 0.2 x = 10 (camera frame), exact rates."""
    rng = np.random.default_rng(RNG_SEED)
    normal = _unit(np.array([0.2, 0.0, 1.0]))
    dist = 10.0 / np.linalg.norm([0.2, 0.0, 1.0])
    e = _unit(np.column_stack([rng.uniform(-0.5, 0.5, (n_points, 2)), np.ones(n_points)]))
    ang = rng.uniform(0, 2 * np.pi, (n_points, k))
    rad = rng.uniform(0.3, 1.0, (n_points, k)) * radius
    u1, u2 = motion.tangent_basis(e)
    nb = _unit(
        e[:, None, :]
        + (np.cos(ang) * rad)[..., None] * u1[:, None, :]
        + (np.sin(ang) * rad)[..., None] * u2[:, None, :]
    )

    def rates(b: np.ndarray) -> np.ndarray:
        r = dist / (b @ normal)
        tb = np.broadcast_to(t, b.shape)
        t_perp = tb - np.sum(tb * b, axis=-1, keepdims=True) * b
        return -t_perp / r[..., None] - np.cross(np.broadcast_to(omega_cam, b.shape), b)

    r_e = dist / (e @ normal)
    return {
        "e": e,
        "de": rates(e),
        "nb": nb,
        "nde": rates(nb),
        "L": (e @ t) / r_e,
        "omega": np.cross(e, t) / r_e[:, None],
        "range": r_e,
    }


def run(
    scene: dict[str, np.ndarray], omega_cam: np.ndarray, noise: float = 1e-5
) -> tuple[motion.LocalFit, np.ndarray]:
    e = scene["e"]
    f = motion.derotate(e, scene["de"], omega_cam)
    n, k, _ = scene["nb"].shape
    nf = motion.derotate(
        scene["nb"].reshape(-1, 3), scene["nde"].reshape(-1, 3), omega_cam
    ).reshape(n, k, 3)
    fit = motion.fit_local_looming(e, f, scene["nb"], nf, noise=noise)
    return fit, f


T = np.array([0.3, -0.1, 2.0])


def test_local_rule_matches_truth_on_plane() -> None:
    scene = plane_scene(T, np.zeros(3))
    fit, f = run(scene, np.zeros(3))
    tor = np.hypot(scene["L"], np.linalg.norm(scene["omega"], axis=1))
    assert fit.valid.all()
    assert np.max(np.abs(fit.looming - scene["L"]) / tor) < 3e-3
    np.testing.assert_allclose(
        motion.perceived_rotation(scene["e"], f), scene["omega"], atol=1e-12
    )


@pytest.mark.parametrize("scale", [0.1, 3.0, -1.0])
def test_scaling_translation_scales_l_and_omega(scale: float) -> None:
    base = plane_scene(T, np.zeros(3))
    scaled = plane_scene(scale * T, np.zeros(3))
    fit_b, f_b = run(base, np.zeros(3))
    fit_s, f_s = run(scaled, np.zeros(3), noise=1e-5 * abs(scale))  # noise is in 1/s too
    np.testing.assert_allclose(fit_s.looming, scale * fit_b.looming, rtol=1e-9, atol=1e-12)
    om_b = motion.perceived_rotation(base["e"], f_b)
    om_s = motion.perceived_rotation(scaled["e"], f_s)
    np.testing.assert_allclose(om_s, scale * om_b, rtol=1e-9, atol=1e-12)
    q_b = motion.owl_quantities(base["e"], fit_b.looming, om_b)
    q_s = motion.owl_quantities(scaled["e"], fit_s.looming, om_s)
    np.testing.assert_allclose(q_s.heading, np.sign(scale) * q_b.heading, atol=1e-9)
    np.testing.assert_allclose(q_s.range_over_speed, q_b.range_over_speed / abs(scale), rtol=1e-9)


def test_rotation_removed_with_exact_gyro_leaves_outputs_unchanged() -> None:
    spin = np.array([0.4, -0.7, 0.25])
    still = plane_scene(T, np.zeros(3))
    rotating = plane_scene(T, spin)
    fit_a, f_a = run(still, np.zeros(3))
    fit_b, f_b = run(rotating, spin)
    np.testing.assert_allclose(f_b, f_a, atol=1e-12)
    np.testing.assert_allclose(fit_b.looming, fit_a.looming, atol=1e-10)
    np.testing.assert_allclose(fit_b.curl, fit_a.curl, atol=1e-10)


def test_leftover_rotation_goes_into_curl() -> None:
    """A gyro error adds a curl to the chart Jacobian (rule 3); L then moves only through the
    error in the direction of f, i.e. by at most |(b x e)| |g| to first order."""
    bias = np.array([0.01, -0.02, 0.05])
    scene = plane_scene(T, np.zeros(3))
    fit_a, _ = run(scene, np.zeros(3))
    fit_b, _ = run(scene, bias)  # derotating with a wrong rate
    shift = np.abs(fit_b.looming - fit_a.looming)
    tor = np.hypot(scene["L"], np.linalg.norm(scene["omega"], axis=1))
    first_order = np.linalg.norm(np.cross(bias, scene["e"]), axis=1) * np.linalg.norm(
        fit_a.slant, axis=1
    )
    assert np.all(shift <= 1.2 * first_order + 2e-3 * tor)
    # the curl takes the rotation about e: c changes by b.e (chart rot90(d) = e x d), up to
    # the same first-order leak through the direction of f
    curl_err = np.abs(fit_b.curl - fit_a.curl - scene["e"] @ bias)
    assert np.all(curl_err <= 1.2 * first_order + 1e-4)


def test_pure_rotation_gives_no_valid_points() -> None:
    spin = np.array([0.1, 0.3, -0.2])
    scene = plane_scene(np.zeros(3), spin)
    fit, f = run(scene, spin)
    omega = motion.perceived_rotation(scene["e"], f)
    q = motion.owl_quantities(scene["e"], fit.looming, omega, min_tor=1e-6)
    assert not q.valid.any()
    assert np.isnan(q.range_over_speed).all() and np.isnan(q.rot).all()


def test_focus_of_expansion_point_is_valid() -> None:
    e = np.array([[0.0, 0.0, 1.0]])
    q = motion.owl_quantities(e, np.array([0.5]), np.zeros((1, 3)))
    assert q.valid[0]
    np.testing.assert_allclose(q.rot[0], [2.0, 0, 0, 0])
    np.testing.assert_allclose(q.heading[0], [0, 0, 1])


def test_receding_point_has_negative_rot_scalar() -> None:
    e = np.array([[0.0, 0.0, 1.0]])
    q = motion.owl_quantities(e, np.array([-0.2]), np.array([[0.1, 0.0, 0.0]]))
    assert q.valid[0] and q.rot[0, 0] < 0
    assert q.heading[0, 2] < 0


def test_outlier_neighbour_is_downweighted() -> None:
    scene = plane_scene(T, np.zeros(3))
    scene["nde"] = scene["nde"].copy()
    scene["nde"][:, 0] += 0.05  # one neighbour per feature on something else
    fit, _ = run(scene, np.zeros(3))
    tor = np.hypot(scene["L"], np.linalg.norm(scene["omega"], axis=1))
    assert np.median(np.abs(fit.looming - scene["L"]) / tor) < 0.02
    clean, _ = run(plane_scene(T, np.zeros(3)), np.zeros(3))
    assert np.all(fit.quality <= clean.quality)


def test_too_few_neighbours_invalid() -> None:
    scene = plane_scene(T, np.zeros(3), n_points=5)
    e = scene["e"]
    f = motion.derotate(e, scene["de"], np.zeros(3))
    nf = scene["nde"]
    mask = np.zeros((5, 12), dtype=bool)
    mask[:, :3] = True
    fit = motion.fit_local_looming(e, f, scene["nb"], nf, mask, min_neighbours=4)
    assert not fit.valid.any()
    assert np.isnan(fit.looming).all() and np.isinf(fit.variance).all()


def test_heading_route_exact_and_fusion_flags() -> None:
    scene = plane_scene(T, np.zeros(3))
    e, truth_l = scene["e"], scene["L"]
    route = motion.looming_from_heading(e, scene["omega"], T / np.linalg.norm(T))
    assert route.valid.all()
    np.testing.assert_allclose(route.looming, truth_l, rtol=1e-9)
    fit, _ = run(scene, np.zeros(3))
    fused = motion.fuse_looming(fit, route, e.shape[0])
    assert np.all(fused.flags == PointFlag.L_LOCAL | PointFlag.L_HEADING)
    # the fused value lies between the two routes
    lo = np.minimum(fit.looming, route.looming) - 1e-12
    hi = np.maximum(fit.looming, route.looming) + 1e-12
    assert np.all((fused.looming >= lo) & (fused.looming <= hi))
    only_local = motion.fuse_looming(fit, None, e.shape[0])
    assert np.all(only_local.flags == PointFlag.L_LOCAL)
    np.testing.assert_allclose(only_local.looming, fit.looming)


def test_fusion_scales_the_local_variance_in_weights_gate_and_result() -> None:
    """With the local variance taken as s * v_l: fused = (L_l / (s v_l) + L_h / v_h) /
    (1 / (s v_l) + 1 / v_h), variance 1 / (1 / (s v_l) + 1 / v_h); a gap within the gate
    only after the scaling keeps both routes."""
    n = 3
    local = motion.LocalFit(
        looming=np.array([1.0, 1.0, 1.0]),
        variance=np.array([0.01, 0.04, 0.01]),
        slant=np.zeros((n, 2)),
        curl=np.zeros(n),
        residual_rms=np.zeros(n),
        quality=np.ones(n),
        num_used=np.full(n, 8),
        valid=np.ones(n, dtype=bool),
    )
    route = motion.HeadingRoute(
        np.array([1.2, 0.9, 1.85]), np.array([0.01, 0.01, 0.01]), np.ones(n, dtype=bool)
    )
    s = 4.0
    fused = motion.fuse_looming(local, route, n, max_disagreement=4.0, local_variance_scale=s)
    wl, wh = 1.0 / (s * local.variance[:2]), 1.0 / route.variance[:2]
    np.testing.assert_allclose(
        fused.looming[:2], (wl * local.looming[:2] + wh * route.looming[:2]) / (wl + wh)
    )
    np.testing.assert_allclose(fused.variance[:2], 1.0 / (wl + wh))
    # point 2: the gap 0.85 is 6.0 sigmas of sqrt(0.01 + 0.01), 3.8 of sqrt(0.04 + 0.01)
    assert fused.flags[2] == PointFlag.L_LOCAL | PointFlag.L_HEADING
    plain = motion.fuse_looming(local, route, n, max_disagreement=4.0)
    assert plain.flags[2] == PointFlag.L_LOCAL and plain.looming[2] == 1.0
    np.testing.assert_allclose(plain.variance[:2], 1.0 / (1.0 / local.variance[:2] + wh))


def test_heading_route_invalid_at_focus_of_expansion() -> None:
    h = np.array([0.0, 0.0, 1.0])
    route = motion.looming_from_heading(np.array([h]), np.zeros((1, 3)), h)
    assert not route.valid[0] and np.isnan(route.looming[0])


def test_disagreeing_routes_keep_local_only() -> None:
    scene = plane_scene(T, np.zeros(3), n_points=10)
    fit, _ = run(scene, np.zeros(3))
    wrong = motion.HeadingRoute(fit.looming + 1.0, np.full(10, 1e-6), np.ones(10, dtype=bool))
    fused = motion.fuse_looming(fit, wrong, 10)
    assert np.all(fused.flags == PointFlag.L_LOCAL)


def test_bad_shapes_raise_with_the_shape() -> None:
    with pytest.raises(InvalidInputError, match=r"\(4, 2\)"):
        motion.perceived_rotation(np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(InvalidInputError, match="first dimension"):
        motion.derotate(np.zeros((4, 3)), np.zeros((5, 3)), np.zeros(3))
    with pytest.raises(InvalidInputError, match="angular_velocity"):
        motion.derotate(np.zeros((4, 3)), np.zeros((4, 3)), np.zeros(2))
    with pytest.raises(InvalidInputError, match="heading"):
        motion.looming_from_heading(np.ones((1, 3)), np.ones((1, 3)), np.zeros(3))


def test_batched_spd_solve_matches_lapack() -> None:
    # fit_local_looming solves its (N, 4, 4) normal equations with a written-out Cholesky
    rng = np.random.default_rng(5)
    jac = rng.normal(size=(200, 12, 4)) * rng.uniform(1e-3, 1e3, size=(200, 1, 4))
    a = np.einsum("nki,nkj->nij", jac, jac) + 1e-9 * np.eye(4)
    b = rng.normal(size=(200, 4))
    x, inv00 = motion._solve_spd4(a, b)
    np.testing.assert_allclose(x, np.linalg.solve(a, b[..., None])[..., 0], rtol=1e-8)
    np.testing.assert_allclose(inv00, np.linalg.inv(a)[:, 0, 0], rtol=1e-8)
    indefinite = np.diag([1.0, -1.0, 1.0, 1.0])[None]
    x_bad, inv_bad = motion._solve_spd4(indefinite, np.ones((1, 4)))
    assert np.all(np.isnan(x_bad)) and np.isnan(inv_bad[0])


@pytest.mark.parametrize("n", [0, 1, 2, 7, 8, 1001])
def test_the_fast_reductions_equal_numpys_bit_for_bit(n: int) -> None:
    """row_norms, all_finite and median are the engine's cheaper forms of np.linalg.norm,
    np.all(np.isfinite(...)) and np.median on short rows and 1-D arrays: the same bits."""
    from owl_core.motion import all_finite, median, row_norms

    rng = np.random.default_rng(n)
    for dim in (2, 3):
        v = rng.normal(size=(n, dim)) * 10.0 ** rng.integers(-8, 8, size=(n, 1))
        assert np.array_equal(row_norms(v), np.linalg.norm(v, axis=-1))
        v[rng.random(v.shape) < 0.1] = rng.choice([np.nan, np.inf, -np.inf])
        assert np.array_equal(all_finite(v), np.all(np.isfinite(v), axis=-1))
    values = rng.normal(size=n)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # NumPy's for an empty median
        assert np.array_equal(median(values), np.median(values), equal_nan=True)
        if n:
            values[n // 3] = np.nan
            assert np.isnan(median(values)) and np.isnan(np.median(values))
