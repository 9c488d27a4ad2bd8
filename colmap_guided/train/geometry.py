"""Epipolar geometry of the training pairs (paper §4.2.2): F in scaled frames, induced by a
homography; pixel-frame conversions. F from poses and the shared two-view helpers:
``colmap_guided.geometry``.

Coordinates. COLMAP's: (0, 0) is the top-left corner of the top-left pixel. The models of the
training scenes are in the frame of the stored (downscaled) images. A training image is resized
to at most ``resolution`` px on its long side with both sides multiples of the stride; this maps
x_train = (sx·x, sy·y), a pure scale in the corner convention (``scale_fundamental``). Lens
distortion: F is defined on ideal (undistorted) pinhole pixels, so the feature-cell centres used by
the epipolar loss are undistorted with the camera model before F is applied (``ideal_pixels``);
observed keypoints are used as they are for point supervision and PCK.
"""

from __future__ import annotations

import numpy as np
import pycolmap

from colmap_guided.geometry import skew


def scale_fundamental(F: np.ndarray, scale_a, scale_b) -> np.ndarray:
    """F in frames scaled by (sx, sy) per image: F' = S_b^{-T} F S_a^{-1}."""
    Sa_inv = np.diag([1.0 / scale_a[0], 1.0 / scale_a[1], 1.0])
    Sb_inv = np.diag([1.0 / scale_b[0], 1.0 / scale_b[1], 1.0])
    return Sb_inv.T @ F @ Sa_inv


def induced_fundamental(H: np.ndarray, epipole_b: np.ndarray) -> np.ndarray:
    """Plane-induced F = [e']_× H (Hartley & Zisserman, result 13.3): x_B^T F x_A = 0 if x_B ~ H
    x_A."""
    F = skew(epipole_b) @ H
    return F / np.linalg.norm(F)


def colmap_to_cv(H: np.ndarray) -> np.ndarray:
    """A homography between COLMAP pixel frames → the same map in OpenCV's (centre-at-integer)
    frames."""
    T = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1.0]])
    return np.linalg.inv(T) @ H @ T


def ideal_pixels(camera: pycolmap.Camera, xy: np.ndarray) -> np.ndarray:
    """Undistort observed pixels (N, 2) to the ideal pinhole pixels of the same calibration
    matrix."""
    if camera.model_name in ("SIMPLE_PINHOLE", "PINHOLE"):
        return xy.astype(np.float64)
    normalized = camera.cam_from_img(np.ascontiguousarray(xy, dtype=np.float64))
    K = camera.calibration_matrix()
    return normalized @ K[:2, :2].T + K[:2, 2]
