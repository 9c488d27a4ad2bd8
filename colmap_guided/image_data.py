"""Plain data types shared by the database io and the matchers, and the bounded image cache of the
match and verify stages (numpy only: importing it loads no torch).

Coordinates follow COLMAP: (0, 0) is the top-left corner of the top-left pixel, so the centre of
pixel (col, row) is (col + 0.5, row + 0.5). Keypoints are in the original image's pixels.
"""

from __future__ import annotations

import math
from collections import defaultdict, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np


@dataclass
class ImageData:
    """One image as a matcher sees it: its keypoints, descriptors and where its pixels are."""

    name: str  # COLMAP image name (path relative to the image folder, '/'-separated)
    image_id: int
    path: Path  # absolute path of the image file (read-only; never written)
    # (N, >=2) float32, x, y first (COLMAP convention), then scale/orientation/affine
    keypoints: np.ndarray
    descriptors: np.ndarray  # (N, D) uint8 (SIFT) or float32
    width: int
    height: int
    # pycolmap.Camera of the database, when there is one (COLMAP's guided matching needs it)
    camera: object = None
    # per-matcher caches (e.g. backbone features, see Matcher.prepare)
    extra: dict = field(default_factory=dict)


# A pair to match: (image_id_a, image_id_b, name_a, name_b).
PairKey = tuple[int, int, str, str]


# Images whose keypoints, descriptors and backbone features the match stage holds at once (about
# 2 MB each with 8k SIFT and the guided backbone): past it, the image needed latest is dropped and
# read again at its next pair, so memory stays flat in N (recon_scripts' `scale` preset measures how
# often that happens).
MAX_IMAGES_HELD = 128


class HeldImages:
    """What ``load(name)`` gives for the images of ``pairs`` (.., .., name_a, name_b), taken in that
    order with ``pair``: an image is loaded at its first pair and dropped after its last; at most
    ``max_held`` are held: past that, the one whose next pair comes last is dropped
    (``on_drop(name)``) and loaded again then (Belady's rule)."""

    def __init__(
        self,
        pairs: list[tuple],
        load: Callable,
        max_held: int = MAX_IMAGES_HELD,
        on_drop: Callable | None = None,
    ):
        if max_held < 2:
            raise ValueError(
                f"max_images_held must be at least 2 (the two images of a pair), got {max_held}."
            )
        self.load, self.max_held, self.on_drop = load, max_held, on_drop
        # positions of each image's pairs not yet taken
        self.uses: dict[str, deque] = defaultdict(deque)
        for i, key in enumerate(pairs):
            for name in key[2:]:
                self.uses[name].append(i)
        self.held: dict[str, object] = {}
        self.reads = self.most_held = 0

    def _get(self, name: str, pair: tuple):
        if name not in self.held:
            if len(self.held) >= self.max_held:
                next_use = lambda n: self.uses[n][0] if self.uses[n] else math.inf  # noqa: E731
                drop = max((n for n in self.held if n not in pair), key=next_use)
                self.held.pop(drop)
                if self.on_drop is not None:
                    self.on_drop(drop)
            self.held[name] = self.load(name)
            self.reads += 1
            self.most_held = max(self.most_held, len(self.held))
        return self.held[name]

    def skip(self, key: tuple) -> None:
        """Pass over the next pair ``key`` without its images."""
        for name in key[2:]:
            self.uses[name].popleft()
            if not self.uses[name]:
                self.held.pop(name, None)

    def pair(self, key: tuple) -> tuple:
        """The two images of ``key``, the next pair; those whose last pair it is are dropped."""
        pair = tuple(key[2:])
        values = tuple(self._get(name, pair) for name in pair)
        for name in pair:
            self.uses[name].popleft()
            if not self.uses[name]:
                self.held.pop(name, None)
        return values


def most_images_held(todo: list[tuple]) -> int:
    """Images held at once when pairs (.., .., name_a, name_b) are matched in this order, each image
    from its first pair to its last."""
    last = {name: i for i, key in enumerate(todo) for name in key[2:]}
    held, most = set(), 0
    for i, key in enumerate(todo):
        held.update(key[2:])
        most = max(most, len(held))
        held.difference_update(name for name in key[2:] if last[name] == i)
    return most


def pair_order(todo: list[tuple]) -> list[tuple]:
    """``todo`` (.., .., name_a, name_b) in the order that holds fewer images at once: as given
    (name order, where a folder per scene keeps a scene together) or grouped along a Cuthill-McKee
    order of the images (breadth first through the pair graph, fewest pairs first), which keeps
    together an archive whose file names say nothing (retrieval pairs of 437 photos under random
    names: 78 images held at once instead of 340)."""
    neighbours: dict[str, set] = defaultdict(set)
    for key in todo:
        neighbours[key[2]].add(key[3])
        neighbours[key[3]].add(key[2])
    position: dict[str, int] = {}
    for seed in sorted(neighbours, key=lambda n: (len(neighbours[n]), n)):
        if seed in position:
            continue
        queue = deque([seed])
        position[seed] = len(position)
        while queue:
            for other in sorted(
                neighbours[queue.popleft()] - position.keys(), key=lambda n: (len(neighbours[n]), n)
            ):
                position[other] = len(position)
                queue.append(other)
    grouped = sorted(todo, key=lambda key: sorted((position[key[2]], position[key[3]])))
    return grouped if most_images_held(grouped) < most_images_held(todo) else list(todo)
