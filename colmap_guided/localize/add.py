"""``localize --add``: a new model version, the model with the placed photos registered, their
points triangulated and bundle adjustment run; the model it started from is left as it was."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pycolmap

from .. import database as dbio
from ..log import colmap_quiet, logger
from ..workspace import Workspace
from .pose import correspondences, estimate_pose, verified_pairs
from .results import ADDED, PLACED, db_name


def add_to_model(
    ws: Workspace, rec: pycolmap.Reconstruction, database: Path, results: dict, conf: dict
) -> Path:
    """WORKSPACE/sparse_localized/0: ``rec`` with the placed photos registered (their inlier
    observations join the model's tracks), new points triangulated from their verified matches with
    the model's images, then bundle adjustment. Written whole into a partial folder first, then
    moved in place."""
    new = pycolmap.Reconstruction(rec)
    names = {rec.images[i].name: i for i in rec.reg_image_ids()}
    image_path = Path(
        json.loads((ws.path / "report.json").read_text(encoding="utf-8"))["image_path"]
    )
    model_ids = {db_name(image_path / n): i for n, i in names.items()}
    placed = [e for e in results.values() if e["status"] == PLACED]
    # A trivial rig takes its camera's id, a trivial frame its image's: ids free in both.
    next_camera = max([*new.cameras, *new.rigs], default=0) + 1
    next_image = max([*new.images, *new.frames], default=0) + 1
    with dbio.open_database(database) as db:
        images = dbio.images_by_name(db)
        # not the model's own photos
        photos = {db_name(Path(e["photo"])) for e in placed} - set(model_ids)
        verified = verified_pairs(db, photos, model_ids)
        for name in sorted(photos):
            ids = (next_camera, next_image)
            if _register(new, rec, db, images[name], verified[name], ids, conf):
                _triangulate(new, next_image, verified[name], conf)
                next_camera, next_image = next_camera + 1, next_image + 1
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    with colmap_quiet():
        pycolmap.bundle_adjustment(new, options)
    final = _write(ws, new)
    logger.info(
        "New model version with %d more photo(s): %s (the model itself unchanged).",
        new.num_reg_images() - rec.num_reg_images(),
        final,
    )
    return final


def _register(
    new: pycolmap.Reconstruction,
    rec: pycolmap.Reconstruction,
    db,
    image: pycolmap.Image,
    pairs: list,
    ids: tuple[int, int],
    conf: dict,
) -> bool:
    """``image`` (of localize.db) into ``new`` as camera and image ``ids``, its inlier
    observations joining the tracks of ``rec``'s points; False when no pose fits."""
    corrs, _ = correspondences(rec, pairs)
    camera = dbio.read_camera(db, image.camera_id)
    keypoints = dbio.read_keypoints(db, image.image_id)
    # seeded: the pose of localized.json
    pose = estimate_pose(camera, keypoints, corrs, rec, conf)
    if pose is None:
        return False
    camera.camera_id, image_id = ids
    new.add_camera_with_trivial_rig(camera)
    new.add_image_with_trivial_frame(
        pycolmap.Image(
            name=image.name,
            keypoints=np.ascontiguousarray(keypoints[:, :2], np.float64),
            camera_id=camera.camera_id,
            image_id=image_id,
        ),
        pose["cam_from_world"],
    )
    seen = set()  # a 3D point is observed once per photo, a keypoint sees one 3D point
    for i, point3D_id in pose["inliers"]:
        if point3D_id not in seen and not new.image(image_id).points2D[i].has_point3D():
            new.add_observation(point3D_id, pycolmap.TrackElement(image_id, i))
            seen.add(point3D_id)
    return True


def _write(ws: Workspace, new: pycolmap.Reconstruction) -> Path:
    """``new`` written whole into sparse_localized.partial/0, then moved to sparse_localized/0."""
    partial, final = ws.path / f"{ADDED}.partial", ws.path / ADDED
    for folder in (partial, final):
        if folder.exists():
            ws.remove(folder.name)
    (partial / "0").mkdir(parents=True)
    new.write(str(partial / "0"))
    os.replace(partial, final)
    return final / "0"


def _triangulate(rec: pycolmap.Reconstruction, image_id: int, pairs: list, conf: dict) -> int:
    """New 3D points from the verified matches of ``image_id`` with model images whose keypoints
    have none."""
    image = rec.image(image_id)
    camera = rec.cameras[image.camera_id]
    made = 0
    for other_id, inliers in pairs:
        other = rec.image(other_id)
        other_camera = rec.cameras[other.camera_id]
        poses = (image.cam_from_world(), other.cam_from_world())
        for i, j in inliers:
            i, j = int(i), int(j)
            if image.points2D[i].has_point3D() or other.points2D[j].has_point3D():
                continue
            xy = (image.points2D[i].xy, other.points2D[j].xy)
            rays = (camera.cam_from_img(xy[0]), other_camera.cam_from_img(xy[1]))
            xyz = pycolmap.triangulate_point(poses[0].matrix(), poses[1].matrix(), rays[0], rays[1])
            if xyz is None or not _good_point(
                np.ravel(xyz), poses, (camera, other_camera), xy, conf
            ):
                continue
            rec.add_point3D(
                np.ravel(xyz),
                pycolmap.Track(
                    [pycolmap.TrackElement(image_id, i), pycolmap.TrackElement(other_id, j)]
                ),
            )
            image, other = rec.image(image_id), rec.image(other_id)
            made += 1
    return made


def _good_point(xyz: np.ndarray, poses: tuple, cameras: tuple, xy: tuple, conf: dict) -> bool:
    """In front of both cameras, seen under at least min_tri_angle_deg, reprojected within
    max_tri_error px."""
    centres = [pose.inverse().translation for pose in poses]
    rays = [xyz - c for c in centres]
    cos = rays[0] @ rays[1] / max(np.linalg.norm(rays[0]) * np.linalg.norm(rays[1]), 1e-12)
    if np.degrees(np.arccos(np.clip(cos, -1, 1))) < conf["min_tri_angle_deg"]:
        return False
    for pose, camera, point in zip(poses, cameras, xy):
        cam = pose.rotation.matrix() @ xyz + pose.translation
        if (
            cam[2] <= 0
            or np.linalg.norm(np.asarray(camera.img_from_cam(cam)) - point) > conf["max_tri_error"]
        ):
            return False
    return True
