"""COLMAP's own guided matching (the paper's Table 2 baseline; `exhaustive_matcher
--FeatureMatching.guided_matching 1`), behind the matcher interface.

Raw matches (mutual NN + ratio, as COLMAP's SIFT matcher) → COLMAP's two-view geometry (E, F or H,
the estimator the pipeline verifies with) → COLMAP re-matches every keypoint constrained by that
geometry (``pycolmap.FeatureMatcher.match_guided``: the other keypoint within ``max_error`` px of
the epipolar line, or of the homography's prediction for planar scenes). A pair whose raw matches
do not verify keeps its raw matches (verification rejects them later, as in COLMAP).
"""

from __future__ import annotations

import numpy as np
import pycolmap

from colmap_guided import verify
from colmap_guided.log import colmap_quiet
from colmap_guided.matchers.base import ImageData, Matcher
from colmap_guided.matchers.raw import RawMatcher


def _colmap_features(
    image: ImageData,
) -> tuple[pycolmap.FeatureKeypoints, pycolmap.FeatureDescriptors]:
    """The image's keypoints and SIFT descriptors as COLMAP's types, converted once per image."""
    if "colmap_features" not in image.extra:
        kp = np.asarray(image.keypoints, np.float64)
        if kp.shape[1] >= 6:
            keypoints = [
                pycolmap.FeatureKeypoint(x=r[0], y=r[1], a11=r[2], a12=r[3], a21=r[4], a22=r[5])
                for r in kp
            ]
        else:
            keypoints = [pycolmap.FeatureKeypoint(x=r[0], y=r[1]) for r in kp]
        descriptors = pycolmap.FeatureDescriptors(
            pycolmap.FeatureExtractorType.SIFT, np.ascontiguousarray(image.descriptors)
        )
        image.extra["colmap_features"] = (pycolmap.FeatureKeypoints(keypoints), descriptors)
    return image.extra["colmap_features"]


class ColmapGuidedMatcher(Matcher):
    """Raw matches, COLMAP two-view geometry, then COLMAP's guided re-matching of all keypoints."""

    name = "guided_colmap"
    default_conf = {
        "ratio": 0.8,  # Lowe's ratio of the raw matches and of COLMAP's guided re-matching
        "max_distance": 0.7,  # COLMAP's SiftMatchingOptions.max_distance for the guided re-matching
        # px: the epipolar/homography window of the re-matching (COLMAP: the RANSAC threshold)
        "max_error": 4.0,
        "device": "auto",  # of the raw matches (torch)
        "chunk_size": 1024,
    }

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        self.raw = RawMatcher({k: self.conf[k] for k in ("ratio", "device", "chunk_size")})
        self.device = self.raw.device
        options = pycolmap.FeatureMatchingOptions()
        options.sift.max_ratio = 1.0 if self.conf["ratio"] is None else self.conf["ratio"]
        options.sift.max_distance = self.conf["max_distance"]
        options.sift.cross_check = True
        with colmap_quiet():
            self.colmap = pycolmap.FeatureMatcher.create(options, pycolmap.Device.cpu)
        self.two_view_options = verify.two_view_options({"max_error": self.conf["max_error"]})

    def match(self, a: ImageData, b: ImageData) -> np.ndarray:
        for image in (a, b):  # before any work: COLMAP's matcher reads only its own SIFT encoding
            if image.descriptors.dtype != np.uint8:
                raise ValueError(
                    f"{image.name}: COLMAP's guided matching needs SIFT (uint8) "
                    "descriptors; use --matcher guided_epipolar for other features."
                )
        raw = self.raw.match(a, b)
        cam_a, cam_b = (im.camera or verify.default_camera(im.width, im.height) for im in (a, b))
        with colmap_quiet():
            geometry = verify.verify_pair(
                cam_a, a.keypoints, cam_b, b.keypoints, raw, self.two_view_options
            )
            if len(geometry.inlier_matches) == 0:
                return raw
            kp_a, desc_a = _colmap_features(a)
            kp_b, desc_b = _colmap_features(b)
            self.colmap.match_guided(
                self.conf["max_error"], kp_a, desc_a, cam_a, kp_b, desc_b, cam_b, geometry
            )
        return np.asarray(geometry.inlier_matches, np.uint32).reshape(-1, 2)
