"""The learned feature types' shared stage (ALIKED, XFeat): a photo read for a network in COLMAP's
frame, its keypoints in COLMAP's convention, and the per-image loop that writes them to the
database.

Keypoints are stored as COLMAP stores ALIKED's: (x, y, 1, 0, 0, 1), the top-left corner of the
top-left pixel at (0, 0); the descriptors as ``database.write_features`` stores their type.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

from .. import database as dbio
from .. import images
from ..log import logger, progress
from .cameras import import_new, reader_options, skip_unread


def read_for_network(path: Path, max_size: int) -> tuple[np.ndarray, float, float]:
    """(H, W, 3) uint8 RGB of a photo in COLMAP's frame, longer side at most ``max_size`` (a JPEG 4x
    that or more is decoded reduced), and the (x, y) factors from that grid to the photo's."""
    width, height = images.image_size(path)
    scale = min(1.0, max_size / max(width, height))
    rgb = images.read_image(path, 2 * max_size)
    if scale < 1.0:
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        box = images.decoded_box((width, height), rgb.shape)
        rgb = np.asarray(
            Image.fromarray(rgb).resize(size, Image.BILINEAR, box=box, reducing_gap=None)
        )
    return rgb, width / rgb.shape[1], height / rgb.shape[0]


def colmap_keypoints(xy: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """(N, 6) float32 COLMAP keypoints of pixel centres ``xy`` (integers in the network's grid) in
    the photo."""
    keypoints = np.zeros((len(xy), 6), np.float32)
    keypoints[:, 0], keypoints[:, 1] = (xy[:, 0] + 0.5) * sx, (xy[:, 1] + 0.5) * sy
    # COLMAP's FeatureKeypoint(x, y): identity affine shape
    keypoints[:, 2], keypoints[:, 5] = 1.0, 1.0
    return keypoints


def extract_images(
    database_path: Path,
    image_path: Path,
    image_names: list[str],
    conf: dict,
    check: bool,
    label: str,
    kind: str,
    extract_image: Callable[[Path], tuple[np.ndarray, np.ndarray]],
) -> dict:
    """``extract_image`` (a photo's path -> COLMAP keypoints and descriptors of the database type
    ``kind``) for the ``image_names`` not yet in the database (a rerun continues where it stopped).
    Cameras and images are made by COLMAP's own reader (``conf``'s camera grouping, as for SIFT).
    Returns {"num_extracted", "skipped", "time", "time_per_image"}."""
    present = set()
    if database_path.exists():
        with dbio.open_database(database_path) as db:
            present = set(dbio.images_by_name(db))
    new = [name for name in image_names if name not in present]
    skipped: dict[str, str] = {}
    if new and check:
        new, skipped = images.check_images(image_path, new, None)
    if new:
        import_new(database_path, image_path, new, *reader_options(conf))
    start = time.time()
    done = 0
    with dbio.open_database(database_path) as db:
        by_name = dbio.images_by_name(db)
        skip_unread(new, by_name, skipped)
        wanted = set(image_names)
        todo = [
            image
            for name, image in by_name.items()
            if name in wanted and not dbio.has_keypoints(db, image.image_id)
        ]
        if todo:
            logger.info(
                "Extracting %s for %d images (%d already in the database)",
                label,
                len(todo),
                len(image_names) - len(todo) - len(skipped),
            )
        for image in progress(todo, "extract", "img"):
            keypoints, descriptors = extract_image(image_path / image.name)
            with dbio.transaction(db):
                dbio.write_features(db, image.image_id, keypoints, descriptors, kind)
            done += 1
    elapsed = time.time() - start
    return {
        "num_extracted": done,
        "skipped": skipped,
        "time": elapsed,
        "time_per_image": elapsed / done if done else None,
    }
