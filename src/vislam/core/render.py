"""Rendered stereo images of a simulated drive: textured planes with known geometry.

:func:`build_scene` lays textured rectangles along the path of a
:class:`~vislam.core.simulate.SimulatedDrive` — the road surface (ground quads every
``segment_m`` metres, ``road_half_width_m`` to each side) and façades on both sides
(vertical quads ``facade_offset_m`` from the path, random heights), each with a
texture from scikit-image's sample images (chosen, offset and brightness-scaled by the
seed). :func:`render_pair` renders the rectified left/right grey images of a frame by
casting the ray of every pixel onto the planes (nearest hit wins), sampling the
texture there with ``cv2.remap`` from mip levels kept separately along the texture's two
axes (a ripmap): each pixel's footprint on the plane gives its level along each axis
(``lod_bias`` added), and the four levels around it are sampled bilinearly and blended, so a
surface's image changes continuously with its distance and a slanted surface (the road, a
façade far ahead) is filtered along its slant only, as a camera pixel integrates its own
stretched footprint. Then the image is blurred (Gaussian, ``blur_sigma_px``) and pixel
noise is added (``noise_grey_levels``). Everything not on a plane is a featureless sky.
Each texture is cropped to a multiple of 2^6 texels so that every level is exactly half
the one below and the levels show the same pattern at the same place (odd sizes would
wrap each level with another period).

:func:`surface_point` casts one ray onto the same planes, which is how the tracker's
observations are graded against the true geometry.

Frames: world as in :mod:`vislam.core.simulate` (z up); camera x right, y down, z forward.
Pure computation (no file I/O); the same drive and options give the same images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vislam.core.lie import se3_inverse

__all__ = ["RenderOptions", "Scene", "build_scene", "render_pair", "surface_point", "camera_poses"]


@dataclass(frozen=True)
class RenderOptions:
    """How the scene is built and rendered (units in the names)."""

    #: Image size (px); KITTI's rectified grey images are 1242 x 375.
    width_px: int = 1242
    height_px: int = 375
    #: Length of each road / façade quad along the path (m).
    segment_m: float = 6.0
    #: Road surface half-width (m).
    road_half_width_m: float = 14.0
    #: Lateral distance of the façades from the path (m), per side: uniform in this range per block.
    facade_offset_m: tuple = (8.0, 12.0)
    #: Façade height range (m).
    facade_height_m: tuple = (6.0, 14.0)
    #: Texture resolution: metres per texel of the finest mip level.
    texel_m: float = 0.01
    #: Road texture scale (metres per texel; coarser than façades).
    road_texel_m: float = 0.006
    #: Gaussian blur of the rendered image (px, 1σ) and white pixel noise (grey levels, 1σ).
    blur_sigma_px: float = 0.6
    noise_grey_levels: float = 1.5
    #: Grey level of the sky (no texture, no corners).
    sky_grey: float = 205.0
    #: Added to every pixel's mip level along each texture axis (log2 of its footprint's extent F
    #: in texels along that axis). Level L is the texture halved L times along the axis (a
    #: Gaussian of 1σ ≈ 0.58·2^L texels, with its own texel grid ≈ 0.65·2^L); a camera pixel
    #: integrates a box of F texels (1σ = F/√12 ≈ 0.29 F): equal at L ≈ log2 F - 1.
    lod_bias: float = -1.0
    #: Planes farther than this from the camera are not drawn (m).
    max_distance_m: float = 150.0
    #: Extra road beyond the last frame (m), so the end of the drive still looks ahead.
    lookahead_m: float = 120.0


@dataclass(frozen=True, eq=False)
class Scene:
    """Textured rectangles: origin (Q, 3), unit axes e1, e2 (Q, 3), lengths (Q, 2), unit
    normal (Q, 3), texture index (Q,), texel size (Q,), texture offset (Q, 2) and gain
    (Q,); textures: one ripmap per texture (``rip[ly][lx]``, float32 images; :func:`_ripmap`)."""

    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    lengths: np.ndarray
    normal: np.ndarray
    texture: np.ndarray
    texel_m: np.ndarray
    offset: np.ndarray
    gain: np.ndarray
    textures: list
    kind: np.ndarray  # 0 road, 1 facade

    @property
    def n_quads(self) -> int:
        return int(self.origin.shape[0])


_ROAD_TEXTURES = ("gravel", "grass")  # not brick: a regular pattern that KLT can slip along
_FACADE_TEXTURES = ("brick", "camera", "astronaut", "coffee", "rocket", "chelsea", "hubble_deep_field",
                    "immunohistochemistry", "retina", "moon", "coins", "cell")


def _load_texture(name: str) -> np.ndarray:
    import skimage.data
    from skimage.color import rgb2gray

    image = getattr(skimage.data, name)()
    if image.ndim == 3:
        image = rgb2gray(image[..., :3]) * 255.0
    image = np.asarray(image, dtype=np.float32)
    # stretch contrast to a common range so every surface has trackable corners
    lo, hi = np.percentile(image, [1, 99])
    return np.clip((image - lo) / max(hi - lo, 1.0), 0, 1).astype(np.float32) * 200.0 + 20.0


#: Mip levels of every texture pyramid, per axis (level 0 included).
_MIP_LEVELS = 7


def _halve(image: np.ndarray, axis: int) -> np.ndarray:
    """The texture filtered along ``axis`` by ``cv2.pyrDown``'s binomial [1 4 6 4 1] / 16 (wrapping
    around, as the texture tiles) and every other texel kept: texel j of the result sits at 2j."""
    n = image.shape[axis]
    pad = np.pad(image, [(2, 2) if a == axis else (0, 0) for a in range(2)], mode="wrap").astype(np.float32, copy=False)

    def shifted(k):
        return pad[k:k + n] if axis == 0 else pad[:, k:k + n]

    out = (shifted(0) + shifted(4) + np.float32(4) * (shifted(1) + shifted(3)) + np.float32(6) * shifted(2)) \
        * np.float32(1 / 16)
    return np.ascontiguousarray(out[::2] if axis == 0 else out[:, ::2])


def _ripmap(image: np.ndarray, levels: int = _MIP_LEVELS) -> list:
    """Mip levels of a texture, separately along its two axes: ``rip[ly][lx]`` is the texture
    (cropped to a multiple of 2^(levels-1) texels) halved ``ly`` times along its rows (s2, the
    image's first axis) and ``lx`` times along its columns (s1). Every level is exactly half the
    one below along its axis, keeps the even texels and wraps with the same period in metres, so
    all levels show the same pattern at the same place. Separate levels per axis let a surface
    seen at a slant keep the detail across the slant (a camera pixel integrates its own
    footprint, which a slanted surface stretches along one direction only)."""
    m = 2 ** (levels - 1)
    h, w = (image.shape[0] // m) * m, (image.shape[1] // m) * m
    if h == 0 or w == 0:
        raise ValueError(f"texture of {image.shape[0]} x {image.shape[1]} texels is smaller than {m} x {m}")
    row = [np.ascontiguousarray(image[:h, :w], dtype=np.float32)]
    for _ in range(levels - 1):
        row.append(_halve(row[-1], 1))
    rip = [row]
    for _ in range(levels - 1):
        rip.append([_halve(t, 0) for t in rip[-1]])
    return rip


def _sample_anisotropic(rip: list, s1: np.ndarray, s2: np.ndarray, lod1: np.ndarray, lod2: np.ndarray,
                        texel_m: float, offset: np.ndarray, cv2) -> np.ndarray:
    """Texture values at plane coordinates (s1, s2) (m, 1-D) with mip level ``lod1`` along s1 and
    ``lod2`` along s2 (>= 0): bilinear in each of the four levels around (lod1, lod2), blended
    bilinearly by their fractional parts, so the image changes continuously as a surface's
    distance and slant do."""
    top = len(rip) - 1
    lod1, lod2 = np.minimum(lod1, np.float32(top)), np.minimum(lod2, np.float32(top))
    b1, b2 = np.minimum(lod1.astype(np.int64), top - 1), np.minimum(lod2.astype(np.int64), top - 1)  # >= 0: floors
    f1, f2 = lod1 - b1.astype(np.float32), lod2 - b2.astype(np.float32)
    key = b2 * top + b1
    out = np.empty(s1.shape, np.float32)
    keys = np.unique(key)
    for k in keys:
        sel = slice(None) if keys.size == 1 else np.flatnonzero(key == k)  # one level pair: the common case
        l1, l2 = int(k % top), int(k // top)
        a1, a2, x, y = f1[sel], f2[sel], s1[sel], s2[sel]
        low = (1 - a1) * _sample_level(rip, l1, l2, x, y, texel_m, offset, cv2) \
            + a1 * _sample_level(rip, l1 + 1, l2, x, y, texel_m, offset, cv2)
        high = (1 - a1) * _sample_level(rip, l1, l2 + 1, x, y, texel_m, offset, cv2) \
            + a1 * _sample_level(rip, l1 + 1, l2 + 1, x, y, texel_m, offset, cv2)
        out[sel] = (1 - a2) * low + a2 * high
    return out


def _sample_level(rip: list, level1: int, level2: int, s1: np.ndarray, s2: np.ndarray, texel_m: float,
                  offset: np.ndarray, cv2) -> np.ndarray:
    """Bilinear texture values of level ``rip[level2][level1]`` at plane coordinates (s1, s2) (m, 1-D)."""
    tex = rip[level2][level1]
    th, tw = tex.shape
    f1, f2 = 2 ** level1, 2 ** level2
    off1, off2 = offset[0] / f1 % tw, offset[1] / f2 % th
    mx = (s1 * np.float32(1 / (texel_m * f1)) + np.float32(off1)) % np.float32(tw)
    my = (s2 * np.float32(1 / (texel_m * f2)) + np.float32(off2)) % np.float32(th)
    n = mx.size
    cols = 4096  # cv2.remap wants maps under 32767 per side
    pad = -n % cols
    if pad:
        mx, my = np.concatenate([mx, np.zeros(pad, np.float32)]), np.concatenate([my, np.zeros(pad, np.float32)])
    return cv2.remap(tex, mx.reshape(-1, cols), my.reshape(-1, cols), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_WRAP).ravel()[:n]


def camera_poses(world_T_imu: np.ndarray, cam_T_imu: np.ndarray) -> np.ndarray:
    """(T, 4, 4) world_T_cam of the left camera."""
    return np.asarray(world_T_imu) @ se3_inverse(np.asarray(cam_T_imu))


def _path_samples(world_T_imu: np.ndarray, segment_m: float, lookahead_m: float):
    """Positions, forward and left unit vectors (horizontal) every ``segment_m`` along the path."""
    p = world_T_imu[:, :3, 3]
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(steps)])
    fwd = world_T_imu[:, :3, 0].copy()
    fwd[:, 2] = 0
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    s_q = np.arange(-2 * segment_m, s[-1] + lookahead_m + segment_m, segment_m)
    pos = np.stack([np.interp(s_q, s, p[:, i]) for i in range(3)], axis=1)
    heading = np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0]))
    h = np.interp(s_q, s, heading)
    beyond = s_q > s[-1]
    behind = s_q < 0
    f_end = np.array([math.cos(heading[-1]), math.sin(heading[-1]), 0.0])
    f_start = np.array([math.cos(heading[0]), math.sin(heading[0]), 0.0])
    pos[beyond] = p[-1] + (s_q[beyond] - s[-1])[:, None] * f_end
    pos[behind] = p[0] + s_q[behind][:, None] * f_start
    f = np.stack([np.cos(h), np.sin(h), np.zeros_like(h)], axis=1)
    left = np.stack([-f[:, 1], f[:, 0], np.zeros_like(h)], axis=1)
    return pos, f, left


def build_scene(world_T_imu, ground_below_imu_m: float, seed: int, options: RenderOptions | None = None) -> Scene:
    """The textured planes along a drive's path (see the module docstring)."""
    o = options or RenderOptions()
    rng = np.random.default_rng([int(seed), 21])
    world_T_imu = np.asarray(world_T_imu, dtype=np.float64)
    pos, fwd, left = _path_samples(world_T_imu, o.segment_m, o.lookahead_m)
    up = np.array([0.0, 0.0, 1.0])
    road_names = [_ROAD_TEXTURES[i] for i in rng.permutation(len(_ROAD_TEXTURES))[:2]]
    facade_names = [_FACADE_TEXTURES[i] for i in rng.permutation(len(_FACADE_TEXTURES))[:6]]
    names = road_names + facade_names
    textures = [_ripmap(_load_texture(n)) for n in names]
    rows = []
    n = pos.shape[0] - 1
    ground = pos - ground_below_imu_m * up
    for i in range(n):
        a, b = ground[i], ground[i + 1]
        e1 = b - a
        length = np.linalg.norm(e1)
        e1 /= length
        lat = left[i]
        lat = lat - e1 * (lat @ e1)
        lat /= np.linalg.norm(lat)
        normal = np.cross(e1, lat)
        if normal[2] < 0:
            normal = -normal
        # overlap the next quad a little so no sliver of sky shows between two
        rows.append((a - o.road_half_width_m * lat, e1, lat, (length * 1.02, 2 * o.road_half_width_m), normal,
                     int(rng.integers(0, len(road_names))), o.road_texel_m, 0))
    # façades: blocks of 2-5 segments per side with their own offset, height and texture
    for side in (+1.0, -1.0):
        i = 0
        while i < n:
            block = int(rng.integers(2, 6))
            offset = rng.uniform(*o.facade_offset_m)
            height = rng.uniform(*o.facade_height_m)
            tex = len(road_names) + int(rng.integers(0, len(facade_names)))
            for k in range(i, min(i + block, n)):
                a = ground[k] + side * offset * left[k]
                b = ground[k + 1] + side * offset * left[k + 1]
                e1 = b - a
                length = np.linalg.norm(e1)
                if length < 1e-6:
                    continue
                e1 /= length
                e2 = up - e1 * (up @ e1)
                e2 /= np.linalg.norm(e2)
                normal = np.cross(e1, e2)
                if normal @ (-side * left[k]) < 0:  # face the road
                    normal = -normal
                rows.append((a, e1, e2, (length * 1.02, height), normal, tex, o.texel_m, 1))
            i += block
    origin, e1, e2, lengths, normal, tex, texel, kind = (np.array(c) for c in zip(*rows))
    q = origin.shape[0]
    return Scene(origin=origin, e1=e1, e2=e2, lengths=lengths.astype(float), normal=normal, texture=tex,
                 texel_m=texel.astype(float), offset=rng.uniform(0, 4096, (q, 2)), gain=rng.uniform(0.75, 1.15, q),
                 textures=textures, kind=kind)


def _ray_directions(K: np.ndarray, width: int, height: int) -> np.ndarray:
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)


def _quad_bbox(scene: Scene, i: int, cam_T_world: np.ndarray, K: np.ndarray, width: int, height: int):
    """Pixel bounding box (u0, u1, v0, v1) of quad i, or None when it is not in view."""
    o, e1, e2, (l1, l2) = scene.origin[i], scene.e1[i], scene.e2[i], scene.lengths[i]
    corners = np.array([o, o + l1 * e1, o + l1 * e1 + l2 * e2, o + l2 * e2])
    c = corners @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
    near = 0.05
    # clip the polygon against z >= near (Sutherland-Hodgman, one plane)
    poly = []
    for k in range(4):
        p, q = c[k], c[(k + 1) % 4]
        if p[2] >= near:
            poly.append(p)
        if (p[2] >= near) != (q[2] >= near):
            t = (near - p[2]) / (q[2] - p[2])
            poly.append(p + t * (q - p))
    if not poly:
        return None
    poly = np.array(poly)
    u = K[0, 0] * poly[:, 0] / poly[:, 2] + K[0, 2]
    v = K[1, 1] * poly[:, 1] / poly[:, 2] + K[1, 2]
    u0, u1 = max(0, int(math.floor(u.min()))), min(width, int(math.ceil(u.max())) + 1)
    v0, v1 = max(0, int(math.floor(v.min()))), min(height, int(math.ceil(v.max())) + 1)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, u1, v0, v1


def _render_view(scene: Scene, world_T_cam: np.ndarray, K: np.ndarray, o: RenderOptions, cv2) -> np.ndarray:
    """One view. A plane point X = O + s1 e1 + s2 e2 is seen at pixel p ~ K A [s1, s2, 1]
    with A = [R e1, R e2, R (O - C)] (R, C: cam_T_world's rotation, the camera centre), so
    (K A)⁻¹ [u, v, 1] = [s1, s2, 1] / z: texture coordinates and depth of every pixel
    from one 3x3 matrix per plane (the ray-plane intersection, written as a homography)."""
    h, w = o.height_px, o.width_px
    cam_T_world = se3_inverse(world_T_cam)
    R = cam_T_world[:3, :3]
    C = world_T_cam[:3, 3]
    image = np.full((h, w), o.sky_grey, np.float32)
    zbuf = np.full((h, w), np.inf, np.float32)
    dist = np.linalg.norm(scene.origin - C, axis=1)
    for i in np.flatnonzero(dist < o.max_distance_m + scene.lengths.max(axis=1)):
        box = _quad_bbox(scene, i, cam_T_world, K, w, h)
        if box is None:
            continue
        u0, u1, v0, v1 = box
        A = np.column_stack([R @ scene.e1[i], R @ scene.e2[i], R @ (scene.origin[i] - C)])
        try:
            Hinv = np.linalg.inv(K @ A)
        except np.linalg.LinAlgError:  # seen edge-on
            continue
        Hf = Hinv.astype(np.float32)  # float32: 1e-6 m at 30 m, a fraction of a texel
        u = np.arange(u0, u1, dtype=np.float32)[None, :]
        v = np.arange(v0, v1, dtype=np.float32)[:, None]
        w2 = Hf[2, 0] * u + (Hf[2, 1] * v + Hf[2, 2])  # 1 / depth
        ok = w2 > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.divide(1.0, w2, dtype=np.float32)
            s1 = (Hf[0, 0] * u + (Hf[0, 1] * v + Hf[0, 2])) * z
            s2 = (Hf[1, 0] * u + (Hf[1, 1] * v + Hf[1, 2])) * z
        l1, l2 = scene.lengths[i]
        ok &= (z > 0.05) & (z < zbuf[v0:v1, u0:u1]) & (s1 >= 0) & (s1 <= l1) & (s2 >= 0) & (s2 <= l2)
        if not ok.any():
            continue
        rip = scene.textures[scene.texture[i]]
        # mip level of every pixel along each texture axis from its footprint on the plane: the
        # Jacobian of (s1, s2) in the pixel (u, v), ds/du = z (H[:2, 0] - s H[2, 0]) and likewise in v;
        # the footprint's extent along s_i (in texels) is the norm of row i (the 1σ of a pixel's
        # box mapped onto the plane, times √12), so a slanted surface is filtered across its slant
        # only as much as a pixel integrates there
        vv, uu = np.nonzero(ok)
        zs, s1p, s2p = z[vv, uu], s1[vv, uu], s2[vv, uu]
        inv_texel = np.float32(1 / scene.texel_m[i])
        d1u, d1v = (Hf[0, 0] - s1p * Hf[2, 0]) * zs, (Hf[0, 1] - s1p * Hf[2, 1]) * zs
        d2u, d2v = (Hf[1, 0] - s2p * Hf[2, 0]) * zs, (Hf[1, 1] - s2p * Hf[2, 1]) * zs
        bias = np.float32(o.lod_bias)
        lod1 = np.maximum(np.log2(np.hypot(d1u, d1v) * inv_texel) + bias, np.float32(0))
        lod2 = np.maximum(np.log2(np.hypot(d2u, d2v) * inv_texel) + bias, np.float32(0))
        values = _sample_anisotropic(rip, s1p, s2p, lod1, lod2, scene.texel_m[i], scene.offset[i], cv2)
        image[v0 + vv, u0 + uu] = values * np.float32(scene.gain[i])
        zbuf[v0:v1, u0:u1][ok] = z[ok]
    return image


def render_pair(scene: Scene, world_T_cam: np.ndarray, K: np.ndarray, baseline_m: float,
                options: RenderOptions | None = None, rng: np.random.Generator | None = None):
    """(left, right) uint8 rectified grey images of the left camera at ``world_T_cam``."""
    import cv2

    o = options or RenderOptions()
    right_T = np.array(world_T_cam, dtype=np.float64)
    right_T[:3, 3] = world_T_cam[:3, 3] + world_T_cam[:3, 0] * baseline_m
    out = []
    for pose in (world_T_cam, right_T):
        img = _render_view(scene, pose, np.asarray(K, float), o, cv2)
        if o.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), o.blur_sigma_px)
        if o.noise_grey_levels > 0 and rng is not None:
            img = img + rng.normal(0.0, o.noise_grey_levels, img.shape).astype(np.float32)
        out.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return out[0], out[1]


def surface_point(scene: Scene, world_T_cam: np.ndarray, K: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(n, 3) world points where the rays of left-image ``pixels`` (n, 2) first meet the
    scene's planes (NaN where a ray meets none: the sky)."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    R, C = world_T_cam[:3, :3], world_T_cam[:3, 3]
    d_cam = np.stack([(pixels[:, 0] - K[0, 2]) / K[0, 0], (pixels[:, 1] - K[1, 2]) / K[1, 1],
                      np.ones(len(pixels))], axis=1)
    d = d_cam @ R.T  # (n, 3)
    best = np.full(len(pixels), np.inf)
    out = np.full((len(pixels), 3), np.nan)
    near = np.flatnonzero(np.linalg.norm(scene.origin - C, axis=1) < 250.0)
    for i in near:
        n = scene.normal[i]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((scene.origin[i] - C) @ n) / (d @ n)
        X = C + t[:, None] * d
        rel = X - scene.origin[i]
        s1, s2 = rel @ scene.e1[i], rel @ scene.e2[i]
        l1, l2 = scene.lengths[i]
        ok = (t > 0.05) & (t < best) & (s1 >= 0) & (s1 <= l1) & (s2 >= 0) & (s2 <= l2)
        best[ok] = t[ok]
        out[ok] = X[ok]
    return out


def track_reprojection_errors(observations, world_T_cam: np.ndarray, K: np.ndarray, baseline_m: float,
                              scene) -> np.ndarray:
    """(N,) error (px) of every tracked observation against the true geometry.

    Each track's point is where its first left pixel's ray meets the scene's planes
    (:func:`surface_point`, true pose); every observation of the track is graded by
    projecting that point with the true pose of its frame: the larger of the left- and
    right-image pixel distances. NaN for tracks whose first ray meets no plane.
    """
    from vislam.core.sequence import StereoObservations  # noqa: F401 - the type of `observations`

    ids, frames, px = observations.landmark_ids, observations.frame_index, observations.pixels
    order = np.lexsort((frames, ids))
    first = order[np.r_[True, ids[order][1:] != ids[order][:-1]]]  # first observation of each track
    X = np.full((observations.n_landmarks, 3), np.nan)
    for f in np.unique(frames[first]):
        rows = first[frames[first] == f]
        X[ids[rows]] = surface_point(scene, world_T_cam[f], K, px[rows, :2])
    cam_T_world = se3_inverse(world_T_cam)
    P = X[ids]
    q = np.einsum("nij,nj->ni", cam_T_world[frames, :3, :3], P) + cam_T_world[frames, :3, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        uL = K[0, 0] * q[:, 0] / q[:, 2] + K[0, 2]
        v = K[1, 1] * q[:, 1] / q[:, 2] + K[1, 2]
        uR = K[0, 0] * (q[:, 0] - baseline_m) / q[:, 2] + K[0, 2]
    left = np.hypot(uL - px[:, 0], v - px[:, 1])
    right = np.hypot(uR - px[:, 2], v - px[:, 3])
    return np.maximum(left, right)
