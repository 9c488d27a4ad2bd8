"""Metrics of the paper's evaluation (§5, Table 2) and of WxBS.

Relative pose (the SuperGlue / OANet YFCC protocol):
- poses are ``cam_from_world`` (x_cam = R x_world + t); the relative pose of a pair is
  cam2_from_cam1;
- rotation error = angle of R_est^T R_gt; translation error = angle between the directions of t_est
  and t_gt, folded to [0, 90] (an essential matrix fixes t up to sign); pose error = max of both;
  a pair whose pose could not be estimated has error = inf;
- AUC at 5/10/20 degrees of the cumulative error curve, trapezoid rule, normalised by the threshold.

Essential matrix: OpenCV's RANSAC (``cv2.findEssentialMat`` on normalised coordinates, threshold =
1 px divided by the mean focal length, confidence 0.99999) then ``cv2.recoverPose`` on its inliers,
keeping the candidate E with most cheirality inliers, as in the SuperGlue evaluation.
``estimator='pycolmap'`` uses ``pycolmap.estimate_essential_matrix`` (COLMAP's LO-RANSAC, threshold
in pixels) instead.

WxBS: hand-labelled correspondences ``x1 y1 x2 y2`` scored against the estimated fundamental matrix
(symmetric epipolar distance, see ``symmetric_epipolar_distance``) or homography (symmetric transfer
error); the score of a pair at threshold T is the share of correspondences with error < T pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

from colmap_guided.geometry import apply_h

AUC_THRESHOLDS = (5.0, 10.0, 20.0)
WXBS_THRESHOLDS = (3.0, 5.0, 10.0)


# ------------------------------------------------------------------------------------- pose errors
def rotation_angle(R: np.ndarray) -> float:
    """Angle (degrees) of a rotation matrix: atan2(|sin|, cos), accurate near 0 and 180 degrees."""
    R = np.asarray(R, float)
    cos = (np.trace(R) - 1.0) / 2.0
    sin = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return float(np.degrees(np.arctan2(sin, cos)))


def rotation_error(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Angle (degrees) of R_est^T R_gt."""
    return rotation_angle(np.asarray(R_est, float).T @ np.asarray(R_gt, float))


def translation_error(
    t_est: np.ndarray, t_gt: np.ndarray, sign_ambiguous: bool = True, min_norm: float = 1e-8
) -> float:
    """Angle (degrees) between translation directions; folded to [0, 90] when the sign is ambiguous.

    A reference translation of (near) zero length has no direction: the error is 0
    (SuperGlue's rule).
    """
    t_est, t_gt = np.asarray(t_est, float).ravel(), np.asarray(t_gt, float).ravel()
    n_est, n_gt = np.linalg.norm(t_est), np.linalg.norm(t_gt)
    if n_gt < min_norm:
        return 0.0
    if n_est < min_norm:
        return 90.0 if sign_ambiguous else 180.0
    cos = float(np.clip(t_est @ t_gt / (n_est * n_gt), -1.0, 1.0))
    angle = float(np.degrees(np.arccos(cos)))
    return min(angle, 180.0 - angle) if sign_ambiguous else angle


def relative_pose_error(R_est, t_est, R_gt, t_gt, sign_ambiguous: bool = True) -> dict:
    """{'R': rotation error, 't': translation direction error, 'pose': max of both} in degrees.

    ``R_est`` None (estimation failed) gives inf everywhere.
    """
    if R_est is None or t_est is None:
        return {"R": float("inf"), "t": float("inf"), "pose": float("inf")}
    err_R = rotation_error(R_est, R_gt)
    err_t = translation_error(t_est, t_gt, sign_ambiguous)
    return {"R": err_R, "t": err_t, "pose": max(err_R, err_t)}


def pose_auc(errors, thresholds=AUC_THRESHOLDS) -> list[float]:
    """Area under the cumulative error curve up to each threshold, normalised to [0, 1].

    The curve is recall(e) = share of errors <= e, a step at each sorted error joined by straight
    lines from (0, 0) (trapezoid rule), continued flat to the threshold. Infinite / NaN errors count
    as failures (they lower the recall but are never below a threshold).
    """
    errors = np.asarray(errors, float).ravel()
    errors = np.where(np.isnan(errors), np.inf, errors)
    n = len(errors)
    if n == 0:
        return [0.0 for _ in thresholds]
    errors = np.concatenate([[0.0], np.sort(errors)])
    recall = np.concatenate([[0.0], np.arange(1, n + 1) / n])
    aucs = []
    for thr in thresholds:
        # errors[:k] < thr (errors[0] = 0 always)
        k = int(np.searchsorted(errors, thr, side="left"))
        k = max(k, 1)
        e = np.concatenate([errors[:k], [thr]])
        r = np.concatenate([recall[:k], [recall[k - 1]]])
        area = float(np.sum((r[1:] + r[:-1]) * np.diff(e)) / 2.0)
        aucs.append(area / thr)
    return aucs


def pose_accuracy(errors, thresholds=AUC_THRESHOLDS) -> list[float]:
    """Share of errors below each threshold (the 'mAP' of OANet's tables, histogram version)."""
    errors = np.asarray(errors, float).ravel()
    if len(errors) == 0:
        return [0.0 for _ in thresholds]
    return [float(np.mean(errors < thr)) for thr in thresholds]


# ---------------------------------------------------------------------------- essential RANSAC
def normalize_points(camera, points: np.ndarray) -> np.ndarray:
    """Pixels (COLMAP convention) -> normalised image coordinates through a pycolmap.Camera
    (undistorts)."""
    points = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 2))
    if len(points) == 0:
        return np.zeros((0, 2))
    return np.asarray(camera.cam_from_img(points), np.float64).reshape(-1, 2)


def mean_focal(*cameras) -> float:
    return float(np.mean([f for cam in cameras for f in (cam.focal_length_x, cam.focal_length_y)]))


def estimate_relative_pose(
    pts1: np.ndarray,
    pts2: np.ndarray,
    camera1,
    camera2,
    threshold_px: float = 1.0,
    confidence: float = 0.99999,
    estimator: str = "cv2",
    seed: int = 0,
) -> dict | None:
    """Relative pose cam2_from_cam1 from matched pixels; None when it cannot be estimated.

    Returns {'R', 't' (unit), 'inliers' (bool mask over the matches), 'num_inliers'}.
    """
    pts1 = np.asarray(pts1, np.float64).reshape(-1, 2)
    pts2 = np.asarray(pts2, np.float64).reshape(-1, 2)
    if len(pts1) < 5:
        return None
    if estimator == "pycolmap":
        import pycolmap

        options = pycolmap.RANSACOptions()
        options.max_error = threshold_px
        options.confidence = confidence
        options.random_seed = seed
        out = pycolmap.estimate_essential_matrix(pts1, pts2, camera1, camera2, options)
        if out is None:
            return None
        pose = out["cam2_from_cam1"]
        inliers = np.asarray(out["inlier_mask"], bool).ravel()
        return {
            "R": pose.rotation.matrix(),
            "t": np.asarray(pose.translation, float),
            "inliers": inliers,
            "num_inliers": int(inliers.sum()),
        }
    if estimator != "cv2":
        raise ValueError(f"unknown estimator {estimator!r}: cv2 or pycolmap")
    k1, k2 = normalize_points(camera1, pts1), normalize_points(camera2, pts2)
    thr = threshold_px / mean_focal(camera1, camera2)
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(
        k1, k2, np.eye(3), threshold=thr, prob=confidence, method=cv2.RANSAC
    )
    if E is None or mask is None:
        return None
    best = None
    for i in range(len(E) // 3):
        n, R, t, pose_mask = cv2.recoverPose(
            E[3 * i : 3 * i + 3], k1, k2, np.eye(3), 1e9, mask=mask.copy()
        )
        if best is None or n > best[0]:
            best = (n, R, t.ravel(), pose_mask.ravel() > 0)
    if best is None:
        return None
    return {"R": best[1], "t": best[2], "inliers": best[3], "num_inliers": int(best[0])}


# ------------------------------------------------------------------------------------------- WxBS
def _homogeneous(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64).reshape(-1, 2)
    return np.concatenate([x, np.ones((len(x), 1))], 1)


def symmetric_epipolar_distance(x1: np.ndarray, x2: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Per correspondence sqrt((d(x2, F x1)^2 + d(x1, F^T x2)^2) / 2), in the points' units.

    d(x, l) is the distance of point x to line l. This is Hartley & Zisserman's symmetric epipolar
    distance (eq. 11.10, a sum of squares) turned into a length: the RMS of the two point-line
    distances.
    """
    h1, h2 = _homogeneous(x1), _homogeneous(x2)
    l2 = h1 @ np.asarray(F, float).T  # lines in image 2: F x1
    l1 = h2 @ np.asarray(F, float)  # lines in image 1: F^T x2
    num = np.abs(np.sum(h2 * l2, 1))
    d2 = num / np.maximum(np.hypot(l2[:, 0], l2[:, 1]), 1e-12)
    d1 = num / np.maximum(np.hypot(l1[:, 0], l1[:, 1]), 1e-12)
    return np.sqrt((d1**2 + d2**2) / 2.0)


def homography_transfer_error(x1: np.ndarray, x2: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Per correspondence mean of ||H x1 - x2|| and ||H^-1 x2 - x1|| (symmetric transfer
    error, px)."""
    H = np.asarray(H, float)
    x1, x2 = (np.asarray(x, np.float64).reshape(-1, 2) for x in (x1, x2))
    with np.errstate(divide="ignore", invalid="ignore"):
        e2 = np.linalg.norm(apply_h(H, x1) - x2, axis=1)
        e1 = np.linalg.norm(apply_h(np.linalg.inv(H), x2) - x1, axis=1)
    err = (e1 + e2) / 2.0
    return np.where(np.isfinite(err), err, np.inf)


def estimate_geometry(
    pts1: np.ndarray,
    pts2: np.ndarray,
    geometry: str = "F",
    threshold_px: float = 1.0,
    confidence: float = 0.999,
    max_iters: int = 10000,
    seed: int = 0,
) -> dict | None:
    """Fundamental matrix ('F', >= 8 matches) or homography ('H', >= 4) with OpenCV's MAGSAC++
    (USAC)."""
    pts1 = np.ascontiguousarray(np.asarray(pts1, np.float64).reshape(-1, 2))
    pts2 = np.ascontiguousarray(np.asarray(pts2, np.float64).reshape(-1, 2))
    cv2.setRNGSeed(seed)
    if geometry not in ("F", "H"):
        raise ValueError(f"geometry must be 'F' or 'H', got {geometry!r}")
    if len(pts1) < (8 if geometry == "F" else 4):
        return None
    try:
        if geometry == "F":
            M, mask = cv2.findFundamentalMat(
                pts1, pts2, cv2.USAC_MAGSAC, threshold_px, confidence, max_iters
            )
        else:
            M, mask = cv2.findHomography(
                pts1, pts2, cv2.USAC_MAGSAC, threshold_px, maxIters=max_iters, confidence=confidence
            )
    except cv2.error:  # OpenCV 5 asserts on degenerate samples instead of returning no model
        return None
    if M is None or mask is None or M.shape != (3, 3):
        return None
    return {"M": M, "inliers": mask.ravel() > 0, "num_inliers": int((mask.ravel() > 0).sum())}


def geometry_errors(corrs: np.ndarray, M: np.ndarray | None, geometry: str = "F") -> np.ndarray:
    """Errors (px) of the hand-labelled correspondences (N, 4) under an estimated geometry
    (inf if None)."""
    corrs = np.asarray(corrs, np.float64).reshape(-1, 4)
    if M is None:
        return np.full(len(corrs), np.inf)
    if geometry == "F":
        return symmetric_epipolar_distance(corrs[:, :2], corrs[:, 2:], M)
    return homography_transfer_error(corrs[:, :2], corrs[:, 2:], M)


def share_within(errors: np.ndarray, thresholds=WXBS_THRESHOLDS) -> list[float]:
    """Share of errors strictly below each threshold (0 for an empty list)."""
    errors = np.asarray(errors, float).ravel()
    if len(errors) == 0:
        return [0.0 for _ in thresholds]
    return [float(np.mean(errors < thr)) for thr in thresholds]
