"""Stage 4: geometric verification of each matched pair with COLMAP's own two-view estimator.

Uses ``pycolmap.estimate_two_view_geometry`` (what `colmap exhaustive_matcher` runs after matching),
pair by pair, so progress shows and a killed run resumes at the first unverified pair.
"""

from __future__ import annotations

import numpy as np
import pycolmap
from tqdm import tqdm

from . import database as dbio
from .conf import merge_conf
from .image_data import MAX_IMAGES_HELD, HeldImages, PairKey
from .log import colmap_quiet

default_conf = {
    "min_num_inliers": 15,  # COLMAP's default
    "max_error": 4.0,  # RANSAC threshold in pixels, COLMAP's default
    "confidence": 0.999,
    "random_seed": 0,  # deterministic verification: reruns give the same database
}


def default_camera(width: int, height: int) -> pycolmap.Camera:
    """COLMAP's camera for a photo without EXIF focal length (feature_extractor's default):
    SIMPLE_RADIAL, f = 1.2 * max(width, height), principal point at the centre."""
    return pycolmap.Camera.create_from_model_id(
        0, pycolmap.CameraModelId.SIMPLE_RADIAL, 1.2 * max(width, height), width, height
    )


def two_view_options(conf: dict | None = None) -> pycolmap.TwoViewGeometryOptions:
    conf = merge_conf(default_conf, conf, "verification")
    options = pycolmap.TwoViewGeometryOptions()
    options.min_num_inliers = conf["min_num_inliers"]
    options.ransac.max_error = conf["max_error"]
    options.ransac.confidence = conf["confidence"]
    options.ransac.random_seed = conf["random_seed"]
    return options


def verify_pair(
    camera_a: pycolmap.Camera,
    kpts_a: np.ndarray,
    camera_b: pycolmap.Camera,
    kpts_b: np.ndarray,
    matches: np.ndarray,
    options: pycolmap.TwoViewGeometryOptions,
) -> pycolmap.TwoViewGeometry:
    """Two-view geometry of one pair; inlier_matches is empty when the pair does not verify."""
    if len(matches) < options.min_num_inliers:
        geometry = pycolmap.TwoViewGeometry()
        geometry.config = pycolmap.TwoViewGeometryConfiguration.UNDEFINED
        return geometry
    return pycolmap.estimate_two_view_geometry(
        camera_a,
        np.ascontiguousarray(kpts_a[:, :2], np.float64),
        camera_b,
        np.ascontiguousarray(kpts_b[:, :2], np.float64),
        np.ascontiguousarray(matches, np.uint32),
        options,
    )


def agreement(
    geometry: pycolmap.TwoViewGeometry,
    kpts_a: np.ndarray,
    kpts_b: np.ndarray,
    matches: np.ndarray,
    max_error: float,
) -> float:
    """Share of ``matches`` (N, 2) that fit ``geometry``'s fundamental matrix (Sampson error under
    ``max_error`` pixels, the RANSAC threshold): do two matchers' verified pairs tell the same
    geometry? 1.0 when there is nothing to compare (no match; no fundamental matrix, e.g. a pure
    rotation)."""
    F = np.asarray(geometry.F, np.float64)
    if len(matches) == 0 or F.shape != (3, 3) or not np.all(np.isfinite(F)) or not np.any(F):
        return 1.0
    matches = np.asarray(matches, np.int64)
    errors = pycolmap.compute_squared_sampson_error(
        np.ascontiguousarray(kpts_a[matches[:, 0], :2], np.float64),
        np.ascontiguousarray(kpts_b[matches[:, 1], :2], np.float64),
        F,
    )
    return float(np.mean(np.asarray(errors) < max_error**2))


def verify_pairs(
    db: pycolmap.Database,
    images: dict[str, pycolmap.Image],
    id_pairs: list[PairKey],
    options: pycolmap.TwoViewGeometryOptions,
    max_images_held: int = MAX_IMAGES_HELD,
) -> int:
    """Two-view geometry of every matched, not yet verified pair (id_a, id_b, name_a, name_b) of the
    open database ``db`` (``images``: name -> its image), in the order given; returns how many were
    verified now. An image's camera and keypoints are read when ``HeldImages`` loads it (at most
    ``max_images_held`` at once)."""
    unverified = [
        p
        for p in id_pairs
        if dbio.pair_has_matches(db, p[0], p[1]) and not dbio.pair_is_verified(db, p[0], p[1])
    ]

    def load(name: str) -> tuple[pycolmap.Camera, np.ndarray]:
        image = images[name]
        return dbio.read_camera(db, image.camera_id), dbio.read_keypoints(db, image.image_id)

    held = HeldImages(unverified, load, max_images_held)
    with colmap_quiet():
        for key in tqdm(
            unverified,
            desc="verify",
            total=len(unverified),
            unit="pair",
            disable=None,
            dynamic_ncols=True,
            leave=False,
        ):
            (camera_a, kpts_a), (camera_b, kpts_b) = held.pair(key)
            matches = dbio.read_pair_matches(db, key[0], key[1])
            geometry = verify_pair(camera_a, kpts_a, camera_b, kpts_b, matches, options)
            dbio.write_pair_geometry(db, key[0], key[1], geometry)
    return len(unverified)
