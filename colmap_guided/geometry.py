"""Two-view geometry shared by the stages, the evaluation and the training: poses are
``cam_from_world`` (x_cam = R x_world + t), a relative pose is cam2_from_cam1, F and E map image
1 to epipolar lines in image 2 (x_2^T F x_1 = 0)."""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=np.float64)


def relative_pose(
    R1: np.ndarray, t1: np.ndarray, R2: np.ndarray, t2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """cam2_from_cam1 from two cam_from_world poses."""
    R1, R2 = np.asarray(R1, float), np.asarray(R2, float)
    R = R2 @ R1.T
    return R, np.asarray(t2, float).ravel() - R @ np.asarray(t1, float).ravel()


def essential_from_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """E = [t]_× R of the relative pose cam2_from_cam1."""
    return skew(np.asarray(t, float).ravel()) @ np.asarray(R, float)


def fundamental_from_poses(K_a, R_a, t_a, K_b, R_b, t_b) -> np.ndarray:
    """F with x_B^T F x_A = 0 for ideal pixels, from world-to-camera poses (R, t) and intrinsics:
    F = K_b^{-T} E K_a^{-1} with E of the relative pose B←A, normalised to unit Frobenius norm."""
    F = (
        np.linalg.inv(K_b).T
        @ essential_from_pose(*relative_pose(R_a, t_a, R_b, t_b))
        @ np.linalg.inv(K_a)
    )
    return F / np.linalg.norm(F)


def apply_h(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Points (N, 2) mapped by the homography H."""
    p = np.concatenate([pts, np.ones((len(pts), 1))], 1) @ H.T
    return p[:, :2] / p[:, 2:3]


def photo_up(cam_from_world_rotations, level_prior: float = 0.01) -> np.ndarray | None:
    """The world's up direction from photos taken upright, or None where their image-up vectors
    (-y rows of R) disagree (mean shorter than 0.5, or fewer than half of them within 30 degrees
    of it: scans rotated by 90 degrees).

    Start from the mean image-up (COLMAP's model_orientation_aligner, "IMAGE-ORIENTATION"), biased
    by the photos' pitch, and pull it towards the direction perpendicular to the cameras' x axes
    (level: roll ~0, whatever the pitch): up = (X^T X / n + level_prior I)^-1 mean. Where the x axes
    are all parallel (photos facing one way) the mean decides along that axis alone."""
    R = np.asarray(list(cam_from_world_rotations), float).reshape(-1, 3, 3)
    ups = -R[:, 1]
    mean = ups.mean(axis=0) if len(ups) else np.zeros(3)
    if np.linalg.norm(mean) < 0.5:
        return None
    upright = ups @ (mean / np.linalg.norm(mean)) > np.cos(np.radians(30))  # rotated scans out
    if 2 * upright.sum() < len(ups):
        return None
    xs, mean = R[upright, 0], ups[upright].mean(axis=0)
    up = np.linalg.solve(xs.T @ xs / len(xs) + level_prior * np.eye(3), mean)
    return up / np.linalg.norm(up)


def image_rays(camera, xy: np.ndarray) -> np.ndarray:
    """Normalised camera coordinates (N, 2) of pixels ``xy``, distortion included; where
    undistortion does not converge (a print with strong estimated distortion, far from the centre)
    the pinhole part of the camera gives the ray, so that no caller draws or writes NaN."""
    xy = np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 2)
    rays = np.asarray(camera.cam_from_img(xy), np.float64).reshape(-1, 2)
    bad = ~np.isfinite(rays).all(axis=1)
    if bad.any():
        K = np.asarray(camera.calibration_matrix(), np.float64)
        pinhole = np.c_[xy[bad], np.ones(bad.sum())] @ np.linalg.inv(K).T
        rays[bad] = pinhole[:, :2] / pinhole[:, 2:]
    return rays
