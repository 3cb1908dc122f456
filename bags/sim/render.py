"""A numpy ray caster for textured rectangles, planes and boxes, with exact ground truth.

Scene
-----
A scene is a sequence of :class:`Rect` (finite rectangles, or infinite planes with
``half_u = half_v = inf``) in the world frame; :func:`box` turns an axis-aligned box into
its six outward-facing rectangles. Each rectangle carries an ``object_id`` (uint16, 0 is
the sky), a procedural texture and a brightness. Textures are attached to the rectangle
(its own ``u``/``v`` axes, in metres), so a moving box carries its texture along.

Rendering
---------
:class:`Renderer` holds one camera (:class:`owl_core.camera.CameraModel`, any distortion
model): the unit ray of every (sub)pixel is computed once with
``CameraModel.pixel_to_bearing``, so a distorted image is rendered exactly (each
distorted pixel gets its true ray). Per frame the scene is moved into the camera frame and
every rectangle is intersected with the rays inside its conservative image bounding box
(vectorised; cost grows with the image area a rectangle covers). Then each visible
rectangle is textured once.

Anti-aliasing: ``supersample`` x ``supersample`` rays per pixel (box filter) for edges, and
anisotropic trilinear mip-mapped texture lookups that integrate over the footprint of one
ray on the surface, so far or grazing surfaces are low-pass filtered instead of shimmering.
The footprint is an ellipse: ``range * ray_spacing`` across and that over
``|cos(incidence)|`` along the ray's direction on the surface. A single lookup at the level
of the larger axis (isotropic mip-mapping) would blur a grazing surface across by the
ratio of the two (about 13 pixels sideways for ground 20 m ahead of a camera 1.5 m up),
much more than a camera's pixel does, with a blur that changes as the surface approaches;
instead ``n = ceil(ratio)`` lookups (at most ``anisotropy``) spread along the long axis are
averaged, each at the level of ``long / n`` (as GPUs filter anisotropically), so a pixel
sees about the area it covers.

Textures (:func:`texture`) are periodic 1024 x 1024 tiles of thresholded pink noise: edges
and blobs at every scale from the texel to the tile, so features exist at every range.

Rolling shutter (:meth:`Renderer.render_rows`): each image row seen from its own pose, with
the scene at its own time (the caller gives one pose and one scene per row): rectangles are
intersected with every row's rays in that row's camera frame, so the image is exact for any
motion during the readout (no bands, no warping).

Outputs (:class:`RenderedFrame`) per pixel centre: the 8-bit image (mono8 or rgb8) with
seeded Gaussian noise, the range (metres along the unit ray from the camera centre, float32,
+inf for the sky, NaN outside the camera's valid region) and the object id (uint16).
Everything is deterministic given the scene, the pose, ``seed`` and ``frame_index``.

Frames: world vectors are in the world frame, ``R_wc`` maps camera optical-frame vectors
(x right, y down, z forward) into the world frame and ``c_w`` is the camera centre.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from bags.errors import ScenarioError
from owl_core.camera import CameraModel

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

TEXTURE_SIZE = 1024
#: Number of distinct texture tiles (rectangles pick one by seed and a seeded offset).
TEXTURE_POOL = 6
SKY_INTENSITY = 200.0
#: Nearest hit distance, metres (rays closer than this miss).
NEAR = 1e-3
#: Direction of the light for the per-face shading, world frame (unit).
LIGHT_DIR = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])


@dataclass(frozen=True)
class Rect:
    """A textured rectangle (or an infinite plane) in the world frame.

    Attributes:
        origin: (3,) centre of the rectangle, metres.
        u: (3,) unit first in-plane axis. v: (3,) unit second axis, perpendicular to ``u``.
            The normal is ``u x v``; one-sided rectangles are seen only from that side.
        half_u, half_v: half extents along ``u`` and ``v``, metres (``inf`` = unbounded).
        object_id: id written in the object-id image (1..65535; 0 is the sky).
        texture_seed: which texture tile (any int; tiles are cached per seed).
        texel_m: size of one texel on the surface, metres.
        brightness: albedo factor in (0, 1].
        tint: (3,) RGB factors for rgb8 images (their luminance is normalised to 1).
        two_sided: visible from both sides (planes) or only from the normal side (box faces).
    """

    origin: tuple[float, float, float]
    u: tuple[float, float, float]
    v: tuple[float, float, float]
    half_u: float
    half_v: float
    object_id: int
    texture_seed: int = 0
    texel_m: float = 0.01
    brightness: float = 1.0
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    two_sided: bool = True

    @property
    def normal(self) -> F64:
        """(3,) unit normal u x v."""
        return np.cross(np.asarray(self.u, float), np.asarray(self.v, float))

    def corners(self) -> F64:
        """(4, 3) corners, world frame (for an unbounded rectangle, at 1e4 m)."""
        o, u, v = (np.asarray(a, float) for a in (self.origin, self.u, self.v))
        hu = min(self.half_u, 1e4)
        hv = min(self.half_v, 1e4)
        return np.array([o + su * hu * u + sv * hv * v for su, sv in _SIGNS])

    def contains(self, points: npt.ArrayLike, tol: float = 1e-4) -> npt.NDArray[np.bool_]:
        """Which (N, 3) world points lie on the rectangle (within ``tol`` metres)."""
        p = np.asarray(points, float) - np.asarray(self.origin, float)
        du = p @ np.asarray(self.u, float)
        dv = p @ np.asarray(self.v, float)
        dn = p @ self.normal
        out: npt.NDArray[np.bool_] = (
            (np.abs(dn) <= tol)
            & (np.abs(du) <= self.half_u + tol)
            & (np.abs(dv) <= self.half_v + tol)
        )
        return out


_SIGNS = ((-1, -1), (1, -1), (1, 1), (-1, 1))


def box(
    center: npt.ArrayLike,
    size: npt.ArrayLike,
    object_id: int,
    *,
    texture_seed: int = 0,
    texel_m: float = 0.01,
    brightness: float = 1.0,
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> list[Rect]:
    """The six outward-facing faces of an axis-aligned box.

    Args:
        center: (3,) box centre, world frame, metres.
        size: (3,) full edge lengths along world x, y, z, metres (> 0).
        object_id: id of the whole box. Each face gets its own texture seed
            (``texture_seed + face``) and a slightly different brightness, so edges show.
    """
    c = np.asarray(center, float)
    h = 0.5 * np.asarray(size, float)
    if c.shape != (3,) or h.shape != (3,) or not np.all(h > 0):
        msg = f"box needs a (3,) centre and (3,) positive size, got {center!r}, {size!r}"
        raise ScenarioError(msg)
    eye = np.eye(3)
    faces = []
    for axis in range(3):
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        for sign in (1.0, -1.0):
            n = sign * eye[axis]
            u = eye[a1]
            v = np.cross(n, u)  # u x v = n
            origin = c + n * h[axis]
            k = len(faces)
            faces.append(
                Rect(
                    origin=tuple(origin),
                    u=tuple(u),
                    v=tuple(v),
                    half_u=float(h[a1]),
                    half_v=float(h[a2]),
                    object_id=object_id,
                    texture_seed=texture_seed + k,
                    texel_m=texel_m,
                    brightness=brightness * (0.8 + 0.04 * k),
                    tint=tint,
                    two_sided=False,
                )
            )
    return faces


@dataclass(frozen=True)
class MipTexture:
    """A periodic square texture with its mip pyramid, flattened for vectorised lookups.

    Each level of edge ``s`` is stored as an ``(s + 1, s + 1)`` block whose last row and
    column repeat the first ones (periodic padding), so a bilinear lookup needs no wrap of
    its second texel.

    Attributes:
        flat: all padded levels concatenated, float32 in [0, 1].
        offsets: (L,) int32 start of each level in ``flat``.
        sizes: (L,) int32 edge length of each level (1024, 512, ..., 1).
    """

    flat: F32
    offsets: npt.NDArray[np.int32]
    sizes: npt.NDArray[np.int32]

    @property
    def levels(self) -> int:
        """Number of mip levels."""
        return int(self.sizes.shape[0])

    def level(self, k: int) -> F32:
        """(s, s) copy of mip level ``k`` (without the padding)."""
        s = int(self.sizes[k])
        block = self.flat[self.offsets[k] : self.offsets[k] + (s + 1) * (s + 1)]
        return block.reshape(s + 1, s + 1)[:s, :s].copy()

    def sample(self, x: F32, y: F32, lod: F32) -> F32:
        """Trilinear lookup at texel coordinates (x, y) of level 0 and level of detail lod.

        Args:
            x, y: (N,) float32 texel coordinates (level-0 texels, periodic).
            lod: (N,) float32 level of detail (0 = finest), clipped to the pyramid.

        Returns:
            (N,) float32 texture values.
        """
        lod = np.clip(lod, np.float32(0.0), np.float32(self.levels - 1))
        l0 = np.minimum(lod.astype(np.int32), np.int32(self.levels - 2))
        frac = lod - l0
        a = self._bilinear(x, y, l0)
        b = self._bilinear(x, y, l0 + np.int32(1))
        out: F32 = a + frac * (b - a)
        return out

    def _bilinear(self, x: F32, y: F32, lvl: npt.NDArray[np.int32]) -> F32:
        scale = np.ldexp(np.float32(1.0), -lvl)
        xs = x * scale - np.float32(0.5)
        ys = y * scale - np.float32(0.5)
        fx = np.floor(xs)
        fy = np.floor(ys)
        wx = xs - fx
        wy = ys - fy
        # np.take: the same gathers as indexing, faster on 1-D arrays
        size = np.take(self.sizes, lvl)
        mask = size - np.int32(1)
        stride = size + np.int32(1)
        i00 = np.take(self.offsets, lvl) + (fy.astype(np.int32) & mask) * stride
        i00 += fx.astype(np.int32) & mask
        f = self.flat
        a = np.take(f, i00)
        b = np.take(f, i00 + 1)
        i00 += stride
        c = np.take(f, i00)
        d = np.take(f, i00 + 1)
        top = a + wx * (b - a)
        bot = c + wx * (d - c)
        out: F32 = top + wy * (bot - top)
        return out


def _pink(rng: np.random.Generator, n: int) -> F64:
    """(n, n) periodic noise with amplitude ~ 1/frequency (equal energy per octave)."""
    k = np.fft.fftfreq(n)
    kk = np.hypot(k[:, None], k[None, :])
    kk[0, 0] = np.inf
    spectrum = np.fft.fft2(rng.standard_normal((n, n))) / kk
    field: F64 = np.real(np.fft.ifft2(spectrum))
    field -= field.mean()
    field /= field.std()
    return field


@functools.cache
def texture(seed: int, size: int = TEXTURE_SIZE) -> MipTexture:
    """The mip-mapped texture tile for ``seed`` (cached; deterministic).

    Thresholded pink noise (sharp-edged blobs at every scale: corners for a tracker at
    every range) mixed with a softer pink field; values in about [0.1, 0.9].
    """
    if size < 2 or size & (size - 1):
        msg = f"texture size must be a power of two >= 2, got {size}"
        raise ScenarioError(msg)
    rng = np.random.default_rng([0x0A11, seed & 0xFFFFFFFF])
    tex = 0.5 + 0.3 * np.tanh(3.0 * _pink(rng, size)) + 0.1 * np.tanh(_pink(rng, size))
    levels = [tex.astype(np.float32)]
    while levels[-1].shape[0] > 1:
        t = levels[-1]
        levels.append(0.25 * (t[0::2, 0::2] + t[1::2, 0::2] + t[0::2, 1::2] + t[1::2, 1::2]))
    padded = [np.pad(lv, ((0, 1), (0, 1)), mode="wrap") for lv in levels]
    sizes = np.array([lv.shape[0] for lv in levels], dtype=np.int32)
    counts = (sizes + 1) * (sizes + 1)
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int32)
    flat = np.concatenate([p.ravel() for p in padded]).astype(np.float32)
    return MipTexture(flat, offsets, sizes)


@dataclass(frozen=True)
class RenderedFrame:
    """One rendered image with its per-pixel ground truth.

    Attributes:
        image: (H, W) uint8 (mono8) or (H, W, 3) uint8 (rgb8).
        range_m: (H, W) float32 distance from the camera centre along the pixel-centre ray,
            metres; +inf where the ray hits nothing, NaN outside the camera's valid region.
        object_id: (H, W) uint16 id of the object hit by the pixel-centre ray (0 = sky).
    """

    image: npt.NDArray[np.uint8]
    range_m: F32
    object_id: npt.NDArray[np.uint16]


@dataclass
class _RayGrid:
    """Unit rays of a pixel grid with the bounds used for culling."""

    rays: F32  # (h, w, 3)
    spacing: F32  # (h, w) angular spacing between neighbouring rays, rad
    col_lo: F64 = field(init=False)
    col_hi: F64 = field(init=False)
    row_lo: F64 = field(init=False)
    row_hi: F64 = field(init=False)

    def __post_init__(self) -> None:
        r = self.rays.astype(np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            ok = r[..., 2] > 1e-6
            nx = np.where(ok, r[..., 0] / np.where(ok, r[..., 2], 1.0), np.nan)
            ny = np.where(ok, r[..., 1] / np.where(ok, r[..., 2], 1.0), np.nan)
        self.wide = bool(np.any(~ok & np.isfinite(r[..., 2])))
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows/columns
            self.col_lo = np.nan_to_num(np.nanmin(nx, axis=0), nan=np.inf)
            self.col_hi = np.nan_to_num(np.nanmax(nx, axis=0), nan=-np.inf)
            self.row_lo = np.nan_to_num(np.nanmin(ny, axis=1), nan=np.inf)
            self.row_hi = np.nan_to_num(np.nanmax(ny, axis=1), nan=-np.inf)

    def window(self, poly_c: F64) -> tuple[slice, slice] | None:
        """Conservative (rows, cols) slice of rays that can hit a convex camera-frame polygon."""
        h, w = self.rays.shape[:2]
        if self.wide:
            return slice(0, h), slice(0, w)
        clipped = _clip_near(poly_c, 1e-4)
        if clipped.shape[0] == 0:
            return None
        nx = clipped[:, 0] / clipped[:, 2]
        ny = clipped[:, 1] / clipped[:, 2]
        cols = np.flatnonzero((self.col_hi >= nx.min()) & (self.col_lo <= nx.max()))
        rows = np.flatnonzero((self.row_hi >= ny.min()) & (self.row_lo <= ny.max()))
        if cols.size == 0 or rows.size == 0:
            return None
        return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def _clip_near(poly: F64, z_min: float) -> F64:
    """Clip a convex polygon (k, 3) to z >= z_min (Sutherland-Hodgman, one plane)."""
    out = []
    k = poly.shape[0]
    for i in range(k):
        a, b = poly[i], poly[(i + 1) % k]
        ina, inb = a[2] >= z_min, b[2] >= z_min
        if ina:
            out.append(a)
        if ina != inb:
            s = (z_min - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.array(out).reshape(-1, 3)


def _ray_grid(camera: CameraModel, ss: int) -> _RayGrid:
    """Rays through the ss x ss sub-pixel sample centres of every pixel (row-major)."""
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    us = (np.arange(camera.width)[:, None] + offs[None, :]).ravel()
    vs = (np.arange(camera.height)[:, None] + offs[None, :]).ravel()
    uu, vv = np.meshgrid(us, vs)
    pix = np.stack([uu, vv], axis=-1)
    rays = camera.pixel_to_bearing(pix)
    step = 1.0 / ss
    du = camera.pixel_to_bearing(pix + np.array([step, 0.0]))
    dv = camera.pixel_to_bearing(pix + np.array([0.0, step]))
    with np.errstate(invalid="ignore"):
        spacing = np.maximum(
            np.linalg.norm(du - rays, axis=-1), np.linalg.norm(dv - rays, axis=-1)
        )
    spacing = np.where(np.isfinite(spacing), spacing, np.nanmax(spacing))
    return _RayGrid(rays.astype(np.float32), spacing.astype(np.float32))


class Renderer:
    """Renders scenes of :class:`Rect` for one camera.

    Args:
        camera: the camera model (distortion rendered exactly through pixel_to_bearing).
        supersample: rays per pixel along each axis (1..4); 2 is a good default.
        noise_sigma: standard deviation of the additive Gaussian image noise, grey levels.
        seed: base seed of the image noise (frame k uses the stream (seed, k)).
        encoding: "mono8" or "rgb8".
        mipmap: filter textures by the ray footprint (True). False samples the finest
            level only (aliased; for comparisons and tests).
        anisotropy: most lookups along the long axis of a grazing ray's footprint (1..64);
            1 is isotropic mip-mapping (the level of the long axis: blurred across).

    Raises:
        ScenarioError: invalid supersample, noise or encoding (names the value).
    """

    def __init__(
        self,
        camera: CameraModel,
        *,
        supersample: int = 2,
        noise_sigma: float = 2.0,
        seed: int = 0,
        encoding: str = "mono8",
        mipmap: bool = True,
        anisotropy: int = 16,
    ) -> None:
        if not isinstance(supersample, int) or not 1 <= supersample <= 4:
            msg = f"supersample must be an integer in 1..4, got {supersample!r}"
            raise ScenarioError(msg)
        if not (math.isfinite(noise_sigma) and noise_sigma >= 0.0):
            msg = f"noise_sigma must be finite and >= 0, got {noise_sigma!r}"
            raise ScenarioError(msg)
        if encoding not in ("mono8", "rgb8"):
            msg = f"encoding must be mono8 or rgb8, got {encoding!r}"
            raise ScenarioError(msg)
        if not isinstance(anisotropy, int) or not 1 <= anisotropy <= 64:
            msg = f"anisotropy must be an integer in 1..64, got {anisotropy!r}"
            raise ScenarioError(msg)
        self.camera = camera
        self.supersample = supersample
        self.noise_sigma = float(noise_sigma)
        self.seed = int(seed)
        self.encoding = encoding
        self.mipmap = bool(mipmap)
        self.anisotropy = anisotropy
        self._fine = _ray_grid(camera, supersample)
        self._centre = self._fine if supersample == 1 else _ray_grid(camera, 1)

    # ----------------------------------------------------------------------------------

    def render(
        self,
        scene: Sequence[Rect],
        R_wc: npt.ArrayLike,
        c_w: npt.ArrayLike,
        frame_index: int = 0,
    ) -> RenderedFrame:
        """Render ``scene`` seen from pose (R_wc, c_w).

        Args:
            scene: rectangles in the world frame.
            R_wc: (3, 3) rotation taking camera optical-frame vectors to the world frame.
            c_w: (3,) camera centre in the world frame, metres.
            frame_index: selects the noise stream (seed, frame_index).

        Returns:
            RenderedFrame (image, range_m, object_id) at the camera's resolution.
        """
        rot = np.asarray(R_wc, dtype=np.float64)
        centre = np.asarray(c_w, dtype=np.float64)
        if rot.shape != (3, 3) or centre.shape != (3,):
            msg = f"pose needs R_wc (3, 3) and c_w (3,), got {rot.shape} and {centre.shape}"
            raise ScenarioError(msg)
        local = [self._to_camera(r, rot, centre) for r in scene]
        return self._render_local(scene, local, frame_index)

    def render_rows(
        self,
        scenes: Sequence[Sequence[Rect]],
        R_wc: npt.ArrayLike,
        c_w: npt.ArrayLike,
        frame_index: int = 0,
    ) -> RenderedFrame:
        """Render with a rolling shutter: image row r from pose (R_wc[r], c_w[r]) with the
        scene ``scenes[r]``.

        Args:
            scenes: H rectangle lists, one per image row, all with the same rectangles in
                the same order (only their origin and axes may differ from row to row:
                objects moving during the readout); ids, textures and brightness are
                taken from the first.
            R_wc: (H, 3, 3) camera-to-world rotation of each row's time.
            c_w: (H, 3) camera centre of each row's time, world, metres.
            frame_index: selects the noise stream (seed, frame_index).

        Returns:
            RenderedFrame; ``range_m`` is each pixel's distance along its ray from the
            camera centre of its row's time.
        """
        h = self.camera.height
        rot = np.asarray(R_wc, dtype=np.float64)
        centre = np.asarray(c_w, dtype=np.float64)
        if rot.shape != (h, 3, 3) or centre.shape != (h, 3) or len(scenes) != h:
            msg = (
                f"a rolling-shutter pose needs {h} rows: R_wc ({h}, 3, 3), c_w ({h}, 3) and "
                f"{h} scenes, got {rot.shape}, {centre.shape} and {len(scenes)}"
            )
            raise ScenarioError(msg)
        count = len(scenes[0])
        if any(len(s) != count for s in scenes):
            msg = "every row's scene must hold the same rectangles (same count and order)"
            raise ScenarioError(msg)
        local = [self._to_camera_rows([s[k] for s in scenes], rot, centre) for k in range(count)]
        return self._render_local(scenes[0], local, frame_index)

    def _render_local(
        self, scene: Sequence[Rect], local: list[dict[str, object]], frame_index: int
    ) -> RenderedFrame:
        """Ray cast, shade and add noise, given each rectangle in camera coordinates."""
        h, w = self.camera.height, self.camera.width
        ss = self.supersample
        rgb = self.encoding == "rgb8"
        tints = np.array([(1.0, 1.0, 1.0)] + [_unit_luma(r.tint) for r in scene], np.float32)

        # pixel-centre rays: range, object id, and the colour of pixels away from edges
        cg = self._centre
        best_t, best_k = self._intersect(cg, local, "window_centre")
        valid = np.isfinite(cg.rays[..., 0])
        ids_lut = np.array([0] + [r.object_id for r in scene], dtype=np.uint16)
        object_id = ids_lut[best_k + 1]
        range_m = np.where(valid, best_t, np.float32(np.nan)).astype(np.float32)

        # edge pixels: some sub-pixel ray hits another rectangle than the centre ray
        if ss > 1:
            ft, fk = self._intersect(self._fine, local, "window_fine")
            edge = np.any(fk.reshape(h, ss, w, ss) != best_k[:, None, :, None], axis=(1, 3))
            edge_fine = np.repeat(np.repeat(edge, ss, axis=0), ss, axis=1)
        else:
            edge = np.zeros((h, w), dtype=bool)

        shade = self._shade(scene, local, cg, best_t, best_k, ~edge, "window_centre")
        img = shade[..., None] * tints[best_k + 1] if rgb else shade
        if ss > 1 and edge.any():
            fg = self._fine
            fshade = self._shade(scene, local, fg, ft, fk, edge_fine, "window_fine")
            if rgb:
                fine = (fshade[..., None] * tints[fk + 1]).reshape(h, ss, w, ss, 3)
                img = np.where(edge[..., None], fine.mean(axis=(1, 3)), img)
            else:
                img = np.where(edge, fshade.reshape(h, ss, w, ss).mean(axis=(1, 3)), img)
        if self.noise_sigma > 0:
            rng = np.random.default_rng([self.seed & 0xFFFFFFFF, int(frame_index)])
            img = img + rng.normal(0.0, self.noise_sigma, img.shape).astype(np.float32)
        image = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        return RenderedFrame(image, range_m, object_id)

    def _shade(
        self,
        scene: Sequence[Rect],
        local: list[dict[str, object]],
        grid: _RayGrid,
        best_t: F32,
        best_k: npt.NDArray[np.int32],
        wanted: npt.NDArray[np.bool_],
        key: str,
    ) -> F32:
        """Grey level of the rays in ``wanted`` (sky / invalid elsewhere)."""
        shade = np.full(best_t.shape, SKY_INTENSITY, dtype=np.float32)
        shade[~np.isfinite(grid.rays[..., 0])] = 0.0
        for k, (rect, loc) in enumerate(zip(scene, local, strict=True)):
            win = loc[key]
            if win is None:
                continue
            sel = (best_k[win] == k) & wanted[win]
            if not sel.any():
                continue
            d = grid.rays[win][sel]
            t = best_t[win][sel]
            if "rows" in loc:  # rolling shutter: each selected ray's row pose
                rows = (np.nonzero(sel)[0] + win[0].start) // self._subrows(grid)
                su, sv, cos, along = _surface_rows(loc, rows, d, t)
            else:
                su, sv, cos, along = _surface(loc, d, t)
            shade[win][sel] = self._texture(rect, su, sv, cos, t, grid.spacing[win][sel], along)
        return shade

    def _subrows(self, grid: _RayGrid) -> int:
        """Ray rows per image row of ``grid`` (the supersampling factor)."""
        return int(grid.rays.shape[0] // self.camera.height)

    # ----------------------------------------------------------------------------------

    def _to_camera(self, rect: Rect, rot: F64, centre: F64) -> dict[str, object]:
        o = rot.T @ (np.asarray(rect.origin, float) - centre)
        u = rot.T @ np.asarray(rect.u, float)
        v = rot.T @ np.asarray(rect.v, float)
        n = np.cross(u, v)
        facing = rect.two_sided or float(o @ n) < 0.0  # camera on the normal side
        corners = (rot.T @ (rect.corners() - centre).T).T
        loc: dict[str, object] = {
            "o": o,
            "u": u,
            "v": v,
            "n": n,
            "half": (rect.half_u, rect.half_v),
        }
        if facing:
            loc["window_fine"] = self._fine.window(corners)
            loc["window_centre"] = self._centre.window(corners)
        else:
            loc["window_fine"] = loc["window_centre"] = None
        return loc

    def _intersect(
        self, grid: _RayGrid, local: list[dict[str, object]], key: str
    ) -> tuple[F32, npt.NDArray[np.int32]]:
        """Nearest hit distance (inf if none) and rectangle index (-1 if none) per ray."""
        shape = grid.rays.shape[:2]
        best_t = np.full(shape, np.inf, dtype=np.float32)
        best_k = np.full(shape, -1, dtype=np.int32)
        for k, loc in enumerate(local):
            win = loc[key]
            if win is None:
                continue
            if "rows" in loc:
                self._intersect_rows(grid, loc, win, k, best_t, best_k)  # type: ignore[arg-type]
                continue
            o, u, v, n = (loc[name] for name in ("o", "u", "v", "n"))
            axes = np.stack([n, u, v], axis=1).astype(np.float32)  # (3, 3) columns
            d = grid.rays[win]
            proj = d @ axes  # (h, w, 3): d.n, d.u, d.v
            dn = proj[..., 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.float32(o @ n) / dn
                hit = (t > NEAR) & (t < best_t[win])
                half_u, half_v = loc["half"]  # type: ignore[misc]
                if math.isfinite(half_u):
                    hit &= np.abs(t * proj[..., 1] - np.float32(o @ u)) <= np.float32(half_u)
                if math.isfinite(half_v):
                    hit &= np.abs(t * proj[..., 2] - np.float32(o @ v)) <= np.float32(half_v)
            best_t[win] = np.where(hit, t, best_t[win])
            best_k[win] = np.where(hit, k, best_k[win])
        return best_t, best_k

    def _intersect_rows(
        self,
        grid: _RayGrid,
        loc: dict[str, object],
        win: tuple[slice, slice],
        k: int,
        best_t: F32,
        best_k: npt.NDArray[np.int32],
    ) -> None:
        """:meth:`_intersect` for one rectangle given per image row (rolling shutter):
        each ray row is tested against the rectangle in its own row's camera frame."""
        rows = np.arange(win[0].start, win[0].stop) // self._subrows(grid)
        o, u, v, n = (np.asarray(loc[name], np.float32)[rows] for name in ("o", "u", "v", "n"))
        axes = np.stack([n, u, v], axis=2)  # (r, 3, 3) columns n, u, v per row
        d = grid.rays[win]
        # d.n, d.u, d.v per ray: the sum written out (the same float32 operations in the same
        # order as einsum("rci,rij->rcj"), so the same bits, at under half its time)
        proj = d[..., 0:1] * axes[:, None, 0] + d[..., 1:2] * axes[:, None, 1]
        proj += d[..., 2:3] * axes[:, None, 2]
        dn = proj[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.einsum("ri,ri->r", o, n)[:, None] / dn
            hit = (t > NEAR) & (t < best_t[win]) & np.asarray(loc["facing"])[rows][:, None]
            half_u, half_v = loc["half"]  # type: ignore[misc]
            if math.isfinite(half_u):
                ou = np.einsum("ri,ri->r", o, u)[:, None]
                hit &= np.abs(t * proj[..., 1] - ou) <= np.float32(half_u)
            if math.isfinite(half_v):
                ov = np.einsum("ri,ri->r", o, v)[:, None]
                hit &= np.abs(t * proj[..., 2] - ov) <= np.float32(half_v)
        best_t[win] = np.where(hit, t, best_t[win])
        best_k[win] = np.where(hit, k, best_k[win])

    def _to_camera_rows(self, rects: Sequence[Rect], rot: F64, centre: F64) -> dict[str, object]:
        """One rectangle at each image row's time (H versions) in each row's camera frame:
        (H, 3) origin and axes, which rows see its front, and conservative windows."""
        origin = np.array([r.origin for r in rects], dtype=np.float64)
        u_w = np.array([r.u for r in rects], dtype=np.float64)
        v_w = np.array([r.v for r in rects], dtype=np.float64)
        first = rects[0]
        o = np.einsum("rji,rj->ri", rot, origin - centre)
        u = np.einsum("rji,rj->ri", rot, u_w)
        v = np.einsum("rji,rj->ri", rot, v_w)
        n = np.cross(u, v)
        facing = np.full(len(rects), True) if first.two_sided else np.einsum("ri,ri->r", o, n) < 0
        hu, hv = min(first.half_u, 1e4), min(first.half_v, 1e4)
        corners = np.stack(
            [o + su * hu * u + sv * hv * v for su, sv in _SIGNS], axis=1
        )  # (H, 4, 3), camera frame of each row
        loc: dict[str, object] = {
            "o": o,
            "u": u,
            "v": v,
            "n": n,
            "half": (first.half_u, first.half_v),
            "rows": True,
            "facing": facing,
        }
        visible = bool(facing.any())
        loc["window_fine"] = self._rows_window(self._fine, corners, facing) if visible else None
        loc["window_centre"] = (
            self._rows_window(self._centre, corners, facing) if visible else None
        )
        return loc

    def _rows_window(
        self, grid: _RayGrid, corners: F64, facing: npt.NDArray[np.bool_]
    ) -> tuple[slice, slice] | None:
        """Conservative (rows, cols) slice of ``grid`` rays that can hit a rectangle whose
        corners (H, 4, 3) are given in each image row's camera frame: a ray row is kept
        when its row's projected rectangle spans it, the columns span every kept row's
        projection. A rectangle partly behind some row's camera gets the whole image."""
        h, w = grid.rays.shape[:2]
        z = corners[..., 2]
        if not (z >= 1e-4)[facing].any():
            return None
        if grid.wide or (z < 1e-4)[facing].any():
            return slice(0, h), slice(0, w)
        nx = corners[..., 0] / z
        ny = corners[..., 1] / z
        pix_rows = np.arange(h) // self._subrows(grid)
        keep = (
            facing[pix_rows]
            & (grid.row_hi >= ny.min(axis=1)[pix_rows])
            & (grid.row_lo <= ny.max(axis=1)[pix_rows])
        )
        if not keep.any():
            return None
        kept = np.unique(pix_rows[keep])
        lo, hi = nx[kept].min(), nx[kept].max()
        cols = np.flatnonzero((grid.col_hi >= lo) & (grid.col_lo <= hi))
        rows = np.flatnonzero(keep)
        if cols.size == 0:
            return None
        return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)

    def _texture(
        self, rect: Rect, su: F32, sv: F32, cos: F32, t: F32, spacing: F32, along: F32
    ) -> F32:
        """Grey level of surface points (su, sv) m on ``rect`` seen at range t (m) and
        incidence cosine ``cos`` by rays ``spacing`` rad apart; ``along`` (M, 2): the unit
        direction (su, sv) in which each footprint is long (the ray's direction on the
        surface)."""
        tex = texture(rect.texture_seed % TEXTURE_POOL)
        inv_texel = np.float32(1.0 / rect.texel_m)
        # decorrelate rectangles sharing a tile: a texel offset per rectangle seed
        x0 = su * inv_texel + np.float32((rect.texture_seed * 7919) % TEXTURE_SIZE)
        y0 = sv * inv_texel + np.float32((rect.texture_seed * 104729) % TEXTURE_SIZE)
        long_px = t * spacing / cos * inv_texel  # footprint axes in level-0 texels
        if not self.mipmap:
            val = tex.sample(x0, y0, np.zeros_like(long_px))
        else:
            # n lookups spread over the long axis, each filtering long / n (>= the short
            # axis t * spacing: n <= 1 / cos); n = 1 where the footprint is round
            n = np.clip(np.ceil(np.float32(1.0) / cos - np.float32(1e-3)), 1, self.anisotropy)
            n = n.astype(np.float32)
            with np.errstate(divide="ignore"):
                lod = np.log2(np.maximum(long_px / n, np.float32(1.0)))
            val = np.zeros_like(x0)
            for i in range(int(n.max())):  # n = 1 (anisotropy 1): one lookup at s = 0
                m = np.flatnonzero(n > i)
                # sample i of n at (i + 1/2) / n - 1/2 of the long axis
                s = ((np.float32(i) + np.float32(0.5)) / n[m] - np.float32(0.5)) * long_px[m]
                val[m] += tex.sample(x0[m] + s * along[m, 0], y0[m] + s * along[m, 1], lod[m])
            val /= n
        normal_w = rect.normal
        lambert = 0.6 + 0.4 * abs(float(normal_w @ LIGHT_DIR))
        gain = np.float32(255.0 * rect.brightness * lambert)
        out: F32 = np.float32(10.0) + gain * val
        return out


def _surface(loc: dict[str, object], d: F32, t: F32) -> tuple[F32, F32, F32, F32]:
    """Surface coordinates (su, sv), m, |incidence cosine| of rays d (M, 3) hitting a
    rectangle (camera-frame ``loc``) at ranges t (M,), and (M, 2) the unit direction of
    each ray on the surface in (su, sv) (where its footprint is long)."""
    o, u, v, n = (np.asarray(loc[name], np.float32) for name in ("o", "u", "v", "n"))
    du, dv = d @ u, d @ v
    su = t * du - np.float32(o @ u)
    sv = t * dv - np.float32(o @ v)
    cos = np.maximum(np.abs(d @ n), np.float32(1e-3))
    return su, sv, cos, _unit2(du, dv)


def _unit2(du: F32, dv: F32) -> F32:
    """(M, 2) unit vectors along (du, dv) (M,) each; (1, 0) where both vanish."""
    norm = np.hypot(du, dv)
    flat = norm < np.float32(1e-9)
    out: F32 = np.stack([np.where(flat, 1.0, du), np.where(flat, 0.0, dv)], axis=1)
    out /= np.where(flat, np.float32(1.0), norm)[:, None]
    return out


def _surface_rows(
    loc: dict[str, object], rows: npt.NDArray[np.int64], d: F32, t: F32
) -> tuple[F32, F32, F32, F32]:
    """:func:`_surface` with the rectangle per image row: ray i in row ``rows[i]``."""
    o, u, v, n = (np.asarray(loc[name], np.float32)[rows] for name in ("o", "u", "v", "n"))
    du, dv = _rowdot(d, u), _rowdot(d, v)
    su = t * du - _rowdot(o, u)
    sv = t * dv - _rowdot(o, v)
    cos = np.maximum(np.abs(_rowdot(d, n)), np.float32(1e-3))
    return su, sv, cos, _unit2(du, dv)


def _rowdot(a: F32, b: F32) -> F32:
    """Row-wise dot products of (M, 3) arrays, (M,): the sum written out (the same float32
    operations in the same order as ``einsum("mi,mi->m")``, so the same bits, faster)."""
    out: F32 = a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]
    out += a[:, 2] * b[:, 2]
    return out


def _unit_luma(tint: tuple[float, float, float]) -> tuple[float, float, float]:
    """Scale an RGB tint so that its Rec. 601 luminance is 1."""
    r, g, b = tint
    luma = 0.299 * r + 0.587 * g + 0.114 * b
    if luma <= 0:
        msg = f"tint must have positive luminance, got {tint!r}"
        raise ScenarioError(msg)
    return (r / luma, g / luma, b / luma)


# --- effects of real cameras (applied to rendered images) ---------------------------------


def exposure_blur(images: Sequence[npt.NDArray[np.uint8]]) -> npt.NDArray[np.uint8]:
    """Motion blur: the mean of renders spread over the exposure time (same shape each)."""
    if not images:
        msg = "exposure_blur needs at least one image"
        raise ScenarioError(msg)
    acc = np.zeros(images[0].shape, dtype=np.float32)
    for im in images:
        acc += im
    return np.clip(np.rint(acc / len(images)), 0, 255).astype(np.uint8)


def apply_gain(image: npt.NDArray[np.uint8], gain: float) -> npt.NDArray[np.uint8]:
    """A camera gain / exposure change: grey levels times ``gain`` (> 0), saturating."""
    if not (math.isfinite(gain) and gain > 0):
        msg = f"gain must be positive, got {gain!r}"
        raise ScenarioError(msg)
    return np.clip(np.rint(image.astype(np.float32) * gain), 0, 255).astype(np.uint8)


def sensor_noise(
    image: npt.NDArray[np.uint8],
    rng: np.random.Generator,
    read_sigma: float = 1.5,
    shot_gain: float = 0.04,
) -> npt.NDArray[np.uint8]:
    """Sensor noise: Gaussian read noise plus signal-dependent shot noise, variance
    ``read_sigma^2 + shot_gain * I`` (grey levels^2) at grey level I."""
    img = image.astype(np.float32)
    sigma = np.sqrt(read_sigma**2 + shot_gain * img)
    noisy = img + sigma * rng.standard_normal(img.shape).astype(np.float32)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
