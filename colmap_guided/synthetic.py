"""A small rendered multi-view scene with exact ground truth, for the demo and the pipeline tests.

A textured "landmark" (a gabled hall, a tower with a pyramid roof, a low annex and a few stone blocks)
stands on a paved plaza in a grass field, with a distant tree line and a sky gradient. Every surface is a
planar polygon with a procedural texture drawn from the seed: stone blocks, bricks or plaster, windows,
doors, posters and stains, roof tiles, pebbles. With ``repeated=True`` all facades show one identical
window, tiled on an exact grid over plain plaster: repeated structure that fools descriptor matching.

Rendering is exact for the ground-truth pinhole cameras: each polygon is mapped into the image by the
homography it induces (``cv2.warpPerspective`` on a mip level of its texture), hidden surfaces are removed
with a z-buffer whose inverse depth is affine in the pixel coordinates, and images are rendered at
``supersample`` times the resolution and reduced with ``INTER_AREA`` for anti-aliasing. COLMAP's pixel
convention holds throughout: pixel (col, row) covers [col, col+1) x [row, row+1).

Output of :func:`render_scene`::

    OUT/images/view_000.jpg ...   JPEG photos (EXIF: one camera make/model, focal length in 35 mm)
    OUT/ground_truth/             COLMAP text model: one PINHOLE camera, every image with cam_from_world
    OUT/depth/view_000.npy ...    float32 depth along the optical axis, 0 = sky or an occlusion edge
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from PIL import Image

from colmap_guided.log import logger

default_conf = {
    "focal_factor": 1.1,  # focal length in pixels / image width
    "arc_step_deg": 14.0,  # azimuth step between consecutive cameras
    # Varied distance, height and aim keep the cameras off a pure orbit around one point: an orbit is a
    # critical motion for self-calibration, and COLMAP's focal lengths and rotations drift on it.
    "radius": (20.0, 28.0),  # camera distance from the hall's centre, metres
    "camera_height": (1.5, 7.0),  # metres above the ground
    "target_jitter": 2.0,  # metres of random offset of the look-at point
    "max_roll_deg": 3.0,
    "supersample": 2,
    "jpeg_quality": 92,
    "exif": True,  # write camera make/model and the focal length (35 mm equivalent) like a camera does
    "noise_sigma": 1.2,  # sensor noise, grey levels
    "texels_per_m": 100.0,  # texture resolution of the buildings
}

_NEAR = 0.05  # near clipping plane, metres
_SKY_TOP = np.array([0.36, 0.55, 0.85], np.float32)
_SKY_HORIZON = np.array([0.80, 0.85, 0.90], np.float32)
_HAZE_START, _HAZE_SCALE = 20.0, 70.0  # metres: haze 1 - exp(-(depth - start) / scale) beyond start


@dataclass
class SceneInfo:
    """Where a rendered scene lies and its ground truth (poses map world to camera: x_cam = R x + t)."""

    image_dir: Path
    gt_dir: Path
    depth_dir: Path
    names: list[str]
    K: np.ndarray
    width: int
    height: int
    cam_from_world: dict[str, tuple[np.ndarray, np.ndarray]]

    def depth(self, name: str) -> np.ndarray:
        """Depth map of one image (metres along the optical axis, 0 where unknown)."""
        return np.load(self.depth_dir / f"{Path(name).stem}.npy")


@dataclass
class Texture:
    """A mip pyramid of an RGB or RGBA float32 image, ``texels_per_m`` at level 0; ``wrap`` tiles it."""

    levels: list[np.ndarray]
    texels_per_m: float
    wrap: bool = False


@dataclass
class Polygon:
    """A planar convex polygon: points ``origin + a * u + b * v`` for (a, b) in ``vertices`` (metres).

    ``u``, ``v`` are orthonormal; the face is seen from the side of ``v x u`` (from there ``u`` points
    right and ``v`` down, so textures are not mirrored). The texture colour at
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


# ----------------------------------------------------------------------------------------------------
# Rendering


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


def _sample(tex: Texture, plane_h: np.ndarray, level_scale: float, size: tuple[int, int]) -> np.ndarray:
    """Warp a texture level into a pixel box; plane_h maps box pixel indices to homogeneous (a, b)."""
    level = min(int(max(0.0, round(math.log2(max(level_scale, 1e-9))))), len(tex.levels) - 1)
    img = tex.levels[level]
    sx = tex.texels_per_m * img.shape[1] / tex.levels[0].shape[1]
    sy = tex.texels_per_m * img.shape[0] / tex.levels[0].shape[0]
    to_texel = np.array([[sx, 0, -0.5], [0, sy, -0.5], [0, 0, 1]])
    border = cv2.BORDER_WRAP if tex.wrap else cv2.BORDER_REPLICATE
    return cv2.warpPerspective(
        img, to_texel @ plane_h, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=border
    )


def render_view(
    polygons: list[Polygon], K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Render RGB float32 colour (sky left at 0) and inverse depth (0 = nothing hit) at width x height.

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
        plane_h = np.stack(
            [K_inv.T @ (R @ poly.u) + (poly.u @ offset) * g, K_inv.T @ (R @ poly.v) + (poly.v @ offset) * g, g]
        ) @ box_to_pix
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
    polygons: list[Polygon], K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int,
    conf: dict, rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """A photo (uint8 RGB) and its depth map (float32, 0 = unknown) for the camera K (width x height).

    Renders at ``conf["supersample"]`` times the size, adds sky and haze, area-downscales, adds noise.
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
    # Depth is kept where the s x s block is one surface (no occlusion edge, no sky); inverse depth is
    # affine in the pixel coordinates on a plane, so its block mean is exact at the pixel centre.
    subs = [inv_depth[i::s, j::s] for i in range(s) for j in range(s)]
    lo, hi = np.minimum.reduce(subs), np.maximum.reduce(subs)
    valid = (lo > 0) & (hi < lo * 1.01)
    out_depth = np.zeros((height, width), np.float32)
    out_depth[valid] = len(subs) / sum(subs)[valid]
    return np.clip(color + 0.5, 0, 255).astype(np.uint8), out_depth


# ----------------------------------------------------------------------------------------------------
# Procedural textures (float32 RGB in [0, 1], rows go down the surface)


def _noise(rng: np.random.Generator, h: int, w: int, cell: int, periodic: bool = False) -> np.ndarray:
    """Smooth value noise with features of about ``cell`` texels, roughly unit variance."""
    gh, gw = -(-h // cell) + 1, -(-w // cell) + 1
    if periodic:  # h and w are multiples of cell: the grid wraps around
        grid = rng.standard_normal((h // cell, w // cell)).astype(np.float32)
        grid = np.pad(grid, 2, mode="wrap")
        big = cv2.resize(grid, (grid.shape[1] * cell, grid.shape[0] * cell), interpolation=cv2.INTER_CUBIC)
        return big[2 * cell : 2 * cell + h, 2 * cell : 2 * cell + w]
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    return cv2.resize(grid, (gw * cell, gh * cell), interpolation=cv2.INTER_CUBIC)[:h, :w]


def _fractal(
    rng: np.random.Generator, h: int, w: int, cells: tuple[int, ...], periodic: bool = False
) -> np.ndarray:
    """Sum of noise octaves, amplitude proportional to feature size, normalised to unit peak scale."""
    total = sum(c * _noise(rng, h, w, c, periodic) for c in cells)
    return total / sum(cells)


def _jitter(rng: np.random.Generator, color, amount: float) -> tuple[float, float, float]:
    """A random variant of a colour: brightness changes by up to ``amount``, hue by a third of it."""
    r = rng.uniform(-amount, amount, 4).tolist()
    gain = 1 + r[0] / max(sum(color) / 3, 0.1)
    return tuple(min(max(c * gain + d / 3, 0.0), 1.0) for c, d in zip(color, r[1:]))


def _plaster(rng: np.random.Generator, h: int, w: int, ppm: float, color, stains: float) -> np.ndarray:
    """Render with faint multi-scale noise, and dirt patches and spots in proportion to ``stains``."""
    img = np.empty((h, w, 3), np.float32)
    img[:] = color
    shade = 1 + 0.05 * _fractal(rng, h, w, (int(ppm * 2), int(ppm / 4), 3))
    if stains:
        dirt = np.clip(_noise(rng, h, w, int(ppm * 1.5)) - 0.6, 0, None) * stains
        shade -= dirt + 0.15 * np.clip(_noise(rng, h, w, int(ppm * 0.3)) - 1.2, 0, None) * stains
    return img * shade[:, :, None]


def _masonry(
    rng: np.random.Generator, h: int, w: int, ppm: float, unit: tuple[float, float], color
) -> np.ndarray:
    """Ashlar or brick courses: per-block colour, mortar joints, offset rows."""
    img = np.empty((h, w, 3), np.float32)
    img[:] = np.array(color) * 0.75  # mortar
    bw, bh, joint = unit[0] * ppm, unit[1] * ppm, max(1, round(0.012 * ppm))
    for row, y in enumerate(np.arange(0, h, bh)):
        x = -rng.uniform(0, bw) if row % 2 else -bw / 2
        while x < w:
            width = bw * rng.uniform(0.7, 1.3)
            c = _jitter(rng, color, 0.08)
            p0 = (int(round(x)) + joint, int(round(y)) + joint)
            p1 = (int(round(x + width)) - joint, int(round(y + bh)) - joint)
            cv2.rectangle(img, p0, p1, c, -1)
            x += width
    return img * (1 + 0.08 * _fractal(rng, h, w, (int(ppm / 3), 4)))[:, :, None]


def _window_params(rng: np.random.Generator) -> dict:
    """The look of one window: frame and glass colours, mullions, shutters, curtain."""
    frames = [(0.92, 0.92, 0.88), (0.25, 0.2, 0.15), (0.35, 0.4, 0.35)]
    shutters = [(0.2, 0.4, 0.25), (0.5, 0.2, 0.15), (0.3, 0.35, 0.5)]
    return {
        "frame": _jitter(rng, frames[rng.integers(3)], 0.05),
        "glass": _jitter(rng, (0.15, 0.2, 0.25), 0.06),
        "mullions": int(rng.integers(3)),
        "shutter": _jitter(rng, shutters[rng.integers(3)], 0.08) if rng.random() < 0.45 else None,
        "curtain": rng.random() < 0.4,
    }


def _draw_window(
    img: np.ndarray, rng: np.random.Generator, x: int, y: int, w: int, h: int, ppm: float, p: dict
) -> None:
    """Frame, glass with reflections, mullions, optional curtain and shutters, sill and lintel."""
    f = max(2, int(0.07 * ppm))
    cv2.rectangle(img, (x - f, y - f), (x + w + f, y + h + f), p["frame"], -1)
    glass = np.empty((h, w, 3), np.float32)
    glass[:] = p["glass"]
    ramp = np.linspace(1.3, 0.7, h, dtype=np.float32)[:, None]
    glass *= (ramp + 0.5 * np.clip(_noise(rng, h, w, max(4, w // 3)), -0.4, 1))[:, :, None]
    if p["curtain"]:
        glass[: h // 3] = glass[: h // 3] * 0.3 + 0.6
    img[y : y + h, x : x + w] = np.clip(glass, 0, 1)
    m = max(1, f // 2)
    if p["mullions"] >= 1:
        cv2.rectangle(img, (x + w // 2 - m, y), (x + w // 2 + m, y + h), p["frame"], -1)
    if p["mullions"] == 2:
        cv2.rectangle(img, (x, y + h // 3 - m), (x + w, y + h // 3 + m), p["frame"], -1)
    cv2.rectangle(img, (x - 2 * f, y + h + f), (x + w + 2 * f, y + h + 2 * f), (0.8, 0.78, 0.72), -1)
    cv2.rectangle(img, (x - 2 * f, y - 3 * f), (x + w + 2 * f, y - f), (0.7, 0.66, 0.6), -1)
    if p["shutter"] is not None:
        for x_s in (x - f - w // 2, x + w + f):
            cv2.rectangle(img, (x_s, y - f), (x_s + w // 2, y + h + f), p["shutter"], -1)
            for y_s in range(y, y + h, max(3, int(0.06 * ppm))):
                slat = tuple(c * 0.6 for c in p["shutter"])
                cv2.line(img, (x_s + 1, y_s), (x_s + w // 2 - 1, y_s), slat, 1)


def _poster(img: np.ndarray, rng: np.random.Generator, x: int, y: int, w: int, h: int) -> None:
    """A sign or poster: a coloured panel with a disc and rows of text-like marks."""
    cv2.rectangle(img, (x, y), (x + w, y + h), _jitter(rng, (0.5, 0.5, 0.5), 0.45), -1)
    ink = _jitter(rng, (0.1, 0.1, 0.1), 0.1) if rng.random() < 0.7 else (0.95, 0.95, 0.9)
    cv2.circle(img, (x + w // 4, y + h // 4), max(2, min(w, h) // 6), _jitter(rng, (0.5, 0.5, 0.5), 0.5), -1)
    line_h = max(3, h // 10)
    for ly in range(y + h // 2, y + h - line_h, 2 * line_h):
        lx = x + w // 10
        while lx < x + w - w // 10:
            word = int(rng.integers(line_h, 4 * line_h))
            cv2.rectangle(img, (lx, ly), (min(lx + word, x + w - w // 10), ly + line_h), ink, -1)
            lx += word + line_h


def _facade(
    rng: np.random.Generator, width: float, height: float, eave: float, ppm: float, motif: np.ndarray | None
) -> np.ndarray:
    """A wall texture (width x height metres; rows below ``eave`` get windows).

    ``motif`` (repeated mode) is one window tile pasted on an exact grid over plain plaster; otherwise
    windows vary in place, size and kind, on stone, brick or plaster with posters and stains.
    """
    h, w = int(round(height * ppm)), int(round(width * ppm))
    if motif is not None:
        img = _plaster(rng, h, w, ppm, (0.82, 0.78, 0.70), stains=0.0)
        mh, mw = motif.shape[:2]
        period_x, period_y = int(2.0 * ppm), int(3.0 * ppm)
        for y in range(h - int(0.5 * ppm) - mh, h - int(eave * ppm) - 1, -period_y):
            for x in range((w % period_x) // 2 + (period_x - mw) // 2, w - mw, period_x):
                img[y : y + mh, x : x + mw] = motif
        return img
    base = _jitter(rng, [(0.75, 0.68, 0.55), (0.62, 0.36, 0.28), (0.85, 0.8, 0.68)][rng.integers(3)], 0.06)
    style = rng.integers(3)
    if style == 0:
        img = _masonry(rng, h, w, ppm, (0.6, 0.3), base)
    elif style == 1:
        img = _masonry(rng, h, w, ppm, (0.3, 0.1), (0.6, 0.32, 0.25))
    else:
        img = _plaster(rng, h, w, ppm, base, stains=0.25)
    eave_px = int(eave * ppm)
    cv2.rectangle(img, (0, h - int(0.5 * ppm)), (w, h), _jitter(rng, (0.45, 0.43, 0.4), 0.05), -1)  # plinth
    cv2.rectangle(img, (0, h - eave_px), (w, h - eave_px + int(0.25 * ppm)), (0.88, 0.86, 0.8), -1)  # cornice
    floors = max(1, int(eave // 3.1))
    columns = max(1, int(width // 2.6))
    spacing = width / columns
    for floor in range(floors):
        for col in range(columns):
            if rng.random() < 0.12:
                continue
            x_c = (col + 0.5 + rng.uniform(-0.1, 0.1)) * spacing
            ww, wh = rng.uniform(0.8, 1.3), rng.uniform(1.2, 1.8)
            bottom = floor * 3.1 + rng.uniform(0.8, 1.1)
            if floor == 0 and rng.random() < 0.2:  # a door
                bottom, wh = 0.0, 2.3
            top_px = h - int((bottom + wh) * ppm)
            if top_px < h - eave_px + int(0.4 * ppm):
                continue
            x_px, w_px, h_px = int((x_c - ww / 2) * ppm), int(ww * ppm), int(wh * ppm)
            _draw_window(img, rng, x_px, top_px, w_px, h_px, ppm, _window_params(rng))
    for _ in range(rng.integers(1, 4)):
        pw, ph = rng.uniform(0.5, 1.4), rng.uniform(0.6, 1.2)
        x, y = rng.uniform(0, width - pw), rng.uniform(0.6, 2.2)
        _poster(img, rng, int(x * ppm), h - int((y + ph) * ppm), int(pw * ppm), int(ph * ppm))
    if rng.random() < 0.6:  # graffiti
        pts = np.stack([rng.uniform(0, w, 8), h - rng.uniform(0.2, 1.6, 8) * ppm], 1).astype(np.int32)
        cv2.polylines(img, [pts], False, _jitter(rng, (0.5, 0.5, 0.5), 0.5), max(2, int(0.05 * ppm)))
    # Soft darkening towards the ground (ambient occlusion).
    img *= (1 - 0.25 * np.exp(-np.linspace(height, 0, h, dtype=np.float32) / 0.8))[:, None, None]
    return img


def _window_motif(rng: np.random.Generator, ppm: float) -> np.ndarray:
    """One window on plaster, the tile of the repeated facades."""
    params = _window_params(rng)
    params["shutter"] = (0.2, 0.38, 0.25)
    w, h = int(1.8 * ppm), int(2.0 * ppm)
    tile = _plaster(rng, h, w, ppm, (0.82, 0.78, 0.70), stains=0.0)
    ww, wh = int(0.8 * ppm), int(1.5 * ppm)
    _draw_window(tile, rng, (w - ww) // 2, (h - wh) // 2, ww, wh, ppm, params)
    return tile


def _roof(rng: np.random.Generator, width: float, height: float, ppm: float) -> np.ndarray:
    """Overlapping tile courses with per-tile colour and moss."""
    h, w = int(round(height * ppm)), int(round(width * ppm))
    color = [(0.62, 0.28, 0.2), (0.3, 0.32, 0.36), (0.5, 0.35, 0.28)][rng.integers(3)]
    img = np.empty((h, w, 3), np.float32)
    img[:] = np.array(color) * 0.5
    course, tile = 0.28 * ppm, 0.32 * ppm
    for row, y in enumerate(np.arange(0, h, course)):
        x = -tile / 2 * (row % 2) - rng.uniform(0, tile / 4)
        y0, y1 = int(y), int(y + course)
        while x < w:
            tw = tile * rng.uniform(0.85, 1.15)
            cv2.rectangle(img, (int(x) + 1, y0), (int(x + tw) - 1, y1 - 1), _jitter(rng, color, 0.06), -1)
            x += tw
        img[y0:y1] *= np.linspace(1.1, 0.75, len(img[y0:y1]), dtype=np.float32)[:, None, None]  # overlap shadow
    moss = np.clip(_noise(rng, h, w, int(ppm)), 0.5, 1.5) - 0.5
    return img * (1 - moss[:, :, None]) + moss[:, :, None] * np.array([0.35, 0.4, 0.2], np.float32)


def _ground(rng: np.random.Generator, size_m: float, plaza_radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Ground colour (grass, a paved plaza and path) and a tiling grey detail (pebbles, patches)."""
    n = 1024
    ppm = n / size_m
    yy, xx = (np.mgrid[0:n, 0:n].astype(np.float32) + 0.5) / ppm - size_m / 2
    radius = np.hypot(xx, yy)
    variation = _fractal(rng, n, n, (64, 16, 4))
    grass = np.array([0.33, 0.45, 0.2], np.float32) * (1 + 0.25 * variation[:, :, None])
    paving = np.array([0.68, 0.64, 0.58], np.float32) * (1 + 0.1 * variation[:, :, None])
    angle = rng.uniform(0, np.pi)
    path = np.abs(xx * np.sin(angle) - yy * np.cos(angle)) < 1.6
    plaza = (radius < plaza_radius + 1.5 * _noise(rng, n, n, 32)) | path
    macro = np.where(plaza[:, :, None], paving, grass)
    d = 2048  # detail: 24 m, wrapping
    dppm = d / 24.0
    detail = 1 + 0.3 * _fractal(rng, d, d, (128, 32, 8, 2), periodic=True)
    for _ in range(2500):  # pebbles, drawn again across the borders so that the tiling is seamless
        x, y = rng.uniform(0, d, 2)
        r = rng.uniform(0.02, 0.12) * dppm
        axes, angle, tone = (int(r), int(r * rng.uniform(0.5, 1))), rng.uniform(0, 180), rng.uniform(0.5, 1.5)
        for dx in (-d, 0, d):
            for dy in (-d, 0, d):
                if -r < x + dx < d + r and -r < y + dy < d + r:
                    cv2.ellipse(detail, (int(x + dx), int(y + dy)), axes, angle, 0, 360, tone, -1)
    return macro, np.clip(detail, 0.2, 2.0)


def _treeline(rng: np.random.Generator, width: float, height: float, ppm: float) -> np.ndarray:
    """RGBA: crowns of trees (discs of greens) with an irregular skyline, transparent above it."""
    h, w = int(height * ppm), int(width * ppm)
    img = np.zeros((h, w, 4), np.float32)
    x = 0.0
    while x < width:
        r = rng.uniform(1.5, 3.5)
        top = rng.uniform(0.0, 0.5) * height + r
        for _ in range(12):
            c = _jitter(rng, (0.2, 0.32, 0.15), 0.07)
            dx, dy = rng.normal(0, r / 2, 2)
            centre = (int((x + dx) * ppm), int((top + abs(dy)) * ppm))
            cv2.circle(img, centre, int(r * ppm * rng.uniform(0.4, 0.8)), (*c, 1.0), -1)
        canopy_base = ((int((x - r) * ppm), int(top * ppm)), (int((x + r) * ppm), h))
        cv2.rectangle(img, *canopy_base, (0.18, 0.28, 0.13, 1.0), -1)
        x += r * rng.uniform(0.8, 1.4)
    img[:, :, :3] *= (1 + 0.25 * _fractal(rng, h, w, (16, 4)))[:, :, None]
    return img


# ----------------------------------------------------------------------------------------------------
# Scene layout


_UP = np.array([0.0, 0.0, 1.0])


def _wall(p0, p1, height: float, tex: Texture, shade: float, gable: float | None = None) -> Polygon:
    """A vertical wall on the ground from p0 to p1 (x, y), facing right of p0 -> p1, so walls listed
    counter-clockwise seen from above face outwards; ``gable`` adds an apex at that height mid-wall."""
    p0, p1 = np.array([*p0, 0.0]), np.array([*p1, 0.0])
    length = float(np.linalg.norm(p1 - p0))
    top = gable if gable is not None else height
    verts = [(0, top - height), (length, top - height), (length, top), (0, top)]
    if gable is not None:
        verts.insert(1, (length / 2, 0.0))
    return Polygon(p0 + top * _UP, (p1 - p0) / length, -_UP, np.array(verts, float), tex, shade)


def _roof_face(eave0, eave1, high, tex: Texture, shade_of, triangle: bool) -> Polygon:
    """A roof face above the eave eave0 -> eave1 (counter-clockwise seen from above) rising to
    ``high``: the ridge end above eave1 (a rectangle) or the apex (a triangle)."""
    a, b, c = (np.array(p, float) for p in (eave0, eave1, high))
    length = float(np.linalg.norm(b - a))
    u = (b - a) / length
    up_slope = c - a - ((c - a) @ u) * u
    rise = float(np.linalg.norm(up_slope))
    v = -up_slope / rise  # texture rows run down the slope from the ridge
    if triangle:
        verts = [(float((c - a) @ u), 0.0), (length, rise), (0.0, rise)]
    else:
        verts = [(0.0, 0.0), (length, 0.0), (length, rise), (0.0, rise)]
    poly = Polygon(a + up_slope, u, v, np.array(verts, float), tex)
    poly.shade = shade_of(poly.normal)
    return poly


def _flat_top(x0: float, y0: float, x1: float, y1: float, z: float, tex: Texture, shade: float) -> Polygon:
    """A horizontal rectangle facing up."""
    verts = np.array([(0, 0), (x1 - x0, 0), (x1 - x0, y1 - y0), (0, y1 - y0)], float)
    return Polygon(np.array([x0, y1, z]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0]), verts, tex, shade)


def _box_walls(x0: float, y0: float, x1: float, y1: float, height: float, make_tex, shade_of) -> list[Polygon]:
    """The four walls of an axis-aligned box standing on the ground."""
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    walls = []
    for p0, p1 in zip(corners, corners[1:] + corners[:1]):
        length = math.dist(p0, p1)
        normal = np.array([p1[1] - p0[1], p0[0] - p1[0], 0.0]) / length
        walls.append(_wall(p0, p1, height, make_tex(length, height, height), shade_of(normal)))
    return walls


def build_scene(seed: int = 0, repeated: bool = False, texels_per_m: float = 100.0) -> list[Polygon]:
    """The polygons of the scene: hall, tower, annex, stone blocks, ground and tree line."""
    rng = np.random.default_rng(seed)
    ppm = texels_per_m
    sun_az = rng.uniform(0, 2 * np.pi)
    sun = np.array([np.cos(sun_az) * 0.75, np.sin(sun_az) * 0.75, 0.66])

    def shade_of(normal: np.ndarray) -> float:
        return float(0.55 + 0.5 * max(0.0, normal @ sun) + 0.1 * normal[2])

    motif = _window_motif(np.random.default_rng(rng.integers(2**32)), ppm) if repeated else None

    def facade(width: float, height: float, eave: float) -> Texture:
        return make_texture(_facade(rng, width, height, eave, ppm, motif), ppm)

    def roof(width: float, height: float) -> Texture:
        return make_texture(_roof(rng, width, height, ppm), ppm)

    stone = (0.7, 0.66, 0.6)

    def stone_block(width: float, height: float, _eave: float) -> Texture:
        return make_texture(_masonry(rng, int(height * ppm), int(width * ppm), ppm, (0.5, 0.3), stone), ppm)

    up_shade = shade_of(_UP)
    # Hall: 12 x 8 m, eaves at 6.5 m, ridge along x at 9.5 m, gables east and west.
    hx, hy, eave, ridge = 6.0, 4.0, 6.5, 9.5
    corners = [(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)]
    polys: list[Polygon] = []
    for i, gable in enumerate([None, ridge, None, ridge]):
        p0, p1 = corners[i], corners[(i + 1) % 4]
        length = math.dist(p0, p1)
        normal = np.array([p1[1] - p0[1], p0[0] - p1[0], 0.0]) / length
        polys.append(_wall(p0, p1, eave, facade(length, gable or eave, eave), shade_of(normal), gable))
    polys.append(_roof_face((-hx, -hy, eave), (hx, -hy, eave), (hx, 0, ridge), roof(12, 5), shade_of, False))
    polys.append(_roof_face((hx, hy, eave), (-hx, hy, eave), (-hx, 0, ridge), roof(12, 5), shade_of, False))
    # Tower through the west gable: 4 x 4 m, 11 m, pyramid roof up to 14 m.
    tx0, ty0, tx1, ty1, th = -9.0, -2.0, -5.0, 2.0, 11.0
    polys += _box_walls(tx0, ty0, tx1, ty1, th, facade, shade_of)
    apex = ((tx0 + tx1) / 2, (ty0 + ty1) / 2, th + 3.0)
    ring = [(tx0, ty0, th), (tx1, ty0, th), (tx1, ty1, th), (tx0, ty1, th)]
    for p0, p1 in zip(ring, ring[1:] + ring[:1]):
        polys.append(_roof_face(p0, p1, apex, roof(4, 3.7), shade_of, True))
    # Annex on the south side with a gravel roof, and a few stone blocks on the plaza.
    polys += _box_walls(1.5, -7.5, 6.5, -4.0, 3.5, facade, shade_of)
    gravel = make_texture(_plaster(rng, 400, 600, ppm, (0.5, 0.5, 0.48), stains=0.5), ppm)
    polys.append(_flat_top(1.5, -7.5, 6.5, -4.0, 3.5, gravel, up_shade))
    for _ in range(3):
        ang, dist = rng.uniform(0, 2 * np.pi), rng.uniform(10.5, 12.5)
        cx, cy, s, bh = dist * np.cos(ang), dist * np.sin(ang), rng.uniform(0.5, 0.8), rng.uniform(0.8, 1.8)
        polys += _box_walls(cx - s, cy - s, cx + s, cy + s, bh, stone_block, shade_of)
        top = make_texture(_plaster(rng, int(2 * s * ppm), int(2 * s * ppm), ppm, stone, stains=0.4), ppm)
        polys.append(_flat_top(cx - s, cy - s, cx + s, cy + s, bh, top, up_shade))
    # Ground: 120 m square in 10 m tiles (each picks its own mip level), a tree line at its edge.
    size, tile = 120.0, 10.0
    macro, detail = _ground(rng, size, plaza_radius=14.0)
    macro_tex, detail_tex = make_texture(macro, 1024 / size), make_texture(detail, 2048 / 24.0, wrap=True)
    for x in np.arange(-size / 2, size / 2, tile):
        for y in np.arange(-size / 2, size / 2, tile):
            ground = _flat_top(-size / 2, -size / 2, size / 2, size / 2, 0.0, macro_tex, up_shade)
            a, b = x + size / 2, size / 2 - y - tile
            ground.vertices = np.array([(a, b), (a + tile, b), (a + tile, b + tile), (a, b + tile)])
            ground.detail = detail_tex
            polys.append(ground)
    half = size / 2 - 2
    edge = [(-half, -half), (-half, half), (half, half), (half, -half)]  # clockwise: facing inwards
    for p0, p1 in zip(edge, edge[1:] + edge[:1]):
        polys.append(_wall(p0, p1, 12.0, make_texture(_treeline(rng, 2 * half, 12.0, 10.0), 10.0), 0.8))
    return polys


def _cameras(rng: np.random.Generator, num_images: int, conf: dict) -> list[tuple[np.ndarray, np.ndarray]]:
    """Poses on an arc around the hall, looking at it with jitter in distance, height, aim and roll."""
    start = rng.uniform(0, 2 * np.pi)
    poses = []
    for i in range(num_images):
        az = start + math.radians(conf["arc_step_deg"]) * (i + rng.uniform(-0.15, 0.15))
        r = rng.uniform(*conf["radius"])
        center = np.array([r * np.cos(az), r * np.sin(az), rng.uniform(*conf["camera_height"])])
        target = np.array([0.0, 0.0, 4.0]) + rng.uniform(-1, 1, 3) * conf["target_jitter"]
        z = (target - center) / np.linalg.norm(target - center)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        roll = math.radians(rng.uniform(-1, 1) * conf["max_roll_deg"])
        c, s = math.cos(roll), math.sin(roll)
        R = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) @ np.stack([x, y, z])
        poses.append((R, -R @ center))
    return poses


# ----------------------------------------------------------------------------------------------------
# Public API


def render_scene(
    out_dir: str | Path,
    num_images: int = 8,
    width: int = 640,
    height: int = 480,
    seed: int = 0,
    repeated: bool = False,
    conf: dict | None = None,
) -> SceneInfo:
    """Render the scene into ``out_dir`` (images/, ground_truth/, depth/) and return its SceneInfo."""
    if num_images < 2:
        raise ValueError(f"num_images must be at least 2, got {num_images}.")
    if width < 32 or height < 32:
        raise ValueError(f"Image size {width}x{height} is too small; use at least 32x32 pixels.")
    conf = {**default_conf, **(conf or {})}
    out_dir = Path(out_dir)
    image_dir, gt_dir, depth_dir = out_dir / "images", out_dir / "ground_truth", out_dir / "depth"
    for d in (image_dir, gt_dir, depth_dir):
        d.mkdir(parents=True, exist_ok=True)
    names = [f"view_{i:03d}.jpg" for i in range(num_images)]
    for stale in [*image_dir.glob("view_*.jpg"), *depth_dir.glob("view_*.npy")]:  # from an earlier, larger render
        if stale.stem not in {Path(n).stem for n in names}:
            stale.unlink()
    tic = time.perf_counter()
    polygons = build_scene(seed, repeated, conf["texels_per_m"])
    logger.debug("Built %d textured polygons in %.2f s.", len(polygons), time.perf_counter() - tic)
    f = conf["focal_factor"] * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    poses = _cameras(np.random.default_rng([seed, 1]), num_images, conf)
    tic = time.perf_counter()
    for i, (name, (R, t)) in enumerate(zip(names, poses)):
        noise_rng = np.random.default_rng([seed, 2, i])  # per image: a shorter render gives the same views
        image, depth = render_image(polygons, K, R, t, width, height, conf, noise_rng)
        _write_jpeg(image_dir / name, image, conf["jpeg_quality"], f if conf["exif"] else None)
        np.save(depth_dir / f"{Path(name).stem}.npy", depth)
    seconds = time.perf_counter() - tic
    logger.info("Rendered %d images of %dx%d in %.1f s into %s.", num_images, width, height, seconds, out_dir)
    _write_model(gt_dir, K, width, height, names, poses)
    return SceneInfo(image_dir, gt_dir, depth_dir, names, K, width, height, dict(zip(names, poses)))


def _write_jpeg(path: Path, image: np.ndarray, quality: int, focal: float | None) -> None:
    """Save RGB as JPEG; with ``focal`` (pixels) add the EXIF tags from which COLMAP reads a focal
    length prior (35 mm equivalent over the diagonal) and groups the images into one camera."""
    exif = Image.Exif()
    if focal is not None:
        exif[0x010F], exif[0x0110] = "colmap_guided", "synthetic"  # Make, Model
        diagonal_35mm = math.hypot(36.0, 24.0)
        exif.get_ifd(0x8769)[0xA405] = round(focal / math.hypot(*image.shape[:2]) * diagonal_35mm)
    Image.fromarray(image).save(path, quality=quality, exif=exif)


def _write_model(path: Path, K: np.ndarray, width: int, height: int, names: list[str], poses) -> None:
    """Write the ground truth as a COLMAP text model (cameras, rigs, frames, images; no points)."""
    rec = pycolmap.Reconstruction()
    params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    camera = pycolmap.Camera(model="PINHOLE", width=width, height=height, params=params, camera_id=1)
    rec.add_camera_with_trivial_rig(camera)
    for image_id, (name, (R, t)) in enumerate(zip(names, poses), start=1):
        image = pycolmap.Image(name=name, camera_id=1, image_id=image_id)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
    rec.write_text(str(path))


def transfer_points(info: SceneInfo, src: str, dst: str, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth correspondences: map pixels (N x 2, COLMAP convention) of ``src`` into ``dst``.

    Uses the depth of ``src`` (nearest pixel) and the poses; ``valid`` is False where the depth is
    unknown (sky, occlusion edges), a point lies outside either image or is hidden in ``dst`` (depth
    test, 2 %).
    """
    points = np.asarray(points, np.float64).reshape(-1, 2)
    depth_src, depth_dst = info.depth(src), info.depth(dst)
    z = _lookup(depth_src, points).astype(np.float64)
    rays = np.concatenate([points, np.ones((len(points), 1))], 1) @ np.linalg.inv(info.K).T
    (R_s, t_s), (R_d, t_d) = info.cam_from_world[src], info.cam_from_world[dst]
    world = (rays * z[:, None] - t_s) @ R_s
    cam = world @ R_d.T + t_d
    proj = cam @ info.K.T
    out = proj[:, :2] / np.where(np.abs(proj[:, 2:]) > 1e-12, proj[:, 2:], 1e-12)
    seen = _lookup(depth_dst, out)
    valid = (z > 0) & (cam[:, 2] > 0) & (seen > 0) & (np.abs(seen - cam[:, 2]) < 0.02 * cam[:, 2])
    return out, valid


def _lookup(depth: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Depth of the pixels containing the points, 0 for points outside the image."""
    h, w = depth.shape
    inside = (points[:, 0] >= 0) & (points[:, 0] < w) & (points[:, 1] >= 0) & (points[:, 1] < h)
    cols = np.clip(np.floor(points[:, 0]), 0, w - 1).astype(int)
    rows = np.clip(np.floor(points[:, 1]), 0, h - 1).astype(int)
    return np.where(inside, depth[rows, cols], 0)


def load_scene(out_dir: str | Path) -> SceneInfo:
    """The SceneInfo of a scene rendered earlier into ``out_dir``."""
    out_dir = Path(out_dir)
    rec = _load_gt(out_dir / "ground_truth")
    images = sorted(rec.images.values(), key=lambda im: im.name)
    camera = rec.cameras[images[0].camera_id]
    poses = {im.name: (im.cam_from_world().rotation.matrix(), im.cam_from_world().translation) for im in images}
    return SceneInfo(
        out_dir / "images", out_dir / "ground_truth", out_dir / "depth", [im.name for im in images],
        camera.calibration_matrix(), camera.width, camera.height, poses,
    )


def _load_gt(gt: SceneInfo | pycolmap.Reconstruction | str | Path) -> pycolmap.Reconstruction:
    if isinstance(gt, pycolmap.Reconstruction):
        return gt
    path = Path(gt.gt_dir if isinstance(gt, SceneInfo) else gt)
    if not path.is_dir():
        raise FileNotFoundError(f"No ground-truth model at {path}; render one with render_scene() first.")
    return pycolmap.Reconstruction(str(path))


def pose_errors(
    reconstruction: pycolmap.Reconstruction, gt: SceneInfo | pycolmap.Reconstruction | str | Path
) -> dict[str, tuple[float, float]]:
    """Per ground-truth image: (rotation error in degrees, camera-centre error / scene extent).

    The estimate is aligned to the ground truth by the similarity that pycolmap fits to the camera
    centres (LO-RANSAC, inlier threshold 5 % of the extent). The scene extent is the largest distance
    between two ground-truth camera centres. Images missing from ``reconstruction`` (or all images,
    when no alignment is found) get (inf, inf).
    """
    gt_rec = _load_gt(gt)
    centers = {im.name: im.projection_center() for im in gt_rec.images.values()}
    pts = np.array(list(centers.values()))
    extent = float(np.max(np.linalg.norm(pts[:, None] - pts[None], axis=2)))
    errors = {name: (math.inf, math.inf) for name in centers}
    sim = pycolmap.align_reconstructions_via_proj_centers(reconstruction, gt_rec, 0.05 * extent)
    if sim is None:
        logger.warning("Could not align the reconstruction to the ground truth.")
        return errors
    aligned = pycolmap.Reconstruction(reconstruction)
    aligned.transform(sim)
    gt_by_name = {im.name: im for im in gt_rec.images.values()}
    for image in aligned.images.values():
        if image.name not in gt_by_name or not image.has_pose:
            continue
        ref = gt_by_name[image.name]
        R_rel = image.cam_from_world().rotation.matrix() @ ref.cam_from_world().rotation.matrix().T
        axis = [R_rel[2, 1] - R_rel[1, 2], R_rel[0, 2] - R_rel[2, 0], R_rel[1, 0] - R_rel[0, 1]]
        angle = math.degrees(math.atan2(np.linalg.norm(axis) / 2, (np.trace(R_rel) - 1) / 2))
        center_err = float(np.linalg.norm(image.projection_center() - ref.projection_center()))
        errors[image.name] = (angle, center_err / extent)
    return errors


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Render the synthetic landmark scene with its ground truth.")
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--num_images", type=int, default=8)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeated", action="store_true", help="periodic window grid on every facade")
    args = parser.parse_args(argv)
    info = render_scene(args.out_dir, args.num_images, args.width, args.height, args.seed, args.repeated)
    print(f"{len(info.names)} images in {info.image_dir}, ground truth in {info.gt_dir}")


if __name__ == "__main__":
    main()
