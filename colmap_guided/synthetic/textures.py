"""Procedural textures of the synthetic scene (float32 RGB in [0, 1], rows go down the surface):
value noise, plaster, masonry, facades with windows, doors and posters, roof tiles, paving and
grass, a tree line."""

from __future__ import annotations

import cv2
import numpy as np


def _noise(
    rng: np.random.Generator, h: int, w: int, cell: int, periodic: bool = False
) -> np.ndarray:
    """Smooth value noise with features of about ``cell`` texels, roughly unit variance."""
    gh, gw = -(-h // cell) + 1, -(-w // cell) + 1
    if periodic:  # h and w are multiples of cell: the grid wraps around
        grid = rng.standard_normal((h // cell, w // cell)).astype(np.float32)
        grid = np.pad(grid, 2, mode="wrap")
        big = cv2.resize(
            grid, (grid.shape[1] * cell, grid.shape[0] * cell), interpolation=cv2.INTER_CUBIC
        )
        return big[2 * cell : 2 * cell + h, 2 * cell : 2 * cell + w]
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    return cv2.resize(grid, (gw * cell, gh * cell), interpolation=cv2.INTER_CUBIC)[:h, :w]


def _fractal(
    rng: np.random.Generator, h: int, w: int, cells: tuple[int, ...], periodic: bool = False
) -> np.ndarray:
    """Sum of noise octaves, amplitude proportional to feature size, normalised to unit peak
    scale."""
    total = sum(c * _noise(rng, h, w, c, periodic) for c in cells)
    return total / sum(cells)


def _jitter(rng: np.random.Generator, color, amount: float) -> tuple[float, float, float]:
    """A random variant of a colour: brightness changes by up to ``amount``, hue by a third
    of it."""
    r = rng.uniform(-amount, amount, 4).tolist()
    gain = 1 + r[0] / max(sum(color) / 3, 0.1)
    return tuple(min(max(c * gain + d / 3, 0.0), 1.0) for c, d in zip(color, r[1:]))


def plaster(
    rng: np.random.Generator, h: int, w: int, ppm: float, color, stains: float
) -> np.ndarray:
    """Render with faint multi-scale noise, and dirt patches and spots in proportion to
    ``stains``."""
    img = np.empty((h, w, 3), np.float32)
    img[:] = color
    shade = 1 + 0.05 * _fractal(rng, h, w, (int(ppm * 2), int(ppm / 4), 3))
    if stains:
        dirt = np.clip(_noise(rng, h, w, int(ppm * 1.5)) - 0.6, 0, None) * stains
        shade -= dirt + 0.15 * np.clip(_noise(rng, h, w, int(ppm * 0.3)) - 1.2, 0, None) * stains
    return img * shade[:, :, None]


def masonry(
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
    cv2.rectangle(
        img, (x - 2 * f, y + h + f), (x + w + 2 * f, y + h + 2 * f), (0.8, 0.78, 0.72), -1
    )
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
    cv2.circle(
        img,
        (x + w // 4, y + h // 4),
        max(2, min(w, h) // 6),
        _jitter(rng, (0.5, 0.5, 0.5), 0.5),
        -1,
    )
    line_h = max(3, h // 10)
    for ly in range(y + h // 2, y + h - line_h, 2 * line_h):
        lx = x + w // 10
        while lx < x + w - w // 10:
            word = int(rng.integers(line_h, 4 * line_h))
            cv2.rectangle(img, (lx, ly), (min(lx + word, x + w - w // 10), ly + line_h), ink, -1)
            lx += word + line_h


def facade(
    rng: np.random.Generator,
    width: float,
    height: float,
    eave: float,
    ppm: float,
    motif: np.ndarray | None,
) -> np.ndarray:
    """A wall texture (width x height metres; rows below ``eave`` get windows).

    ``motif`` (repeated mode) is one window tile pasted on an exact grid over plain plaster;
    otherwise windows vary in place, size and kind, on stone, brick or plaster with posters and
    stains.
    """
    h, w = int(round(height * ppm)), int(round(width * ppm))
    if motif is not None:
        img = plaster(rng, h, w, ppm, (0.82, 0.78, 0.70), stains=0.0)
        mh, mw = motif.shape[:2]
        period_x, period_y = int(2.0 * ppm), int(3.0 * ppm)
        for y in range(h - int(0.5 * ppm) - mh, h - int(eave * ppm) - 1, -period_y):
            for x in range((w % period_x) // 2 + (period_x - mw) // 2, w - mw, period_x):
                img[y : y + mh, x : x + mw] = motif
        return img
    base = _jitter(
        rng, [(0.75, 0.68, 0.55), (0.62, 0.36, 0.28), (0.85, 0.8, 0.68)][rng.integers(3)], 0.06
    )
    style = rng.integers(3)
    if style == 0:
        img = masonry(rng, h, w, ppm, (0.6, 0.3), base)
    elif style == 1:
        img = masonry(rng, h, w, ppm, (0.3, 0.1), (0.6, 0.32, 0.25))
    else:
        img = plaster(rng, h, w, ppm, base, stains=0.25)
    eave_px = int(eave * ppm)
    # plinth
    cv2.rectangle(img, (0, h - int(0.5 * ppm)), (w, h), _jitter(rng, (0.45, 0.43, 0.4), 0.05), -1)
    # cornice
    cv2.rectangle(img, (0, h - eave_px), (w, h - eave_px + int(0.25 * ppm)), (0.88, 0.86, 0.8), -1)
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
        pts = np.stack([rng.uniform(0, w, 8), h - rng.uniform(0.2, 1.6, 8) * ppm], 1).astype(
            np.int32
        )
        cv2.polylines(
            img, [pts], False, _jitter(rng, (0.5, 0.5, 0.5), 0.5), max(2, int(0.05 * ppm))
        )
    # Soft darkening towards the ground (ambient occlusion).
    img *= (1 - 0.25 * np.exp(-np.linspace(height, 0, h, dtype=np.float32) / 0.8))[:, None, None]
    return img


def window_motif(rng: np.random.Generator, ppm: float) -> np.ndarray:
    """One window on plaster, the tile of the repeated facades."""
    params = _window_params(rng)
    params["shutter"] = (0.2, 0.38, 0.25)
    w, h = int(1.8 * ppm), int(2.0 * ppm)
    tile = plaster(rng, h, w, ppm, (0.82, 0.78, 0.70), stains=0.0)
    ww, wh = int(0.8 * ppm), int(1.5 * ppm)
    _draw_window(tile, rng, (w - ww) // 2, (h - wh) // 2, ww, wh, ppm, params)
    return tile


def roof(rng: np.random.Generator, width: float, height: float, ppm: float) -> np.ndarray:
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
            cv2.rectangle(
                img, (int(x) + 1, y0), (int(x + tw) - 1, y1 - 1), _jitter(rng, color, 0.06), -1
            )
            x += tw
        # overlap shadow
        img[y0:y1] *= np.linspace(1.1, 0.75, len(img[y0:y1]), dtype=np.float32)[:, None, None]
    moss = np.clip(_noise(rng, h, w, int(ppm)), 0.5, 1.5) - 0.5
    return img * (1 - moss[:, :, None]) + moss[:, :, None] * np.array([0.35, 0.4, 0.2], np.float32)


def ground(
    rng: np.random.Generator, size_m: float, plaza_radius: float
) -> tuple[np.ndarray, np.ndarray]:
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
        axes, angle, tone = (
            (int(r), int(r * rng.uniform(0.5, 1))),
            rng.uniform(0, 180),
            rng.uniform(0.5, 1.5),
        )
        for dx in (-d, 0, d):
            for dy in (-d, 0, d):
                if -r < x + dx < d + r and -r < y + dy < d + r:
                    cv2.ellipse(detail, (int(x + dx), int(y + dy)), axes, angle, 0, 360, tone, -1)
    return macro, np.clip(detail, 0.2, 2.0)


def treeline(rng: np.random.Generator, width: float, height: float, ppm: float) -> np.ndarray:
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
