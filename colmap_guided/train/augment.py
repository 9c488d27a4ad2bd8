"""What training sees besides the stored photos: synthetic homography views and archival looks.

* Synthetic pairs from single photos: B is a random homography warp (rotation, scale, perspective,
  crop) of A, so every point has an exact match. A homography does not determine a fundamental
  matrix; we use the plane-induced one, F = [e']_× H, with a random virtual epipole e' (as if the
  camera had also moved along a random direction while looking at a plane): every true
  correspondence satisfies x_B^T F x_A = x_B·(e' × H x_A) = 0, so the epipolar loss gets the same
  weak, line-only supervision as on real pairs, and the point loss gets the exact matches.
* Archival looks (``colmap_guided.archival``) and small, soft scans (``soft_scan``) of either image,
  seeded by the view's name (``variant_seed``) so that cached features stay reproducible.
"""

from __future__ import annotations

import zlib

import cv2
import numpy as np

from colmap_guided.geometry import apply_h
from colmap_guided.train.geometry import colmap_to_cv


def random_homography(
    width: int, height: int, out_w: int, out_h: int, rng: np.random.Generator, strength: float = 1.0
) -> np.ndarray:
    """Random H (COLMAP frames) from a (width, height) photo to an (out_w, out_h) view of it.

    A random crop (35–100 % of the area) of the photo is rotated (±30°·strength), its corners moved
    by up to 12 %·strength of its size (perspective), and fitted into the output frame.
    """
    frac = np.sqrt(rng.uniform(0.35, 1.0))
    cw, ch = width * frac, height * frac
    cx = rng.uniform(cw / 2, width - cw / 2)
    cy = rng.uniform(ch / 2, height - ch / 2)
    src = np.array(
        [
            [cx - cw / 2, cy - ch / 2],
            [cx + cw / 2, cy - ch / 2],
            [cx + cw / 2, cy + ch / 2],
            [cx - cw / 2, cy + ch / 2],
        ]
    )
    angle = np.deg2rad(rng.uniform(-30, 30) * strength)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    src = (src - [cx, cy]) @ rot.T + [cx, cy]
    src = src + rng.uniform(-0.12, 0.12, size=(4, 2)) * [cw, ch] * strength
    dst = np.array([[0, 0], [out_w, 0], [out_w, out_h], [0, out_h]], dtype=np.float64)
    H = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32)).astype(
        np.float64
    )
    return H  # photo pixels -> output pixels (corners of the crop -> corners of the output)


def warp_image(image: np.ndarray, H: np.ndarray, out_w: int, out_h: int) -> np.ndarray:
    """Warp with H given between COLMAP frames (pixel centres at +0.5); black outside the photo.

    When H shrinks the photo, it is first downscaled with area averaging (no aliasing) and H
    adapted.
    """
    h, w = image.shape[:2]
    centre = np.array([[w / 2, h / 2], [w / 2 + 1, h / 2], [w / 2, h / 2 + 1]])
    m = apply_h(H, centre)
    scale = np.sqrt(abs(np.cross(m[1] - m[0], m[2] - m[0])))  # local linear scale of H
    if scale < 0.8:
        small = cv2.resize(
            image,
            (max(1, round(w * scale)), max(1, round(h * scale))),
            interpolation=cv2.INTER_AREA,
        )
        S = np.diag([small.shape[1] / w, small.shape[0] / h, 1.0])
        image, H = small, H @ np.linalg.inv(S)
    return cv2.warpPerspective(
        image,
        colmap_to_cv(H),
        (out_w, out_h),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
    )


def random_epipole(width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """A virtual epipole for the plane-induced F: at infinity (sideways motion) or outside/inside
    the image (forward motion), so epipolar lines take varied directions."""
    angle = rng.uniform(0, 2 * np.pi)
    if rng.random() < 0.5:
        return np.array([np.cos(angle), np.sin(angle), 0.0])
    r = rng.uniform(0.0, 2.0) * max(width, height)
    return np.array([width / 2 + r * np.cos(angle), height / 2 + r * np.sin(angle), 1.0])


def soft_scan(
    image: np.ndarray, rng: np.random.Generator, long_side: tuple[int, int] = (128, 288)
) -> np.ndarray:
    """A small, soft scan (realistic scale gaps): the network input downscaled to a long side
    of ``long_side`` px (a small print or a low-resolution scan), blurred there (sigma 0.4-1.2 px:
    soft focus, print grain), and brought back to the input size as the pipeline upsamples small
    photos. Corner-aligned resizes keep the geometry of the view exact (a pure scale)."""
    h, w = image.shape[:2]
    s = rng.uniform(*long_side) / max(h, w)
    if s >= 1:
        return image
    small = cv2.resize(
        image, (max(8, round(w * s)), max(8, round(h * s))), interpolation=cv2.INTER_AREA
    )
    small = cv2.GaussianBlur(small, (0, 0), rng.uniform(0.4, 1.2))
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


def variant_seed(*keys) -> int:
    """Stable seed from names (Python's hash() is salted per process)."""
    return zlib.crc32("/".join(map(str, keys)).encode())
