"""Plain data types shared by the database io and the matchers (numpy only: importing it loads no torch).

Coordinates follow COLMAP: (0, 0) is the top-left corner of the top-left pixel, so the centre of
pixel (col, row) is (col + 0.5, row + 0.5). Keypoints are in the original image's pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class ImageData:
    """One image as a matcher sees it: its keypoints, descriptors and where its pixels are."""

    name: str  # COLMAP image name (path relative to the image folder, '/'-separated)
    image_id: int
    path: Path  # absolute path of the image file (read-only; never written)
    keypoints: np.ndarray  # (N, >=2) float32, x, y first (COLMAP convention), then scale/orientation/affine
    descriptors: np.ndarray  # (N, D) uint8 (SIFT) or float32
    width: int
    height: int
    camera: object = None  # pycolmap.Camera of the database, when there is one (COLMAP's guided matching needs it)
    extra: dict = field(default_factory=dict)  # per-matcher caches (e.g. backbone features, see Matcher.prepare)


# A pair to match: (image_id_a, image_id_b, name_a, name_b).
PairKey = tuple[int, int, str, str]
