"""Dense OWL on rendered textured planes with exact answers (owl_core.dense)."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import cv2
import numpy as np
import pytest
from scipy.stats import norm

from owl_core.camera import CameraModel
from owl_core.dense import (
    DenseOptions,
    DenseOwl,
    Readout,
    _Grid,
    _LocalFit,
    _minus_global_affine,
    _ttc,
)
from owl_core.errors import InvalidInputError
from owl_core.geometry import so3_exp

W, H = 320, 240
FX = 0.5 * W / math.tan(math.radians(35.0))
DT_NS = 33_333_333


def _camera() -> CameraModel:
    k = np.array([[FX, 0.0, (W - 1) / 2], [0.0, FX, (H - 1) / 2], [0.0, 0.0, 1.0]])
    return CameraModel(W, H, k, np.zeros(0), "none")


def _texture(seed: int = 3, size: int = 1024) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.normal(size=(size, size)).astype(np.float32)
    tex = cv2.GaussianBlur(noise, (0, 0), 2.0) + 0.5 * cv2.GaussianBlur(noise, (0, 0), 6.0)
    tex = (tex - tex.mean()) / tex.std()
    return np.clip(128.0 + 45.0 * tex, 0, 255).astype(np.float32)


def _render(
    cam: CameraModel, tex: np.ndarray, r_wc: np.ndarray, c_w: np.ndarray, plane_z: float
) -> tuple[np.ndarray, np.ndarray]:
    """Image of the plane world-Z = plane_z (texel 1 cm) and the range of each pixel, m."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    e = cam.pixel_to_bearing(np.stack([u, v], axis=-1))
    d = e @ r_wc.T
    s = (plane_z - c_w[2]) / d[..., 2]
    x = c_w + s[..., None] * d
    texel = 0.01
    mx = (x[..., 0] / texel + tex.shape[1] / 2).astype(np.float32)
    my = (x[..., 1] / texel + tex.shape[0] / 2).astype(np.float32)
    img = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), s


def _run(
    speed: float = 1.0,
    plane_z: float = 4.0,
    yaw_rate: float = 0.0,
    frames: int = 5,
    lateral: float = 0.0,
    options: DenseOptions | None = None,
    accel: float = 0.0,
    pass_rate: bool = True,
):
    cam = _camera()
    tex = _texture()
    dense = DenseOwl(cam, options or DenseOptions(width=160, height=120))
    velocity = np.array([lateral, 0.0, speed])
    rotations = {}
    result = None
    rng_ = None
    for k in range(frames):
        t = k * DT_NS * 1e-9
        r_wc = so3_exp(np.array([0.0, yaw_rate * t, 0.0]))
        c_w = velocity * t + 0.5 * np.array([0.0, 0.0, accel]) * t * t
        img, rng_ = _render(cam, tex, r_wc, c_w, plane_z)
        stamp = 1_000_000_000 + k * DT_NS
        rotations[stamp] = r_wc
        prev = dense.previous_stamp_ns
        rot = None if prev is None else r_wc.T @ rotations[prev]
        # heading in the current camera frame, and d ln|v|/dt
        v_now = velocity + np.array([0.0, 0.0, accel * t])
        h = r_wc.T @ v_now
        rate = accel * v_now[2] / float(v_now @ v_now) if pass_rate else 0.0
        result = dense.process(img, stamp, rot, h / np.linalg.norm(h), 0.0, rate)
    assert result is not None and rng_ is not None
    return dense, result, rng_, r_wc.T @ v_now


def _truth_ros(dense: DenseOwl, rng: np.ndarray, speed: float) -> np.ndarray:
    px = np.rint(dense.grid.full_px).astype(int)
    return rng[px[..., 1], px[..., 0]] / speed


def test_translation_toward_a_plane_gives_its_range_over_speed_and_ttc() -> None:
    dense, res, rng, _ = _run(speed=2.0, plane_z=4.0)
    truth = _truth_ros(dense, rng, 2.0)
    conf = res.confident
    assert res.confident_fraction > 0.6
    rel = np.abs(res.range_over_speed[conf] - truth[conf]) / truth[conf]
    assert np.median(rel) < 0.03
    assert np.percentile(rel, 90) < 0.15
    # L = (t.e)/r; straight ahead of a fronto-parallel plane the time to contact is Z/v
    assert res.ttc is not None
    z_now = (4.0 - 2.0 * 4 * DT_NS * 1e-9) / 2.0
    # the k-th shortest of the cone's 1/L after L is averaged over ttc_window_px squares
    assert res.ttc.seconds == pytest.approx(z_now, rel=0.1)
    assert res.ttc.pixel is not None
    assert np.hypot(*(res.ttc.pixel - [(W - 1) / 2, (H - 1) / 2])) < FX * math.tan(
        math.radians(dense.options.ttc_cone_deg) * 1.05
    )
    # depth over speed of a fronto-parallel plane is its distance over speed everywhere
    depth = res.depth_over_speed[conf]
    assert np.median(np.abs(depth - z_now) / z_now) < 0.03
    # omega is perpendicular to the bearing
    dots = np.einsum("...i,...i->...", res.omega, dense.grid.bearings)
    assert np.nanmax(np.abs(dots)) < 1e-4


def test_ttc_window_removes_the_order_statistic_bias() -> None:
    """Per pixel 1/L in the cone scatters by about 8 % (1-sigma) around the plane's true
    Z/v; its 20th smallest of ~1100 values sits about 2 sigma short. Averaging L over the
    window first brings the shortest time to contact back to within 10 %."""
    z_now = (4.0 - 2.0 * 4 * DT_NS * 1e-9) / 2.0
    raw_options = DenseOptions(width=160, height=120, ttc_window_px=1, ttc_lower_sigmas=0.0)
    _, raw, _, _ = _run(speed=2.0, options=raw_options)
    assert raw.ttc is not None
    values = raw.ttc.image[np.isfinite(raw.ttc.image)]
    assert np.median(values) == pytest.approx(z_now, rel=0.05)  # no bias in the middle
    assert raw.ttc.seconds < 0.88 * z_now  # the tail is
    _, avg, _, _ = _run(speed=2.0, options=DenseOptions(width=160, height=120))
    assert avg.ttc is not None
    assert avg.ttc.seconds == pytest.approx(z_now, rel=0.1)


def test_ttc_read_below_the_average_removes_the_selection_bias() -> None:
    """A looming field L = 0.5 1/s (2 s to contact everywhere) with independent normal
    noise of known sigma (10 % of L) per pixel, no window averaging: the 20th largest of N
    cone values lies Phi^-1(1 - 20/N) sigmas above L, so the 20th shortest 1/L reads short
    by that much; reading each pixel at L - z sigma with z = Phi^-1(1 - 20/N) takes it
    back (to the order statistic's own scatter, about 0.1 sigma for N of a few thousand)."""
    cam = _camera()
    dense = DenseOwl(cam, DenseOptions(width=160, height=120))
    grid = dense.grid
    true_l, sigma = 0.5, 0.05
    rng = np.random.default_rng(7)
    looming = (true_l + sigma * rng.standard_normal(grid.e.shape[1:])).astype(np.float32)
    var_l = np.full(looming.shape, sigma**2, dtype=np.float32)
    heading = np.array([0.0, 0.0, 1.0])
    options = DenseOptions(width=160, height=120, ttc_window_px=1, ttc_cone_deg=30.0)
    textured = np.ones(looming.shape, dtype=bool)
    plain = _ttc(grid, replace(options, ttc_lower_sigmas=0.0), looming, var_l, heading, textured)
    n = plain.confident_in_cone
    assert n > 1000
    z = float(norm.ppf(1.0 - options.ttc_min_pixels / n))
    # the plain reading: short by z sigma in L, i.e. 1/(L + z sigma)
    assert plain.seconds == pytest.approx(1.0 / (true_l + z * sigma), rel=0.02)
    assert plain.seconds < 0.85 / true_l
    lowered = _ttc(grid, replace(options, ttc_lower_sigmas=z), looming, var_l, heading, textured)
    assert lowered.seconds == pytest.approx(1.0 / true_l, rel=0.02)
    # every window is read at its lower bound; the image stays NaN outside the cone
    inside = np.isfinite(lowered.image)
    assert np.allclose(lowered.image[inside], 1.0 / (looming[inside] - z * sigma), rtol=1e-5)
    with pytest.raises(InvalidInputError):
        DenseOptions(ttc_lower_sigmas=-1.0)


def test_ttc_ignores_what_dense_flow_filled_into_a_textureless_region() -> None:
    """A textured surface 5 s away fills the path cone but for a textureless band where the
    flow (filled in from an edge) reads L = 0.5 1/s: its windows are as precise as any by
    the variance model, and taken as measured they give 2 s. Read over textured pixels
    only the time to contact is the surface's, and the band stays NaN in the image."""
    cam = _camera()
    options = DenseOptions(width=160, height=120, ttc_cone_deg=30.0)
    grid = DenseOwl(cam, options).grid
    looming = np.full(grid.e.shape[1:], 0.2, dtype=np.float32)  # 5 s
    band = np.zeros(looming.shape, dtype=bool)
    band[30:70, 50:110] = True  # in the cone, 40 x 60 working pixels (25 px windows)
    looming[band] = 0.5
    var_l = np.full(looming.shape, 1e-6, dtype=np.float32)
    heading = np.array([0.0, 0.0, 1.0])
    taken = _ttc(grid, options, looming, var_l, heading, np.ones(looming.shape, dtype=bool))
    assert taken.seconds == pytest.approx(2.0, rel=0.01)  # the filled-in flow, as measured
    ttc = _ttc(grid, options, looming, var_l, heading, ~band)
    assert ttc.seconds == pytest.approx(5.0, rel=0.01)
    assert np.all(np.isnan(ttc.image[band]))
    assert np.isfinite(ttc.image[~band & np.isfinite(taken.image)]).all()


def test_range_scales_with_speed() -> None:
    """Twice the speed toward the same plane: half the r/|t| (L and omega double)."""
    d1, r1, rng1, _ = _run(speed=1.0)
    d2, r2, rng2, _ = _run(speed=2.0)
    both = r1.confident & r2.confident
    ratio = np.median(r1.range_over_speed[both] / r2.range_over_speed[both])
    truth = np.median(_truth_ros(d1, rng1, 1.0)[both] / _truth_ros(d2, rng2, 2.0)[both])
    assert ratio == pytest.approx(truth, rel=0.03)


def test_an_accelerating_camera_gets_r_over_the_current_speed() -> None:
    """From 1 m/s at 3 m/s^2: 1.4 m/s at the last frame, d ln|v|/dt = 2.1 1/s. The flow over
    the 3-frame baseline (0.1 s) measures r/|t| at its middle in units of the speed there,
    1.25 m/s; the sparse engine's rate brings it to the current speed (exp(-s dt/2): 0.6 %
    from the exact ratio 1.25/1.4 under constant acceleration). Without it the median reads
    high by ln(1.4/1.25) = 11 %."""
    speed_now = 1.0 + 3.0 * 4 * DT_NS * 1e-9
    dense, res, rng, _ = _run(speed=1.0, accel=3.0)
    truth = _truth_ros(dense, rng, speed_now)
    conf = res.confident
    assert res.confident_fraction > 0.5
    signed = (res.range_over_speed[conf] - truth[conf]) / truth[conf]
    assert abs(np.median(signed)) < 0.03
    _, plain, _, _ = _run(speed=1.0, accel=3.0, pass_rate=False)
    both = conf & plain.confident
    ratio = np.median(plain.range_over_speed[both] / res.range_over_speed[both])
    # the same pixels read exp(s dt / 2) = 1.113 times longer without the rate
    assert ratio == pytest.approx(math.exp(3.0 / speed_now * 0.05), rel=0.005)


def test_gyro_rotation_is_removed() -> None:
    """A camera turning at 0.3 rad/s while it moves: with the rotation handed in, the same
    r/|t| as without the turn; with identity instead, clearly wrong."""
    dense, res, rng, _ = _run(speed=2.0, yaw_rate=0.3, lateral=0.3)
    truth = _truth_ros(dense, rng, math.hypot(2.0, 0.3))
    conf = res.confident
    assert res.confident_fraction > 0.5
    rel = np.abs(res.range_over_speed[conf] - truth[conf]) / truth[conf]
    assert np.median(rel) < 0.04


def test_without_heading_the_local_rule_alone_still_measures_looming() -> None:
    cam = _camera()
    tex = _texture()
    dense = DenseOwl(cam, DenseOptions(width=160, height=120, baseline_frames=3))
    res = None
    for k in range(4):
        c_w = np.array([0.0, 0.0, 2.0 * k * DT_NS * 1e-9])
        img, _ = _render(cam, tex, np.eye(3), c_w, 4.0)
        res = dense.process(img, 1_000_000_000 + k * DT_NS, np.eye(3), None)
    assert res is not None
    assert res.ttc is None
    assert any("no heading" in r for r in res.reasons)
    # near the optical axis L = v e_z^2 / Z, about 0.25 1/s
    centre = res.looming_local[50:70, 70:90]
    assert np.nanmedian(centre) == pytest.approx(2.0 / 3.8, rel=0.15)


def test_local_fit_of_an_affine_field_is_exact() -> None:
    h, w = 40, 50
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    field = np.stack([0.1 + 0.02 * u - 0.01 * v, -0.3 * u + 0.05 * v, 0.2 + 0 * u])
    weights = np.ones((h, w))
    weights[::3, ::2] = 0.0  # holes must not bias a weighted fit
    gu, gv, s2, _ = _LocalFit(7).fit(field, weights)
    inner = (slice(None), slice(5, -5), slice(5, -5))
    assert np.allclose(np.moveaxis(gu[inner], 0, -1), [0.02, -0.3, 0.0], atol=1e-9)
    assert np.allclose(np.moveaxis(gv[inner], 0, -1), [-0.01, 0.05, 0.0], atol=1e-9)
    assert np.all(s2[inner[1:]] < 1e-12)
    noise = np.random.default_rng(0).normal(scale=0.01, size=field.shape)
    _, _, s2n, _ = _LocalFit(7).fit(field + noise, weights)
    # 3 components, one tangent-component variance reported: about 1.5 x 1e-4 here
    assert 0.5e-4 < np.median(s2n[inner[1:]]) < 3e-4
    # float32 (the dense stage's type) on a field of the size the stage fits (it takes a
    # global affine field out first, below): moments of a 7x7 window of values about 0.1
    # lose about 1e-7 relative, so a residual variance of 1e-4 keeps about 3 digits
    small = 0.05 * field + noise
    _, _, s2_64, _ = _LocalFit(7).fit(small, weights)
    gu32, _, s2_32, _ = _LocalFit(7).fit(small.astype(np.float32), weights)
    assert gu32.dtype == np.float32
    assert np.allclose(s2_32[inner[1:]], s2_64[inner[1:]], rtol=1e-2)


def test_global_affine_split_is_exact() -> None:
    """The float32 fit works on the field minus a global affine fit: the split's gradient
    added back gives the same gradient and residual as the whole field's fit."""
    grid = _Grid(_camera(), 40, 30)
    v, u = np.mgrid[0:30, 0:40].astype(np.float64)
    field = np.stack([0.3 + 0.02 * u - 0.01 * v + 1e-4 * u * u, -0.3 * u, 0 * u + 2.0])
    weights = (np.random.default_rng(1).random((30, 40)) > 0.3).astype(np.float64)
    rest, grads = _minus_global_affine(grid, field, weights)
    # what is left of the affine components is float32 rounding of the fit
    assert np.max(np.abs(rest[1:])) < 1e-5
    assert grads[1] == pytest.approx([-0.3, 0.0], abs=1e-6)
    fit = _LocalFit(5)
    gu, gv, s2, _ = fit.fit(field, weights)
    gu_r, gv_r, s2_r, _ = fit.fit(rest.astype(np.float64), weights)
    ok = np.isfinite(s2)
    # the split is computed in float32 (about 1e-8 on values of 0.3): 1e-7 per pixel
    assert np.allclose((gu_r + grads[:, 0, None, None])[:, ok], gu[:, ok], atol=1e-7)
    assert np.allclose((gv_r + grads[:, 1, None, None])[:, ok], gv[:, ok], atol=1e-7)
    assert np.allclose(s2_r[ok], s2[ok], rtol=1e-3, atol=1e-12)


def test_the_check_flow_refinement_changes_only_the_check() -> None:
    """The forward flow serves the forward-backward check alone: with fewer refinement
    iterations the measured (backward) flow is the same array, with the preset's own count
    (3 for balanced) everything is as with None, and never more than the preset's; the
    plane is still measured."""

    def run(iterations: int | None) -> Any:
        opts = DenseOptions(width=160, height=120, fb_refinement_iterations=iterations)
        return _run(speed=2.0, plane_z=4.0, options=opts)

    dense, res_none, rng, _ = run(None)
    _, res_same, _, _ = run(3)
    _, res_zero, _, _ = run(0)
    np.testing.assert_array_equal(res_same.range_over_speed, res_none.range_over_speed)
    np.testing.assert_array_equal(res_zero.flow, res_none.flow)
    # never more refinement than the measured flow's: ultrafast has none
    ultrafast = DenseOwl(_camera(), DenseOptions(preset="ultrafast", fb_refinement_iterations=1))
    assert ultrafast._setup.dis_check is ultrafast._setup.dis
    truth = _truth_ros(dense, rng, 2.0)
    conf = res_zero.confident
    assert res_zero.confident_fraction > 0.6
    rel = np.abs(res_zero.range_over_speed[conf] - truth[conf]) / truth[conf]
    assert np.median(rel) < 0.03


def test_first_frame_and_a_stamp_going_back_give_none() -> None:
    cam = _camera()
    dense = DenseOwl(cam, DenseOptions(width=160, height=120))
    img = np.zeros((H, W), dtype=np.uint8)
    assert dense.process(img, 10, None, None) is None
    assert dense.previous_stamp_ns == 10
    assert dense.process(img, 5, None, None) is None
    assert dense.previous_stamp_ns == 5
    with pytest.raises(InvalidInputError, match="uint8"):
        dense.process(np.zeros((H, W)), 20, None, None)


@pytest.mark.parametrize(
    ("kwargs", "text"),
    [
        ({"window_px": 4}, "window_px"),
        ({"preset": "slow"}, "preset"),
        ({"width": 8}, "width"),
        ({"ttc_cone_deg": 95.0}, "ttc_cone_deg"),
        ({"min_confidence": 1.5}, "min_confidence"),
        ({"baseline_frames": 0}, "baseline_frames"),
        ({"ttc_window_px": 8}, "ttc_window_px"),
        ({"fb_refinement_iterations": -1}, "fb_refinement_iterations"),
        ({"fb_refinement_iterations": 1.5}, "fb_refinement_iterations"),
    ],
)
def test_bad_options_name_the_value(kwargs: dict[str, object], text: str) -> None:
    with pytest.raises(InvalidInputError, match=text):
        DenseOptions(**kwargs)  # type: ignore[arg-type]


def _render_rolling(
    cam: CameraModel, tex: np.ndarray, pose: Any, t0: float, readout_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_render` with a rolling shutter: input row v seen at ``t0 + (v / H) T`` from
    ``pose(t) = (R_wc, c_w)``; the range is from the camera centre at ``t0``, m."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    e = cam.pixel_to_bearing(np.stack([u, v], axis=-1))
    poses = [pose(t0 + row / H * readout_s) for row in range(H)]
    r_rows = np.stack([p[0] for p in poses])
    c_rows = np.stack([p[1] for p in poses])
    d = np.einsum("hij,hwj->hwi", r_rows, e)
    s = (4.0 - c_rows[:, None, 2]) / d[..., 2]
    x = c_rows[:, None, :] + s[..., None] * d
    mx = (x[..., 0] / 0.01 + tex.shape[1] / 2).astype(np.float32)
    my = (x[..., 1] / 0.01 + tex.shape[0] / 2).astype(np.float32)
    img = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    rng = np.linalg.norm(x - pose(t0)[1], axis=-1)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), rng


def test_rolling_shutter_rows_are_derotated_from_their_own_times() -> None:
    """A rolling shutter (30 ms readout) on a camera pitching at 1 rad/s while it moves at
    2 m/s toward a plane 4 m away: the rows of the two images of a 3-frame baseline are
    seen up to 3 ms further apart than their stamps (the rotation moves content 23 px
    vertically), and the rotation between them differs from the stamps' by up to 3 mrad
    against a translational flow of about 15 mrad. Derotated with the stamps' rotation the
    median r/|t| error is 6.5 %; with each row's own rotation and interval (:class:`Readout`,
    gyro tables of 9 row times) it is that of a global shutter (2.8 % against 3.6 %)."""
    cam = _camera()
    tex = _texture()
    readout_s, m = 0.03, 8
    velocity = np.array([0.0, 0.0, 2.0])

    def pose(t: float) -> tuple[np.ndarray, np.ndarray]:
        return so3_exp(np.array([1.0 * t, 0.0, 0.0])), velocity * t

    def run(with_readout: bool) -> tuple[float, float]:
        dense = DenseOwl(cam, DenseOptions(width=160, height=120))
        res, rng = None, None
        for k in range(5):
            t = k * DT_NS * 1e-9
            img, rng = _render_rolling(cam, tex, pose, t, readout_s)
            prev = dense.previous_stamp_ns
            r_now = pose(t)[0]
            rot, readout = None, None
            if prev is not None:
                tp = (prev - 1_000_000_000) * 1e-9
                rot = r_now.T @ pose(tp)[0]
                if with_readout:
                    rows = [[r_now.T @ pose(s + j / m * readout_s)[0] for j in range(m + 1)]
                            for s in (tp, t)]  # fmt: skip
                    readout = Readout(readout_s, np.array(rows[0]), np.array(rows[1]))
            h = r_now.T @ velocity
            res = dense.process(
                img, 1_000_000_000 + k * DT_NS, rot, h / 2.0, 0.0, 0.0, readout=readout
            )
        assert res is not None and rng is not None
        truth = _truth_ros(dense, rng, 2.0)
        conf = res.confident
        assert res.confident_fraction > 0.4
        rel = np.abs(res.range_over_speed[conf] - truth[conf]) / truth[conf]
        return float(np.median(rel)), float(np.percentile(rel, 90))

    stamps_only = run(False)
    rows = run(True)
    assert stamps_only[0] > 0.05 and stamps_only[1] > 0.15
    assert rows[0] < 0.04 and rows[1] < 0.11
    with pytest.raises(InvalidInputError):
        Readout(0.0, np.zeros((9, 3, 3)), np.zeros((9, 3, 3)))
    with pytest.raises(InvalidInputError):
        Readout(0.03, np.zeros((9, 3, 3)), np.zeros((5, 3, 3)))
