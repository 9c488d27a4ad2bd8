"""Stage 4: geometric verification of each matched pair with COLMAP's own two-view estimator.

Uses ``pycolmap.estimate_two_view_geometry`` (what `colmap exhaustive_matcher` runs after matching),
pair by pair, so progress shows and a killed run resumes at the first unverified pair.
"""

from __future__ import annotations

import numpy as np
import pycolmap

default_conf = {
    "min_num_inliers": 15,  # COLMAP's default
    "max_error": 4.0,  # RANSAC threshold in pixels, COLMAP's default
    "confidence": 0.999,
    "random_seed": 0,  # deterministic verification: reruns give the same database
}


def default_camera(width: int, height: int) -> pycolmap.Camera:
    """COLMAP's camera for a photo without EXIF focal length (feature_extractor's default): SIMPLE_RADIAL,
    f = 1.2 * max(width, height), principal point at the centre."""
    return pycolmap.Camera.create_from_model_id(0, pycolmap.CameraModelId.SIMPLE_RADIAL, 1.2 * max(width, height), width, height)


def two_view_options(conf: dict | None = None) -> pycolmap.TwoViewGeometryOptions:
    conf = {**default_conf, **(conf or {})}
    options = pycolmap.TwoViewGeometryOptions()
    options.min_num_inliers = conf["min_num_inliers"]
    options.ransac.max_error = conf["max_error"]
    options.ransac.confidence = conf["confidence"]
    options.ransac.random_seed = conf["random_seed"]
    return options


def verify_pair(
    camera_a: pycolmap.Camera, kpts_a: np.ndarray, camera_b: pycolmap.Camera, kpts_b: np.ndarray, matches: np.ndarray, options: pycolmap.TwoViewGeometryOptions
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
