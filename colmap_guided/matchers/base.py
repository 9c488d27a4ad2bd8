"""The matcher interface every matcher implements (raw, guided, guided epipolar/homography, ...).

Coordinates follow COLMAP: (0, 0) is the top-left corner of the top-left pixel, so the centre of
pixel (col, row) is (col + 0.5, row + 0.5). Keypoints are in the original image's pixels.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from colmap_guided.conf import merge_conf


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
    extra: dict = field(default_factory=dict)  # per-matcher caches (e.g. backbone features)


class Matcher:
    """Base class: ``match(a, b)`` returns (M, 2) uint32 indices into a.keypoints and b.keypoints."""

    name = "base"
    default_conf: dict = {}
    verification_conf: dict = {}  # options of verify.two_view_options for this matcher's pairs (e.g. min_num_inliers)
    pair_workers: int = 1  # pairs that match_database may match at once in threads (``match`` must be thread-safe)
    torch_threads: int | None = None  # torch CPU threads while match_database runs (set, then restored); None: as is

    def __init__(self, conf: dict | None = None):
        self.conf = merge_conf(self.default_conf, conf, f"{self.name} matcher")

    def match(self, a: ImageData, b: ImageData) -> np.ndarray:
        raise NotImplementedError

    def release(self, name: str) -> None:
        """Called when the pipeline will not pass image ``name`` again: drop what is cached for it."""

    def describe(self) -> dict:
        """What the report records about this matcher."""
        return {"name": self.name, "conf": self.conf}


@contextlib.contextmanager
def scoped_torch_threads(threads: int | None):
    """torch's (process-wide) CPU thread count set to ``threads`` inside the block, restored after it.
    A library call must not leave global state changed; None leaves it as it is."""
    if threads is None:
        yield
        return
    import torch

    saved = torch.get_num_threads()
    if saved != threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        if torch.get_num_threads() != saved:
            torch.set_num_threads(saved)
