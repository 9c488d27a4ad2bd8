"""Archival-photo degradations: make modern photos look like scanned prints of the past.

The paper trains on MegaDepth (modern internet photos) and evaluates on LTLL (historical photos of
landmarks, §5). No historical multi-view collection is available offline, so training images are
degraded with effects typical of old prints and scans: grayscale, sepia toning, faded contrast,
blur, film grain, JPEG artefacts, vignetting, scratches and dust, a printer's halftone screen, and
an optional crop. The named looks range from realistic prints (``realistic_*``) to harshly damaged
ones (``damaged_scan``, ``old_postcard``) and printed postcards (``postcard_*``), which ``postcard``
mounts on a card with a border and a caption (``collage``: several pictures on one card).

Every effect takes and returns an RGB float32 image in [0, 1] and draws its randomness only from the
``numpy.random.Generator`` it is given, so a result is fully determined by (image, seed, strength).

API
    degrade(image, rng, strength=1.0, effects=None, crop=0.0, return_offset=False)
        random subset of effects (or the listed ones), random parameters scaled by ``strength``.
    apply_preset(image, name, seed=0)   named, reproducible looks: see ``PRESETS``.
    EFFECTS                             name -> function(img, rng, strength) for single effects.
    postcard(picture, rng), mount(...), collage(pictures, ...)   a print on a card.

Input: uint8 (H, W, 3) RGB or (H, W) gray. Output: uint8 (H', W', 3) RGB (H' = H unless cropped).
A crop keeps COLMAP's pixel convention: a point (x, y) of the input is (x - x0, y - y0) in the
output, with (x0, y0) the integer offset returned when ``return_offset=True``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from colmap_guided.images import read_image
from colmap_guided.log import logger
from colmap_guided.workspace import Workspace

_LUMA = np.array([0.299, 0.587, 0.114], np.float32)  # ITU-R BT.601, RGB order
# Classic sepia toning matrix (rows: output R, G, B; columns: input R, G, B).
_SEPIA = np.array([[0.393, 0.769, 0.189], [0.349, 0.686, 0.168], [0.272, 0.534, 0.131]], np.float32)


def _as_rng(rng) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


def _to_float(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise TypeError(f"expected a uint8 image, got {image.dtype}")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected (H, W) or (H, W, 3) image, got shape {image.shape}")
    return image.astype(np.float32) * (1.0 / 255.0)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    return np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _luma(img: np.ndarray) -> np.ndarray:
    return img @ _LUMA


# ----------------------------------------------------------------------------------------- effects
def grayscale(img: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """Black-and-white film: luminance replicated on the three channels (strength is unused)."""
    return np.repeat(_luma(img)[..., None], 3, axis=2)


def sepia(img: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """Sepia toning: the classic sepia matrix on the luminance, blended with random amount."""
    amount = float(np.clip(rng.uniform(0.6, 1.0) * strength, 0, 1))
    gray = np.repeat(_luma(img)[..., None], 3, axis=2)
    toned = gray @ _SEPIA.T
    # keep white below saturation: a brown-ish paper tone
    toned /= max(float(_SEPIA.sum(1).max()), 1.0)
    return (1 - amount) * img + amount * toned


def fade(img: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """Faded print: contrast reduced, blacks lifted to grey, whites dimmed, slight colour cast."""
    contrast = 1.0 - strength * rng.uniform(0.3, 0.6)
    black = strength * rng.uniform(0.05, 0.2)
    white = 1.0 - strength * rng.uniform(0.0, 0.15)
    cast = 1.0 + strength * rng.uniform(-0.06, 0.06, size=3).astype(np.float32)
    mean = float(img.mean())
    out = mean + (img - mean) * contrast
    out = black + (white - black) * np.clip(out, 0, 1)
    return out * cast


def blur(img: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """Out-of-focus lens or soft print: Gaussian blur, sigma relative to the image size."""
    size = max(img.shape[:2])
    sigma = max(0.5, strength * rng.uniform(0.6, 2.0) * size / 1000.0)
    return cv2.GaussianBlur(img, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)


def film_grain(img: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """Film grain: spatially correlated luminance noise, stronger in the mid-tones."""
    h, w = img.shape[:2]
    amp = strength * rng.uniform(0.03, 0.08)
    grain = max(1.0, max(h, w) / 1000.0 * rng.uniform(0.7, 1.5))  # grain size in pixels
    gh, gw = max(1, int(round(h / grain))), max(1, int(round(w / grain)))
    noise = rng.standard_normal((gh, gw), dtype=np.float32)
    if (gh, gw) != (h, w):
        noise = cv2.resize(noise, (w, h), interpolation=cv2.INTER_LINEAR)
        noise /= max(float(noise.std()), 1e-6)
    y = _luma(img)
    weight = 0.5 + 2.0 * y * (1.0 - y)  # mid-tones get most grain
    return img + (amp * noise * weight)[..., None]


def jpeg(img: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """JPEG artefacts of a low-quality scan: re-encode at a random low quality."""
    quality = int(np.clip(round(60 - strength * rng.uniform(25, 50)), 5, 95))
    bgr = _to_uint8(img)[..., ::-1]
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(bgr), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:  # pragma: no cover - OpenCV always encodes a valid uint8 image
        raise RuntimeError("JPEG encoding failed")
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) * (1.0 / 255.0)


def vignette(img: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """Lens vignetting: radial darkening towards the corners around a slightly shifted centre."""
    h, w = img.shape[:2]
    cx = w * (0.5 + rng.uniform(-0.1, 0.1))
    cy = h * (0.5 + rng.uniform(-0.1, 0.1))
    x = (np.arange(w, dtype=np.float32) + 0.5 - cx) / (0.5 * w)
    y = (np.arange(h, dtype=np.float32) + 0.5 - cy) / (0.5 * h)
    r2 = (y[:, None] ** 2 + x[None, :] ** 2) * 0.5  # 1 at the corners of a centred vignette
    amount = strength * rng.uniform(0.3, 0.7)
    falloff = 1.0 - amount * np.clip(r2, 0, 2) ** rng.uniform(1.0, 2.0)
    return img * np.clip(falloff, 0, 1)[..., None]


def scratches(img: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """Scratches (long thin near-vertical lines) and dust specks, bright or dark."""
    h, w = img.shape[:2]
    size = max(h, w)
    mask_bright = np.zeros((h, w), np.float32)
    mask_dark = np.zeros((h, w), np.float32)
    n_lines = int(rng.integers(2, 6) * max(strength, 0.2) + 0.5) + 1
    for _ in range(n_lines):
        x0 = rng.uniform(0, w)
        y0 = rng.uniform(-0.2 * h, 0.5 * h)
        length = rng.uniform(0.3, 1.0) * h
        angle = np.pi / 2 + rng.uniform(-0.15, 0.15)
        x1, y1 = x0 + length * np.cos(angle), y0 + length * np.sin(angle)
        thick = max(1, int(round(size / 1000.0 * rng.uniform(0.8, 2.0))))
        target = mask_bright if rng.random() < 0.6 else mask_dark
        cv2.line(
            target,
            (int(x0), int(y0)),
            (int(x1), int(y1)),
            float(rng.uniform(0.4, 0.9)),
            thick,
            cv2.LINE_AA,
        )
    _dust_specks(mask_bright, mask_dark, rng, strength)
    return _apply_masks(img, mask_bright, mask_dark)


def dust(img: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """Dust specks alone, bright or dark (a print kept well: no scratches)."""
    mask_bright = np.zeros(img.shape[:2], np.float32)
    mask_dark = np.zeros(img.shape[:2], np.float32)
    _dust_specks(mask_bright, mask_dark, rng, strength)
    return _apply_masks(img, mask_bright, mask_dark)


def _dust_specks(
    mask_bright: np.ndarray, mask_dark: np.ndarray, rng: np.random.Generator, strength: float
) -> None:
    h, w = mask_bright.shape
    size = max(h, w)
    n_dust = int(rng.integers(20, 60) * strength * (size / 1000.0) ** 2) + 5
    for _ in range(n_dust):
        c = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        radius = max(1, int(round(size / 1000.0 * rng.exponential(1.5))))
        target = mask_dark if rng.random() < 0.6 else mask_bright
        cv2.circle(target, c, radius, float(rng.uniform(0.5, 1.0)), -1, cv2.LINE_AA)


def _apply_masks(img: np.ndarray, mask_bright: np.ndarray, mask_dark: np.ndarray) -> np.ndarray:
    out = img + mask_bright[..., None] * (1.0 - img)
    return out * (1.0 - mask_dark[..., None])


def halftone(img: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """A printed card's screen: each ink a grid of dots whose size follows its tone (one screen
    for gray, one per channel at its own angle for colour), softened by the scanner."""
    h, w = img.shape[:2]
    period = max(2.5, max(h, w) / rng.uniform(180, 260))  # dot pitch in pixels
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    gray = float(np.abs(img - img.mean(axis=2, keepdims=True)).max()) < 1e-3
    angles = [45.0] if gray else [15.0, 75.0, 0.0]
    out = np.empty_like(img)
    for c in range(3):
        theta = np.deg2rad(angles[min(c, len(angles) - 1)] + rng.uniform(-5, 5))
        u = (x * np.cos(theta) + y * np.sin(theta)) * (2 * np.pi / period)
        v = (-x * np.sin(theta) + y * np.cos(theta)) * (2 * np.pi / period)
        screen = 0.5 + 0.25 * (np.cos(u) + np.cos(v))
        out[..., c] = (img[..., c] > screen).astype(np.float32)
        if gray:
            out[..., 1:] = out[..., :1]
            break
    out = cv2.GaussianBlur(out, (0, 0), 0.35 * period)
    amount = min(1.0, 0.7 * strength)
    return (1 - amount) * img + amount * out


EFFECTS: dict[str, Callable[[np.ndarray, np.random.Generator, float], np.ndarray]] = {
    "grayscale": grayscale,
    "sepia": sepia,
    "fade": fade,
    "blur": blur,
    "grain": film_grain,
    "jpeg": jpeg,
    "vignette": vignette,
    "scratches": scratches,
    "dust": dust,
    "halftone": halftone,
}
# Physical order of a degradation chain: toning of the print, ageing, optics, then the scan.
_ORDER = [
    "grayscale",
    "sepia",
    "fade",
    "vignette",
    "halftone",
    "blur",
    "grain",
    "scratches",
    "dust",
    "jpeg",
]
# Probability of each effect when ``degrade`` picks a random subset (colour: gray xor sepia xor
# none); dust has none: it is part of scratches there, so the training augmentation draws as before.
_PROB = {"fade": 0.6, "vignette": 0.5, "blur": 0.5, "grain": 0.6, "scratches": 0.3, "jpeg": 0.5}

PRESETS: dict[str, dict] = {
    "none": {"effects": []},
    "bw_print": {"effects": ["grayscale", "fade", "grain"], "strength": 0.8},
    "sepia_print": {"effects": ["sepia", "fade", "vignette", "grain"], "strength": 1.0},
    "faded_colour": {"effects": ["fade", "blur", "jpeg"], "strength": 1.0},
    "damaged_scan": {
        "effects": ["grayscale", "fade", "vignette", "blur", "grain", "scratches", "jpeg"],
        "strength": 1.0,
    },
    "old_postcard": {"effects": ["sepia", "blur", "grain", "scratches", "jpeg"], "strength": 1.2},
    # Realistic prints, kept well: moderate fading, soft focus, fine grain, dust.
    "realistic_bw": {"effects": ["grayscale", "fade", "blur", "grain", "dust"], "strength": 0.5},
    "realistic_sepia": {
        "effects": ["sepia", "fade", "vignette", "blur", "grain", "dust"],
        "strength": 0.5,
    },
    "realistic_colour": {"effects": ["fade", "blur", "grain", "dust"], "strength": 0.5},
    # Printed picture postcards (mounted on a card with ``postcard``): halftone-screened prints.
    "postcard_bw": {"effects": ["grayscale", "fade", "halftone", "dust", "jpeg"], "strength": 0.7},
    "postcard_sepia": {"effects": ["sepia", "fade", "halftone", "blur", "dust"], "strength": 0.7},
    "postcard_colour": {"effects": ["fade", "halftone", "blur", "jpeg"], "strength": 0.7},
}

# Card stock (RGB): white, cream, ivory; printed ink; captions as publishers printed them.
PAPERS = ((236, 240, 244), (238, 230, 208), (242, 236, 220))
INK = (40, 30, 30)
CAPTIONS = (
    ("Gruss aus der Altstadt - Rathaus und Markt", "Verlag 1931"),
    ("Partie am Schloss",),
    ("Blick auf die Kirche", "Kunstverlag - Nachdruck verboten"),
    ("Souvenir - Vue generale",),
)


def mount(
    picture: np.ndarray, paper=PAPERS[0], border: int = 40, caption=(), band: int = 70
) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """The picture on a card: a paper border around it and, under it, a band of printed caption
    lines; returns the card and the picture's box (x0, y0, x1, y1) on it."""
    h, w = picture.shape[:2]
    card = np.empty((h + 2 * border + (band if caption else 0), w + 2 * border, 3), np.uint8)
    card[:] = paper
    card[border : border + h, border : border + w] = picture
    for line, text in enumerate(caption):
        y = border + h + 28 + 30 * line
        cv2.putText(card, text, (border + 10, y), cv2.FONT_HERSHEY_SIMPLEX, 0.8, INK, 2)
    return card, (border, border, border + w, border + h)


def collage(
    pictures: list[np.ndarray], paper=PAPERS[0], border: int = 40, gutter: int = 24
) -> tuple[np.ndarray, list[tuple[int, int, int, int]]]:
    """Several pictures side by side on one card, a gutter of paper between them; returns the card
    and each picture's box, left to right."""
    h = max(p.shape[0] for p in pictures)
    w = sum(p.shape[1] for p in pictures) + gutter * (len(pictures) - 1)
    card = np.empty((h + 2 * border, w + 2 * border, 3), np.uint8)
    card[:] = paper
    x, boxes = border, []
    for p in pictures:
        card[border : border + p.shape[0], x : x + p.shape[1]] = p
        boxes.append((x, border, x + p.shape[1], border + p.shape[0]))
        x += p.shape[1] + gutter
    return card, boxes


def postcard(
    picture: np.ndarray, rng: np.random.Generator | int | None = None
) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """A picture mounted as a publisher would: card stock, border and caption drawn from ``rng``;
    returns the card and the picture's box on it."""
    rng = _as_rng(rng)
    paper = PAPERS[int(rng.integers(len(PAPERS)))]
    border = int(round(max(picture.shape[:2]) * rng.uniform(0.03, 0.07)))
    caption = CAPTIONS[int(rng.integers(len(CAPTIONS)))]
    return mount(picture, paper, border, caption)


def random_crop(
    image: np.ndarray, rng: np.random.Generator, min_fraction: float
) -> tuple[np.ndarray, tuple[int, int]]:
    """Crop keeping at least ``min_fraction`` of each side; returns the crop and its offset
    (x0, y0)."""
    h, w = image.shape[:2]
    cw = int(round(w * rng.uniform(min_fraction, 1.0)))
    ch = int(round(h * rng.uniform(min_fraction, 1.0)))
    cw, ch = max(1, min(w, cw)), max(1, min(h, ch))
    x0 = int(rng.integers(0, w - cw + 1))
    y0 = int(rng.integers(0, h - ch + 1))
    return image[y0 : y0 + ch, x0 : x0 + cw], (x0, y0)


def degrade(
    image: np.ndarray,
    rng: np.random.Generator | int | None = None,
    strength: float = 1.0,
    effects: list[str] | None = None,
    crop: float = 0.0,
    return_offset: bool = False,
):
    """Degrade an image like an archival photo.

    Args:
        image: uint8 (H, W, 3) RGB or (H, W) gray.
        rng: numpy Generator or seed; the only source of randomness.
        strength: 0 = no change, 1 = typical, up to ~2 = heavy.
        effects: names from ``EFFECTS`` applied in physical order; None draws a random subset
            (one of gray/sepia/colour, then each other effect with its own probability).
        crop: if > 0, random crop keeping at least (1 - crop) of each side before the effects.
        return_offset: also return the crop's offset (x0, y0) ((0, 0) without crop).
    """
    rng = _as_rng(rng)
    img = _to_float(image)
    offset = (0, 0)
    if crop > 0:
        img, offset = random_crop(img, rng, 1.0 - crop)
    if effects is None:
        colour = rng.random()
        chosen = {"grayscale"} if colour < 0.35 else {"sepia"} if colour < 0.6 else set()
        chosen |= {name for name in _ORDER if name in _PROB and rng.random() < _PROB[name]}
    else:
        unknown = set(effects) - set(EFFECTS)
        if unknown:
            raise ValueError(f"unknown effect(s) {sorted(unknown)}; known: {sorted(EFFECTS)}")
        chosen = set(effects)
    if strength > 0:
        for name in _ORDER:
            if name in chosen:
                img = np.clip(EFFECTS[name](img, rng, strength), 0.0, 1.0)
    out = _to_uint8(img)
    return (out, offset) if return_offset else out


def apply_preset(image: np.ndarray, name: str, seed: int = 0) -> np.ndarray:
    """Apply a named look from ``PRESETS`` (deterministic for a given seed)."""
    if name not in PRESETS:
        raise ValueError(f"unknown archival preset {name!r}; known: {sorted(PRESETS)}")
    preset = PRESETS[name]
    return degrade(
        image,
        np.random.default_rng(seed),
        strength=preset.get("strength", 1.0),
        effects=preset["effects"],
    )


def main(argv=None):
    """Write degraded copies of images (for a visual check or a simulated archival set)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("images", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--preset", default=None, help=f"one of {sorted(PRESETS)}; default: random effects"
    )
    parser.add_argument("--strength", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="remove the copies an earlier run wrote in --out first",
    )
    args = parser.parse_args(argv)
    sources = {path.resolve().parent for path in args.images}
    try:
        out = Workspace.claim(
            args.out, "archival", keep=tuple(sources), overwrite=args.overwrite, flag="--out"
        )
    except ValueError as err:
        logger.error("%s", err)
        return 2
    names = [path.name for path in args.images]
    written = 0
    for i, path in enumerate(args.images):
        target = out.path / path.name
        if names.count(path.name) > 1 or (target.exists() and not out.owns(path.name)):
            logger.warning(
                "%s: another file of that name is, or would be, in %s. Skipped.", path, out.path
            )
            continue
        try:
            rgb = read_image(path)
        except ValueError as err:
            logger.warning("%s Skipped.", err)
            continue
        if args.preset:
            image = apply_preset(rgb, args.preset, seed=args.seed + i)
        else:
            image = degrade(rgb, np.random.default_rng(args.seed + i), strength=args.strength)
        out.record(path.name)
        if not cv2.imwrite(str(target), np.ascontiguousarray(image[..., ::-1])):
            logger.warning("Could not write %s (check the extension). Skipped.", target)
            continue
        written += 1
    logger.info("Wrote %d of %d degraded images to %s.", written, len(args.images), out.path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
