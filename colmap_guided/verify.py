"""Stage 4: geometric verification of each matched pair with COLMAP's own two-view estimator.

Uses ``pycolmap.estimate_two_view_geometry`` (what `colmap exhaustive_matcher` runs after matching),
pair by pair, so progress shows and a killed run resumes at the first unverified pair.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pycolmap

from . import database as dbio
from .conf import merge_conf
from .image_data import MAX_IMAGES_HELD, HeldImages, PairKey
from .log import colmap_quiet, progress

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


def verify_images(a, b, matches: np.ndarray, conf: dict | None = None) -> pycolmap.TwoViewGeometry:
    """``verify_pair`` of two ``ImageData`` on their cameras (COLMAP's default where they have
    none) with ``two_view_options(conf)``: e.g. a matcher's ``verification_conf``."""
    camera_a, camera_b = (
        image.camera or default_camera(image.width, image.height) for image in (a, b)
    )
    options = two_view_options(conf)
    return verify_pair(camera_a, a.keypoints, camera_b, b.keypoints, matches, options)


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


def union(primary: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """``primary`` (K, 2) matches plus those of ``extra`` whose keypoints ``primary`` leaves
    unmatched in both images: the union stays one-to-one, and ``primary`` wins where the two
    disagree; sorted by index in the first image."""
    primary, extra = (np.asarray(m, np.int64).reshape(-1, 2) for m in (primary, extra))
    keep = ~np.isin(extra[:, 0], primary[:, 0]) & ~np.isin(extra[:, 1], primary[:, 1])
    merged = np.concatenate([primary, extra[keep]])
    return merged[np.argsort(merged[:, 0], kind="stable")]


def best_of(
    camera_a: pycolmap.Camera,
    kpts_a: np.ndarray,
    camera_b: pycolmap.Camera,
    kpts_b: np.ndarray,
    guided: np.ndarray,
    raw: Callable[[], np.ndarray],
    options: pycolmap.TwoViewGeometryOptions,
    min_inliers: int,
    raw_min_inliers: int,
    min_agreement: float,
    raw_below: int | None = None,
) -> tuple[np.ndarray, pycolmap.TwoViewGeometry]:
    """Guided or raw matches of one pair, whichever verification trusts, and their geometry (what
    ``verify_pair`` with ``options`` gives on them: the pair needs no second verification).

    Never lose what raw matching finds, never keep what it contradicts: guided passes with
    ``min_inliers`` (a wrong coarse flow gathers chance inliers), raw with ``raw_min_inliers``
    (COLMAP's 15, as plain COLMAP). When only one passes it is returned. When both pass and their
    geometries agree (``agreement`` >= ``min_agreement`` both ways) the union of their inliers is
    verified too and the candidate with the most inliers is returned (guided first on ties); when
    they disagree, one of them holds wrong inliers that its own RANSAC accepted, and raw is
    returned, as plain COLMAP would keep the pair. When none passes, raw (which fails
    verification). ``raw`` is computed only when needed: not when the guided matches reach
    ``raw_below`` inliers (None: always)."""

    def check(m: np.ndarray) -> tuple[np.ndarray, pycolmap.TwoViewGeometry]:
        m = np.asarray(m, np.uint32).reshape(-1, 2)
        geometry = verify_pair(camera_a, kpts_a, camera_b, kpts_b, m, options)
        return np.asarray(geometry.inlier_matches, np.int64).reshape(-1, 2), geometry

    guided = np.asarray(guided, np.uint32).reshape(-1, 2)
    with colmap_quiet():
        g_inl, g_geo = check(guided)
        if raw_below is not None and len(g_inl) >= max(raw_below, min_inliers):
            return guided, g_geo
        raw_matches = np.asarray(raw(), np.uint32).reshape(-1, 2)
        r_inl, r_geo = check(raw_matches)
        if len(g_inl) < min_inliers:
            return raw_matches, r_geo
        if len(r_inl) < raw_min_inliers:
            return guided, g_geo
        threshold = options.ransac.max_error
        if (
            min(
                agreement(g_geo, kpts_a, kpts_b, r_inl, threshold),
                agreement(r_geo, kpts_a, kpts_b, g_inl, threshold),
            )
            < min_agreement
        ):
            return raw_matches, r_geo
        candidates = [(len(g_inl), guided, g_geo), (len(r_inl), raw_matches, r_geo)]
        both = union(g_inl, r_inl).astype(np.uint32)
        u_inl, u_geo = check(both)
        if len(u_inl) >= min_inliers:
            candidates.append((len(u_inl), both, u_geo))
    _, matches, geometry = max(candidates, key=lambda c: c[0])  # the first on ties: guided, raw
    return matches, geometry


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
        for key in progress(unverified, "verify", "pair"):
            (camera_a, kpts_a), (camera_b, kpts_b) = held.pair(key)
            matches = dbio.read_pair_matches(db, key[0], key[1])
            geometry = verify_pair(camera_a, kpts_a, camera_b, kpts_b, matches, options)
            dbio.write_pair_geometry(db, key[0], key[1], geometry)
    return len(unverified)
