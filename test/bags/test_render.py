"""bags.sim.render: exact geometry (independent float64 ray casting, OpenCV's distortion),
anti-aliasing, texture coverage at every range, noise and determinism."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from bags.errors import ScenarioError
from bags.sim.render import Rect, Renderer, box, texture
from owl_core.camera import CameraModel

# camera optical frame looking along world +x (world: x forward, y left, z up)
R_WC = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
C_W = np.array([0.0, 0.0, 1.5])
BARREL = np.array([-0.25, 0.07, 0.0005, -0.0003, 0.0])


def _camera(w: int = 160, h: int = 120, d: np.ndarray | None = None) -> CameraModel:
    f = 0.5 * w / math.tan(math.radians(35))
    k = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    if d is None:
        return CameraModel(w, h, k, np.zeros(0), "none")
    return CameraModel(w, h, k, d, "plumb_bob")


def _scene() -> list[Rect]:
    ground = Rect((0, 0, 0), (1, 0, 0), (0, 1, 0), math.inf, math.inf, 1, 1, 0.01)
    wall = Rect((30, 0, 5), (0, -1, 0), (0, 0, 1), 12, 5, 2, 2, 0.03)
    rects = [ground, wall]
    rects += box((6.0, 1.0, 0.8), (1.5, 1.2, 1.6), 10, texture_seed=20, texel_m=0.005)
    rects += box((10.0, -2.0, 1.0), (2.0, 2.0, 2.0), 11, texture_seed=30, texel_m=0.005)
    # a box partly hidden behind the first one
    rects += box((9.0, 1.6, 1.2), (1.0, 1.0, 2.4), 12, texture_seed=40, texel_m=0.005)
    return rects


def _reference_cast(camera: CameraModel, scene: list[Rect], r_wc: np.ndarray, c_w: np.ndarray):
    """Independent float64 brute force: every pixel-centre ray against every rectangle."""
    uu, vv = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    e = camera.pixel_to_bearing(np.stack([uu, vv], -1).astype(float))  # (H, W, 3)
    d = e @ r_wc.T  # world directions
    best = np.full(e.shape[:2], np.inf)
    ids = np.zeros(e.shape[:2], dtype=np.uint16)
    for r in scene:
        n = r.normal
        o = np.asarray(r.origin, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            dn = d @ n
            t = ((o - c_w) @ n) / dn
            p = c_w + t[..., None] * d - o
            ok = (t > 1e-3) & (np.abs(p @ np.asarray(r.u)) <= r.half_u)
            ok &= np.abs(p @ np.asarray(r.v)) <= r.half_v
            if not r.two_sided:
                ok &= dn < 0
        closer = ok & (t < best)
        best = np.where(closer, t, best)
        ids = np.where(closer, r.object_id, ids)
    return e, best, ids


@pytest.mark.parametrize("distortion", [None, BARREL], ids=["pinhole", "plumb_bob"])
def test_range_and_ids_match_independent_ray_cast(distortion) -> None:
    camera = _camera(d=distortion)
    scene = _scene()
    out = Renderer(camera, supersample=2, noise_sigma=0.0).render(scene, R_WC, C_W)
    e, ref_t, ref_ids = _reference_cast(camera, scene, R_WC, C_W)
    assert out.range_m.dtype == np.float32 and out.object_id.dtype == np.uint16
    assert set(np.unique(out.object_id)) == {0, 1, 2, 10, 11, 12}
    # ids agree everywhere except where float32 and float64 disagree on an exact edge
    differ = out.object_id != ref_ids
    assert differ.mean() < 2e-3
    hit = np.isfinite(ref_t) & ~differ
    np.testing.assert_allclose(out.range_m[hit], ref_t[hit], rtol=2e-6, atol=1e-5)
    assert np.all(np.isinf(out.range_m[ref_ids == 0]) | differ[ref_ids == 0])
    # bearing * range lands on a rectangle of the object named by the id image
    rng = np.where(np.isfinite(out.range_m), out.range_m, 0.0).astype(float)
    pts = C_W + (e * rng[..., None]) @ R_WC.T
    for oid in (1, 2, 10, 11, 12):
        sel = (out.object_id == oid) & ~differ
        on_any = np.zeros(int(sel.sum()), dtype=bool)
        for r in (r for r in scene if r.object_id == oid):
            on_any |= r.contains(pts[sel], tol=1e-5 * 40)
        assert on_any.all(), oid


def test_distorted_rays_agree_with_opencv_undistortion() -> None:
    """A distorted pixel sees what the pinhole camera sees at cv2.undistortPoints(pixel)."""
    pin = _camera(320, 240)
    dist = _camera(320, 240, BARREL)
    scene = _scene()
    a = Renderer(pin, supersample=1, noise_sigma=0.0).render(scene, R_WC, C_W)
    b = Renderer(dist, supersample=1, noise_sigma=0.0).render(scene, R_WC, C_W)
    uu, vv = np.meshgrid(np.arange(320.0), np.arange(240.0))
    pix = np.stack([uu, vv], -1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    k_d = np.asarray(dist.K)
    und = cv2.undistortPointsIter(pix, k_d, BARREL, None, np.asarray(pin.K), crit)
    und = und.reshape(240, 320, 2)
    x0 = np.floor(und[..., 0]).astype(int)
    y0 = np.floor(und[..., 1]).astype(int)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 < 319) & (y0 < 239)
    xi, yi = np.clip(x0, 0, 318), np.clip(y0, 0, 238)
    same = np.ones_like(inside)
    for dy in (0, 1):
        for dx in (0, 1):
            same &= a.object_id[yi + dy, xi + dx] == b.object_id
    sel = inside & same & (b.object_id > 0)
    assert sel.mean() > 0.5  # most of the image is compared
    # inverse depth 1/z is exactly linear in pinhole pixel coordinates on a plane, so its
    # bilinear interpolation is exact up to float32 rounding
    k = np.asarray(pin.K)
    fx, fy = und[..., 0] - x0, und[..., 1] - y0
    norm_a = np.hypot(np.hypot((uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1]), 1.0)
    inv_a = norm_a / a.range_m.astype(float)
    interp = (
        inv_a[yi, xi] * (1 - fx) * (1 - fy)
        + inv_a[yi, xi + 1] * fx * (1 - fy)
        + inv_a[yi + 1, xi] * (1 - fx) * fy
        + inv_a[yi + 1, xi + 1] * fx * fy
    )
    xn = (und[..., 0] - k[0, 2]) / k[0, 0]
    yn = (und[..., 1] - k[1, 2]) / k[1, 1]
    inv_b = np.hypot(np.hypot(xn, yn), 1.0) / b.range_m.astype(float)
    rel = np.abs(interp[sel] - inv_b[sel]) / inv_b[sel]
    # (the few exceptions straddle a crease between two faces of one box)
    assert np.mean(rel > 2e-5) < 0.01 and np.median(rel) < 1e-6
    # the distorted image really is distorted: comparing at the same pixel fails
    assert np.median(np.abs(inv_a[sel] - inv_b[sel]) / inv_b[sel]) > 1e-3


def _flicker(mipmap: bool) -> float:
    """Mean frame difference of a far, grazing texture under a sub-pixel camera shift."""
    camera = _camera(160, 120)
    ground = Rect((0, 0, 0), (1, 0, 0), (0, 1, 0), math.inf, math.inf, 1, 3, 0.01)
    r = Renderer(camera, supersample=1, noise_sigma=0.0, mipmap=mipmap)
    a = r.render([ground], R_WC, C_W).image.astype(float)
    b = r.render([ground], R_WC, C_W + np.array([0.0, 0.013, 0.0])).image.astype(float)
    far = r.render([ground], R_WC, C_W).range_m > 15.0
    return float(np.mean(np.abs(a - b)[far]))


def test_mipmapping_removes_shimmer_of_far_surfaces() -> None:
    # a 1.3 cm lateral shift moves 15-60 m ground points by < 0.1 px: a band-limited image
    # barely changes, an aliased one changes by a good part of the texture contrast
    filtered, aliased = _flicker(True), _flicker(False)
    assert filtered < 1.5
    assert aliased > 4 * filtered


def test_anisotropic_filtering_integrates_the_pixel_footprint() -> None:
    """Ground 3-20 m ahead of a camera 1.5 m up is seen at 4:1 to 13:1 grazing incidence.
    A pixel integrates its footprint there: the reference is the same view rendered at 4x
    the resolution with 4x4 rays per pixel (isotropically filtered, so 16x finer) and
    box-averaged back. Isotropic mip-mapping blurs across by the footprint's aspect ratio
    and loses contrast; anisotropic lookups keep the reference's contrast and pixels."""
    ground = Rect((0, 0, 0), (1, 0, 0), (0, 1, 0), math.inf, math.inf, 1, 3, 0.01)
    hi = Renderer(_camera(480, 360), supersample=4, noise_sigma=0.0, anisotropy=1)
    ref = hi.render([ground], R_WC, C_W).image.astype(float).reshape(90, 4, 120, 4)
    ref = ref.mean(axis=(1, 3))
    for anisotropy, near_rms in ((16, 4.0), (1, 11.0)):
        out = Renderer(_camera(120, 90), noise_sigma=0.0, anisotropy=anisotropy).render(
            [ground], R_WC, C_W
        )
        for lo, hi_m, contrast in ((3.0, 8.0, 0.9), (8.0, 20.0, 0.85)):
            near = (out.range_m > lo) & (out.range_m < hi_m)
            img = out.image.astype(float)[near]
            rms = float(np.sqrt(np.mean((img - ref[near]) ** 2)))
            ratio = img.std() / ref[near].std()
            if anisotropy > 1:
                assert rms < near_rms * (1.0 if lo < 8 else 1.5), (lo, rms)
                assert abs(ratio - 1.0) < 1.0 - contrast, (lo, ratio)
            else:  # what the anisotropic lookups fix
                assert rms > near_rms and ratio < contrast, (lo, rms, ratio)


def test_anisotropy_is_checked() -> None:
    with pytest.raises(ScenarioError, match=r"anisotropy must be an integer in 1\.\.64, got 0"):
        Renderer(_camera(), anisotropy=0)


def test_features_at_every_range() -> None:
    """Shi-Tomasi corners exist on near, middle and far surfaces."""
    camera = _camera(320, 240)
    scene = _scene()
    out = Renderer(camera, noise_sigma=0.0).render(scene, R_WC, C_W)
    corners = cv2.goodFeaturesToTrack(out.image, 2000, 0.01, 4).reshape(-1, 2)
    rng = out.range_m[corners[:, 1].astype(int), corners[:, 0].astype(int)]
    for lo, hi in ((2.0, 5.0), (5.0, 12.0), (12.0, 40.0)):
        assert np.sum((rng >= lo) & (rng < hi)) >= 20, (lo, hi)


def test_noise_determinism_and_rgb() -> None:
    camera = _camera()
    scene = _scene()
    clean = Renderer(camera, noise_sigma=0.0).render(scene, R_WC, C_W).image.astype(float)
    r = Renderer(camera, noise_sigma=3.0, seed=5)
    a = r.render(scene, R_WC, C_W, frame_index=1).image
    b = r.render(scene, R_WC, C_W, frame_index=1).image
    c = r.render(scene, R_WC, C_W, frame_index=2).image
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)
    noise = a.astype(float) - clean
    unclipped = (clean > 15) & (clean < 240)
    assert 2.7 < noise[unclipped].std() < 3.3  # sigma 3 plus rounding (1/12 level^2)
    rgb = Renderer(camera, noise_sigma=0.0, encoding="rgb8").render(scene, R_WC, C_W).image
    assert rgb.shape == (120, 160, 3)
    luma = rgb.astype(float) @ np.array([0.299, 0.587, 0.114])
    unsat = np.all((rgb > 0) & (rgb < 255), axis=-1)
    assert np.abs(luma - clean)[unsat].max() <= 1.5


def test_texture_pyramid_and_bad_options() -> None:
    tex = texture(3)
    assert tex.levels == 11
    lv0, lv1 = tex.level(0), tex.level(1)
    assert lv0.shape == (1024, 1024) and lv1.shape == (512, 512)
    np.testing.assert_allclose(lv1[3, 5], lv0[6:8, 10:12].mean(), rtol=1e-5)
    # periodic lookup: one tile further gives the same value
    x = np.array([10.3, 500.7], np.float32)
    y = np.array([7.9, 1000.2], np.float32)
    lod = np.array([0.0, 2.5], np.float32)
    shifted = tex.sample(x + 1024, y - 2048, lod)
    np.testing.assert_allclose(tex.sample(x, y, lod), shifted, rtol=1e-4)  # float32 coords
    # high contrast at every level up to 1/16 of the tile
    for k in range(7):
        assert tex.level(k).std() > 0.08, k
    with pytest.raises(ScenarioError, match="supersample"):
        Renderer(_camera(), supersample=0)
    with pytest.raises(ScenarioError, match="encoding"):
        Renderer(_camera(), encoding="bgr16")
    with pytest.raises(ScenarioError, match="positive size"):
        box((0, 0, 0), (1, 0, 1), 3)


def test_camera_effects_blur_gain_and_noise() -> None:
    from bags.sim.render import apply_gain, exposure_blur, sensor_noise

    a = np.full((4, 5), 10, dtype=np.uint8)
    b = np.full((4, 5), 21, dtype=np.uint8)
    np.testing.assert_array_equal(
        exposure_blur([a, b]), np.full((4, 5), 16)
    )  # 15.5 rounds to even
    np.testing.assert_array_equal(apply_gain(b, 1.5), np.full((4, 5), 32))
    assert int(apply_gain(np.full((1, 1), 200, dtype=np.uint8), 2.0)[0, 0]) == 255
    flat = np.full((200, 200), 100, dtype=np.uint8)
    noisy = sensor_noise(flat, np.random.default_rng(0), read_sigma=1.5, shot_gain=0.04)
    # variance read^2 + gain * I = 2.25 + 4 = 6.25 (plus 1/12 of rounding)
    assert np.var(noisy.astype(float)) == pytest.approx(6.25 + 1 / 12, rel=0.05)
    with pytest.raises(ScenarioError):
        apply_gain(a, 0.0)


def test_render_rows_with_one_pose_is_the_global_render_and_checks_its_input() -> None:
    camera = _camera()
    scene = _scene()
    r = Renderer(camera, supersample=2, noise_sigma=0.0)
    h = camera.height
    rows = r.render_rows([scene] * h, np.repeat(R_WC[None], h, 0), np.repeat(C_W[None], h, 0))
    flat = r.render(scene, R_WC, C_W)
    diff = np.abs(rows.image.astype(int) - flat.image.astype(int))
    assert diff.max() <= 1 and np.mean(diff > 0) < 0.002  # float32 rounding only
    np.testing.assert_array_equal(rows.object_id, flat.object_id)
    fin = np.isfinite(flat.range_m)
    np.testing.assert_array_equal(np.isfinite(rows.range_m), fin)
    np.testing.assert_allclose(rows.range_m[fin], flat.range_m[fin], rtol=1e-5)
    with pytest.raises(ScenarioError, match="rolling-shutter pose needs 120 rows"):
        r.render_rows([scene] * 3, np.repeat(R_WC[None], 3, 0), np.repeat(C_W[None], 3, 0))
    with pytest.raises(ScenarioError, match="same rectangles"):
        r.render_rows(
            [scene] * (h - 1) + [scene[:2]],
            np.repeat(R_WC[None], h, 0),
            np.repeat(C_W[None], h, 0),
        )


def test_render_rows_sees_each_row_from_its_own_pose() -> None:
    """Row r of a rolling render equals row r of a global render from row r's pose."""
    camera = _camera()
    scene = _scene()
    r = Renderer(camera, supersample=2, noise_sigma=0.0)
    h = camera.height
    yaw = np.linspace(0.0, 0.03, h)  # the camera turns 0.03 rad and moves 4 cm during readout
    rot = np.array(
        [[[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]] for a in yaw]
    )
    r_rows = rot @ R_WC
    c_rows = C_W + np.outer(np.linspace(0.0, 0.04, h), [1.0, 0.0, 0.0])
    out = r.render_rows([scene] * h, r_rows, c_rows)
    for row in (0, 37, 80, h - 1):
        ref = r.render(scene, r_rows[row], c_rows[row])
        assert np.abs(out.image[row].astype(int) - ref.image[row].astype(int)).max() <= 1
        np.testing.assert_array_equal(out.object_id[row], ref.object_id[row])
    # the rows really differ: a global render from row 0's pose is elsewhere at the bottom
    first = r.render(scene, r_rows[0], c_rows[0])
    assert np.abs(out.image[-1].astype(int) - first.image[-1].astype(int)).mean() > 5
