"""One photo's pose in the model: retrieval of the model's most similar images, the verified
matches with them, 2D-3D correspondences through the model's tracks, absolute pose estimation and
the verdict."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pycolmap

from .. import database as dbio
from .. import match, model_check
from ..log import colmap_quiet
from ..matchers.base import scoped_torch_threads
from ..workspace import Workspace
from .results import NOT_PLACED, PLACED, RETRIEVAL, UNCERTAIN, db_name, image_root


def retrieve(
    matcher, workspace: Workspace, model_files: dict[str, Path], photos: dict[str, Path], k: int
) -> dict[str, list[str]]:
    """{photo: its ``k`` most similar model images}; the model's descriptors are kept in
    localize_retrieval.npz."""
    model_names = sorted(model_files)
    if len(model_names) <= k:
        return {name: model_names for name in photos}
    cache = workspace.path / RETRIEVAL
    cached = {}
    if cache.is_file():
        with np.load(cache) as saved:
            cached = dict(zip(saved["names"].tolist(), saved["descriptors"]))
    missing = [n for n in model_names if n not in cached]
    root = image_root()
    with scoped_torch_threads(matcher.torch_threads):  # the backbone as in matching
        if missing:
            computed = match._global_descriptors(
                matcher, root, [db_name(model_files[n]) for n in missing]
            )
            cached.update(zip(missing, computed))
            tmp = workspace.path / f"{RETRIEVAL}.partial.npz"
            np.savez(tmp, names=np.array(list(cached)), descriptors=np.stack(list(cached.values())))
            os.replace(tmp, cache)
        photo_desc = match._global_descriptors(matcher, root, [db_name(p) for p in photos.values()])
    model_desc = np.stack([cached[n] for n in model_names])
    top = np.argsort(-(photo_desc @ model_desc.T), axis=1, kind="stable")[:, :k]
    return {name: [model_names[j] for j in row] for name, row in zip(photos, top)}


def _reprojection_error(
    camera: pycolmap.Camera, cam_from_world: pycolmap.Rigid3d, xy: np.ndarray, xyz: np.ndarray
) -> float:
    cam = xyz @ cam_from_world.rotation.matrix().T + cam_from_world.translation
    proj = np.asarray(camera.img_from_cam(cam))
    return float(np.mean(np.linalg.norm(proj - xy, axis=1))) if len(xy) else float("nan")


def verified_pairs(
    db, photos: set[str], model_ids: dict[str, int]
) -> dict[str, list[tuple[int, np.ndarray]]]:
    """{photo: [(model image_id, (N, 2) verified matches: photo keypoint, model keypoint)]} of
    ``photos`` (names in localize.db) with the model's images ({name in localize.db: image_id in the
    model}), all read in one pass over the database's two-view geometries."""
    rows = dbio.images_by_name(db)
    photo_ids = {rows[n].image_id: n for n in photos if n in rows}
    model = {rows[n].image_id: model_id for n, model_id in model_ids.items() if n in rows}
    out: dict[str, list] = {name: [] for name in photo_ids.values()}
    for (id_a, id_b), inliers in sorted(dbio.read_verified_inliers(db).items()):
        for photo, other, matches in ((id_a, id_b, inliers), (id_b, id_a, inliers[:, ::-1])):
            if photo in photo_ids and other in model and photo != other:
                out[photo_ids[photo]].append((model[other], matches))
                break
    return out


def correspondences(
    rec: pycolmap.Reconstruction, pairs: list[tuple[int, np.ndarray]]
) -> tuple[list, list]:
    """(2D-3D correspondences (keypoint, point3D_id), matched model images [{image, matches,
    points3D}]) of one photo's ``verified_pairs``: a matched keypoint of a model image leads to its
    3D point."""
    matched, corrs = [], {}
    for other, inliers in pairs:
        points2D = rec.images[other].points2D
        found = 0
        for i, j in inliers:
            if points2D[int(j)].has_point3D():
                corrs.setdefault((int(i), points2D[int(j)].point3D_id), None)
                found += 1
        matched.append(
            {"image": rec.images[other].name, "matches": len(inliers), "points3D": found}
        )
    matched.sort(key=lambda m: (-m["matches"], m["image"]))
    return list(corrs), matched


def estimate_pose(
    camera: pycolmap.Camera,
    keypoints: np.ndarray,
    corrs: list,
    rec: pycolmap.Reconstruction,
    conf: dict,
) -> dict | None:
    """Absolute pose (and focal length, unless the photo's EXIF gives it) from 2D-3D
    correspondences; None when no pose fits. ``camera`` is refined in place."""
    xy = np.array([keypoints[i, :2] for i, _ in corrs], np.float64).reshape(-1, 2)
    xyz = np.array([rec.points3D[p].xyz for _, p in corrs], np.float64).reshape(-1, 3)
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.estimate_focal_length = not camera.has_prior_focal_length  # scans of prints: no EXIF
    estimation.ransac.max_error = conf["max_error"]
    estimation.ransac.random_seed = conf["random_seed"]
    refinement = pycolmap.AbsolutePoseRefinementOptions()
    refinement.refine_focal_length = estimation.estimate_focal_length
    refinement.refine_extra_params = estimation.estimate_focal_length
    with colmap_quiet():
        answer = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, camera, estimation, refinement)
    if answer is None:
        return None
    mask = np.asarray(answer["inlier_mask"], bool)
    pose = answer["cam_from_world"]
    return {
        "cam_from_world": pose,
        "inliers": [c for c, keep in zip(corrs, mask) if keep],
        "reprojection_error": _reprojection_error(camera, pose, xy[mask], xyz[mask]),
    }


def verdict(
    num_corrs: int, matched: list, pose: dict | None, camera: pycolmap.Camera, conf: dict
) -> tuple[str, str]:
    """(status, the confidence in words) of one photo."""
    if not matched:
        return NOT_PLACED, "not placed: no image of the model matched"
    if num_corrs < conf["min_inliers"]:
        return NOT_PLACED, f"not placed: only {num_corrs} matches reach the model's 3D points"
    if pose is None:
        return NOT_PLACED, "not placed: no camera pose fits the matches"
    inliers = len(pose["inliers"])
    if inliers < conf["min_inliers"]:
        return NOT_PLACED, f"not placed: {inliers} inliers"
    focal = model_check.implausible_focal(camera)
    if focal is not None:
        return UNCERTAIN, f"uncertain: {focal}"
    if not pose["reprojection_error"] <= conf["max_reprojection_error"]:
        return UNCERTAIN, f"uncertain: reprojection error {pose['reprojection_error']:.1f} px"
    if inliers < conf["placed_inliers"]:
        return UNCERTAIN, f"uncertain: {inliers} inliers"
    return PLACED, PLACED


def pose_json(camera: pycolmap.Camera, pose: pycolmap.Rigid3d) -> dict:
    x, y, z, w = (float(v) for v in pose.rotation.quat)
    return {
        "qvec_wxyz": [w, x, y, z],  # cam_from_world, as in COLMAP's images.txt
        "tvec": [float(v) for v in pose.translation],
        "centre": [float(v) for v in pose.inverse().translation],
        "focal_length": float(camera.mean_focal_length()),
        "camera": {
            "model": camera.model.name,
            "width": camera.width,
            "height": camera.height,
            "params": [float(v) for v in camera.params],
        },
    }
