"""Pose errors of a reconstruction against a ground-truth model (the synthetic scene's, or any
COLMAP model)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pycolmap

from colmap_guided.log import logger
from colmap_guided.synthetic import SceneInfo, load_ground_truth

from .metrics import rotation_angle


def pose_errors(
    reconstruction: pycolmap.Reconstruction, gt: SceneInfo | pycolmap.Reconstruction | str | Path
) -> dict[str, tuple[float, float]]:
    """Per ground-truth image: (rotation error in degrees, camera-centre error / scene extent).

    The estimate is aligned to the ground truth by the similarity that pycolmap fits to the camera
    centres (LO-RANSAC, inlier threshold 5 % of the extent). The scene extent is the largest
    distance between two ground-truth camera centres. Images missing from ``reconstruction`` (or all
    images, when no alignment is found) get (inf, inf).
    """
    gt_rec = load_ground_truth(gt)
    centers = {im.name: im.projection_center() for im in gt_rec.images.values()}
    pts = np.array(list(centers.values()))
    extent = float(np.max(np.linalg.norm(pts[:, None] - pts[None], axis=2)))
    errors = {name: (math.inf, math.inf) for name in centers}
    sim = pycolmap.align_reconstructions_via_proj_centers(reconstruction, gt_rec, 0.05 * extent)
    if sim is None:
        logger.warning("Could not align the reconstruction to the ground truth.")
        return errors
    aligned = pycolmap.Reconstruction(reconstruction)
    aligned.transform(sim)
    gt_by_name = {im.name: im for im in gt_rec.images.values()}
    for image in aligned.images.values():
        if image.name not in gt_by_name or not image.has_pose:
            continue
        ref = gt_by_name[image.name]
        angle = rotation_angle(
            image.cam_from_world().rotation.matrix() @ ref.cam_from_world().rotation.matrix().T
        )
        center_err = float(np.linalg.norm(image.projection_center() - ref.projection_center()))
        errors[image.name] = (angle, center_err / extent)
    return errors
