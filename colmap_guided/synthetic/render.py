"""Exact rendering of textured planar polygons for pinhole cameras.

Each polygon is mapped into the image by the homography it induces (``cv2.warpPerspective`` on a mip
level of its texture), hidden surfaces are removed with a z-buffer whose inverse depth is affine in
the pixel coordinates, and images are rendered at ``supersample`` times the resolution and reduced
with ``INTER_AREA`` for anti-aliasing. COLMAP's pixel convention holds throughout: pixel (col, row)
covers [col, col+1) x [row, row+1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

_NEAR = 0.05  # near clipping plane, metres
_SKY_TOP = np.array([0.36, 0.55, 0.85], np.float32)
_SKY_HORIZON = np.array([0.80, 0.85, 0.90], np.float32)
_HAZE_START, _HAZE_SCALE = 20.0, 70.0  # metres: haze 1 - exp(-(depth - start) / scale) beyond start


@dataclass
class Texture:
    """A mip pyramid of an RGB or RGBA float32 image, ``texels_per_m`` at level 0; ``wrap`` tiles
    it."""

    levels: list[np.ndarray]
    texels_per_m: float
    wrap: bool = False


@dataclass
class Polygon:
    """A planar convex polygon: points ``origin + a * u + b * v`` for (a, b) in ``vertices``
    (metres).

    ``u``, ``v`` are orthonormal; the face is seen from the side of ``v x u`` (from there ``u``
    points right and ``v`` down, so textures are not mirrored). The texture colour at
    (a, b) is its texel (a, b) * texels_per_m, times ``detail`` (a grey modulation) and ``shade``.
    """

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    vertices: np.ndarray
    texture: Texture
    shade: float = 1.0
    detail: Texture | None = None

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.v, self.u)


def make_texture(image: np.ndarray, texels_per_m: float, wrap: bool = False) -> Texture:
    """Build the mip pyramid; area averaging keeps texel centres aligned, odd sizes included."""
    levels = [np.ascontiguousarray(image, np.float32)]
    while min(levels[-1].shape[:2]) >= 16:
        h, w = levels[-1].shape[:2]
        levels.append(cv2.resize(levels[-1], (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    return Texture(levels, texels_per_m, wrap)


def _clip_near(points: np.ndarray, ab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Clip a polygon (camera coordinates, with its plane coordinates) to z >= _NEAR."""
    out_p, out_ab = [], []
    n = len(points)
    for i in range(n):
        p, q = points[i], points[(i + 1) % n]
        if p[2] >= _NEAR:
            out_p.append(p)
            out_ab.append(ab[i])
        if (p[2] >= _NEAR) != (q[2] >= _NEAR):
            s = (_NEAR - p[2]) / (q[2] - p[2])
            out_p.append(p + s * (q - p))
            out_ab.append(ab[i] + s * (ab[(i + 1) % n] - ab[i]))
    return np.array(out_p).reshape(-1, 3), np.array(out_ab).reshape(-1, 2)


def _signed_area(poly: np.ndarray) -> float:
    """Shoelace area of a 2D polygon, positive for counter-clockwise in x-right, y-up axes."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _inside(pix: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """Pixels of the box [x0, x1) x [y0, y1) whose centre lies inside the convex polygon ``pix``."""
    xs = np.arange(x0, x1, dtype=np.float32) + 0.5
    ys = np.arange(y0, y1, dtype=np.float32) + 0.5
    orientation = 1.0 if _signed_area(pix) > 0 else -1.0
    mask = np.ones((len(ys), len(xs)), bool)
    for p, q in zip(pix, np.roll(pix, -1, axis=0)):
        dx, dy = (q - p) * orientation
        mask &= (dx * (ys - p[1]))[:, None] >= (dy * (xs - p[0]))[None, :]
    return mask


def _sample(
    tex: Texture, plane_h: np.ndarray, level_scale: float, size: tuple[int, int]
) -> np.ndarray:
    """Warp a texture level into a pixel box; plane_h maps box pixel indices to homogeneous
    (a, b)."""
    level = min(int(max(0.0, round(math.log2(max(level_scale, 1e-9))))), len(tex.levels) - 1)
    img = tex.levels[level]
    sx = tex.texels_per_m * img.shape[1] / tex.levels[0].shape[1]
    sy = tex.texels_per_m * img.shape[0] / tex.levels[0].shape[0]
    to_texel = np.array([[sx, 0, -0.5], [0, sy, -0.5], [0, 0, 1]])
    border = cv2.BORDER_WRAP if tex.wrap else cv2.BORDER_REPLICATE
    return cv2.warpPerspective(
        img,
        to_texel @ plane_h,
        size,
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=border,
    )


def render_view(
    polygons: list[Polygon], K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Render RGB float32 colour (sky left at 0) and inverse depth (0 = nothing hit) at width x
    height.

    ``K`` is for this resolution, in COLMAP's convention; R, t map world to camera.
    """
    color = np.zeros((height, width, 3), np.float32)
    inv_depth = np.zeros((height, width), np.float32)
    K_inv = np.linalg.inv(K)
    center = -R.T @ t
    for poly in polygons:
        n = poly.normal
        if n @ (center - poly.origin) <= 1e-9:  # back face
            continue
        world = poly.origin + poly.vertices[:, :1] * poly.u + poly.vertices[:, 1:] * poly.v
        cam, ab = _clip_near(world @ R.T + t, poly.vertices)
        if len(cam) < 3:
            continue
        pix = cam @ K.T
        pix = pix[:, :2] / pix[:, 2:]
        x0, y0 = np.floor(pix.min(0)).astype(int)
        x1, y1 = np.ceil(pix.max(0)).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
        if x0 >= x1 or y0 >= y1:
            continue
        box = (x1 - x0, y1 - y0)
        # Pixel centre of box index (i, j) is (x0 + i + 0.5, y0 + j + 0.5).
        box_to_pix = np.array([[1, 0, x0 + 0.5], [0, 1, y0 + 0.5], [0, 0, 1.0]])
        n_cam, o_cam = R @ n, R @ poly.origin + t
        g = K_inv.T @ n_cam / (n_cam @ o_cam)  # inverse depth = g . (x, y, 1)
        offset = center - poly.origin
        plane_h = (
            np.stack(
                [
                    K_inv.T @ (R @ poly.u) + (poly.u @ offset) * g,
                    K_inv.T @ (R @ poly.v) + (poly.v @ offset) * g,
                    g,
                ]
            )
            @ box_to_pix
        )
        mask = _inside(pix, x0, y0, x1, y1)
        # Texels per pixel over the visible part picks the mip level.
        texel_area = abs(_signed_area(ab)) * poly.texture.texels_per_m**2
        level_scale = math.sqrt(texel_area / max(abs(_signed_area(pix)), 1e-9))
        rgb = _sample(poly.texture, plane_h, level_scale, box)
        if rgb.shape[2] == 4:
            mask &= rgb[:, :, 3] > 0.5
            rgb = rgb[:, :, :3]
        if poly.detail is not None:
            scale = level_scale * poly.detail.texels_per_m / poly.texture.texels_per_m
            rgb = rgb * _sample(poly.detail, plane_h, scale, box)[:, :, None]
        gx = (np.arange(x0, x1, dtype=np.float32) + 0.5) * g[0]
        gy = (np.arange(y0, y1, dtype=np.float32) + 0.5) * g[1] + g[2]
        inv = gy[:, None] + gx[None, :]
        zbox = inv_depth[y0:y1, x0:x1]
        win = mask & (inv > zbox)
        zbox[win] = inv[win]
        color[y0:y1, x0:x1][win] = rgb[win] * poly.shade
    return color, inv_depth


def render_image(
    polygons: list[Polygon],
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    width: int,
    height: int,
    conf: dict,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """A photo (uint8 RGB) and its depth map (float32, 0 = unknown) for the camera K
    (width x height).

    Renders at ``conf["supersample"]`` times the size, adds sky and haze, area-downscales, adds
    noise.
    """
    s = conf["supersample"]
    K = np.diag([s, s, 1.0]) @ K
    color, inv_depth = render_view(polygons, K, R, t, width * s, height * s)
    rows, cols = np.nonzero(inv_depth <= 0)
    pix = np.stack([cols + 0.5, rows + 0.5, np.ones(len(cols))], 1).astype(np.float32)
    rays = pix @ (R.T @ np.linalg.inv(K)).T.astype(np.float32)  # world directions
    elevation = np.clip(rays[:, 2] / np.linalg.norm(rays, axis=1), 0, 1)[:, None] ** 0.6
    color[rows, cols] = _SKY_HORIZON + (_SKY_TOP - _SKY_HORIZON) * elevation
    rows, cols = np.nonzero((inv_depth > 0) & (inv_depth < 1 / _HAZE_START))
    haze = 1 - np.exp((_HAZE_START - 1 / inv_depth[rows, cols]) / _HAZE_SCALE)
    color[rows, cols] += (_SKY_HORIZON - color[rows, cols]) * haze[:, None]
    color = cv2.resize(color, (width, height), interpolation=cv2.INTER_AREA)
    color = color * 255 + rng.standard_normal(color.shape, np.float32) * conf["noise_sigma"]
    # Depth is kept where the s x s block is one surface (no occlusion edge, no sky); inverse depth
    # is affine in the pixel coordinates on a plane, so its block mean is exact at the pixel centre.
    subs = [inv_depth[i::s, j::s] for i in range(s) for j in range(s)]
    lo, hi = np.minimum.reduce(subs), np.maximum.reduce(subs)
    valid = (lo > 0) & (hi < lo * 1.01)
    out_depth = np.zeros((height, width), np.float32)
    out_depth[valid] = len(subs) / sum(subs)[valid]
    return np.clip(color + 0.5, 0, 255).astype(np.uint8), out_depth
