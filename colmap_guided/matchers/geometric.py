"""Classical guided matching baselines of the paper's Table 2 (Shah et al. 2015).

A geometric model is estimated (LO-RANSAC, pycolmap) from raw matches of the 20 % largest-scale
keypoints of each image, then all keypoints are re-matched with the candidates restricted by it:
- ``guided_epipolar``: p^B within ``band_px`` of the epipolar line F p^A (and p^A within
  ``band_px`` of F^T p^B for the reverse direction);
- ``guided_homography``: p^B within ``window_px`` of H p^A (and p^A of H^-1 p^B), which is eq. 1 of
  the paper with the homography as the coarse match.
Mutual check and ratio test among the candidates follow, as for the learned guidance. When the
model cannot be estimated (fewer than ``min_seed_inliers``), the pair falls back to raw matching.
"""

from __future__ import annotations

import numpy as np
import pycolmap
import torch

from colmap_guided.log import logger
from colmap_guided.matchers.base import ImageData, Matcher
from colmap_guided.matchers.guided import guided_match
from colmap_guided.matchers.raw import (
    mutual_nn_match,
    normalize_descriptors,
    resolve_device,
)


def keypoint_scales(keypoints: np.ndarray) -> np.ndarray:
    """Scale of each keypoint: column 2 of (x, y, scale, orientation) or sqrt|det| of COLMAP's
    affine (x, y, a11, a12, a21, a22)."""
    if keypoints.shape[1] >= 6:
        a11, a12, a21, a22 = keypoints[:, 2], keypoints[:, 3], keypoints[:, 4], keypoints[:, 5]
        return np.sqrt(np.abs(a11 * a22 - a12 * a21))
    if keypoints.shape[1] >= 3:
        return keypoints[:, 2].astype(np.float64)
    raise ValueError("Keypoints carry no scale (need x, y, scale[, ...] or COLMAP's affine shape).")


def top_scale_indices(keypoints: np.ndarray, fraction: float) -> np.ndarray:
    """Indices of the ``fraction`` largest-scale keypoints (at least one when there are any)."""
    k = max(1, round(fraction * len(keypoints))) if len(keypoints) else 0
    return np.argsort(-keypoint_scales(keypoints), kind="stable")[:k]


def _homogeneous(xy: torch.Tensor) -> torch.Tensor:
    return torch.cat([xy, torch.ones_like(xy[:, :1])], 1)


def epipolar_distances(
    F: torch.Tensor, pts_a: torch.Tensor, pts_b: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Point-to-epipolar-line distances for all pairs, with COLMAP's convention x_b^T F x_a = 0.

    Returns (N, M) distances of p^B to the line F p^A (B pixels) and of p^A to F^T p^B (A pixels).
    """
    ha, hb = _homogeneous(pts_a), _homogeneous(pts_b)
    lines_b = ha @ F.T  # (N, 3): F p^A
    lines_a = hb @ F  # (M, 3): F^T p^B
    alg = lines_b @ hb.T  # (N, M): p^B . F p^A
    d_b = alg.abs() / torch.linalg.norm(lines_b[:, :2], dim=1, keepdim=True).clamp(min=1e-12)
    d_a = alg.abs() / torch.linalg.norm(lines_a[:, :2], dim=1)[None].clamp(min=1e-12)
    return d_b, d_a


def apply_homography(H: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """Map (N, 2) points through a 3x3 homography (points at infinity become NaN-free far
    points)."""
    p = _homogeneous(pts) @ H.T
    w = torch.where(p[:, 2].abs() < 1e-12, torch.full_like(p[:, 2], 1e-12), p[:, 2])
    return p[:, :2] / w[:, None]


class _ShahGuidedMatcher(Matcher):
    """Shared part: seed matches on the largest-scale keypoints, model by LO-RANSAC, guided
    re-matching."""

    model = ""

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        self.device = resolve_device(self.conf["device"])

    def _estimate(self, pa: np.ndarray, pb: np.ndarray) -> dict | None:
        options = pycolmap.RANSACOptions()
        options.max_error = self.conf["ransac_max_error"]
        options.random_seed = 0
        if self.model == "F":
            return pycolmap.estimate_fundamental_matrix(pa, pb, options)
        return pycolmap.estimate_homography_matrix(pa, pb, options)

    def seed_model(
        self, a: ImageData, b: ImageData, da: torch.Tensor, db: torch.Tensor
    ) -> np.ndarray | None:
        """The geometric model (3x3, A -> B) from the top-scale seed matches, or None."""
        sa = top_scale_indices(a.keypoints, self.conf["top_fraction"])
        sb = top_scale_indices(b.keypoints, self.conf["top_fraction"])
        seeds = (
            mutual_nn_match(da[sa], db[sb], self.conf["seed_ratio"], self.conf["chunk_size"])
            .cpu()
            .numpy()
        )
        if len(seeds) < self.conf["min_seed_inliers"]:
            return None
        pa = a.keypoints[sa[seeds[:, 0]], :2].astype(np.float64)
        pb = b.keypoints[sb[seeds[:, 1]], :2].astype(np.float64)
        result = self._estimate(pa, pb)
        if result is None or result["num_inliers"] < self.conf["min_seed_inliers"]:
            return None
        return np.asarray(result[self.model])

    def guided(
        self, a: ImageData, b: ImageData, da: torch.Tensor, db: torch.Tensor, model: torch.Tensor
    ) -> torch.Tensor:
        """Mutual matches of all keypoints with candidates restricted by ``model`` (3x3, A -> B)."""
        raise NotImplementedError

    def match(self, a: ImageData, b: ImageData) -> np.ndarray:
        da = normalize_descriptors(a.descriptors, self.device)
        db = normalize_descriptors(b.descriptors, self.device)
        model = self.seed_model(a, b, da, db)
        if model is None:
            logger.debug(
                "%s: no %s model for %s / %s; raw matching", self.name, self.model, a.name, b.name
            )
            m = mutual_nn_match(da, db, self.conf["ratio"], self.conf["chunk_size"])
        else:
            m = self.guided(
                a, b, da, db, torch.as_tensor(model, dtype=torch.float32, device=self.device)
            )
        return m.cpu().numpy().astype(np.uint32)


_COMMON_CONF = {
    "ratio": 0.8,  # ratio test among the candidates of the guided re-matching (None = off)
    "seed_ratio": 0.8,  # ratio test of the raw seed matching
    "top_fraction": 0.2,  # seed keypoints: this share of largest scales (Shah et al. 2015)
    "min_seed_inliers": 15,  # fewer RANSAC inliers: no model, the pair is raw-matched
    "ransac_max_error": 4.0,  # px, COLMAP's default verification threshold
    "device": "auto",
    "chunk_size": 1024,
}


class EpipolarGuidedMatcher(_ShahGuidedMatcher):
    """Re-match inside the epipolar band of a fundamental matrix estimated from top-scale seeds."""

    name = "guided_epipolar"
    model = "F"
    default_conf = {**_COMMON_CONF, "band_px": 4.0}

    def guided(
        self, a: ImageData, b: ImageData, da: torch.Tensor, db: torch.Tensor, model: torch.Tensor
    ) -> torch.Tensor:
        pa = torch.tensor(a.keypoints[:, :2], dtype=torch.float32, device=self.device)
        pb = torch.tensor(b.keypoints[:, :2], dtype=torch.float32, device=self.device)
        band = self.conf["band_px"]

        def mask(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            d_b, d_a = epipolar_distances(model, pa[rows], pb)
            return d_b < band, d_a < band

        return mutual_nn_match(da, db, self.conf["ratio"], self.conf["chunk_size"], mask_fn=mask)


class HomographyGuidedMatcher(_ShahGuidedMatcher):
    """Re-match within ``window_px`` of the homography's prediction (eq. 1 with m = H)."""

    name = "guided_homography"
    model = "H"
    default_conf = {**_COMMON_CONF, "window_px": 20.0, "max_pairs": 1 << 20}

    def guided(
        self, a: ImageData, b: ImageData, da: torch.Tensor, db: torch.Tensor, model: torch.Tensor
    ) -> torch.Tensor:
        pa = torch.tensor(a.keypoints[:, :2], dtype=torch.float32, device=self.device)
        pb = torch.tensor(b.keypoints[:, :2], dtype=torch.float32, device=self.device)
        flow_ab = apply_homography(model, pa)
        flow_ba = apply_homography(torch.linalg.inv(model), pb)
        w = self.conf["window_px"]
        return guided_match(
            pa,
            da,
            pb,
            db,
            flow_ab,
            flow_ba,
            w,
            w,
            self.conf["ratio"],
            max_pairs=self.conf["max_pairs"],
        )
