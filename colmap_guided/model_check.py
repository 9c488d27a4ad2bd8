"""Sanity check of the mapped models: a registered count means nothing if the model is degenerate.

A weak view graph can make COLMAP's mappers "register" photos with impossible cameras (focal lengths
of 10^5-10^7 px, i.e. an orthographic camera that fits any matches) or poses that jump between
photos that see the same points. Each model is checked for:

- focal length outside [min_focal_ratio, max_focal_ratio] x the image's larger side;
- an image whose mean reprojection error exceeds ``max_reprojection_error`` px;
- a pose jump: an image whose viewing direction differs by more than ``max_view_angle_deg`` from
  that of the image it shares the most 3D points with.

The findings go to report.json (``model_check``) and a WARNING line per problem.
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import pycolmap

from .conf import merge_conf

default_conf = {
    # 0.1 x the larger side is a ~160° field of view (a fisheye); 20 x is a 720 mm lens on 35 mm
    # film (a 3° field of view). COLMAP's mappers reject [0.1, 10] while registering; 10-20 x is
    # still a real telephoto. The degenerate models seen had 50-5000 x.
    "min_focal_ratio": 0.1,
    "max_focal_ratio": 20.0,
    # COLMAP drops observations beyond 4 px after bundle adjustment: an image whose mean is larger
    # was not fit.
    "max_reprojection_error": 4.0,
    # SIFT matching does not survive much more than ~60° of viewpoint change, so the best-connected
    # neighbour of a correctly posed photo looks within that angle (the optical axes, so roll is
    # ignored).
    "max_view_angle_deg": 75.0,
    "min_shared_points": 15,  # neighbours sharing fewer 3D points are not compared
}


def implausible_focal(camera: pycolmap.Camera, conf: dict | None = None) -> str | None:
    """The camera's first focal length outside the plausible range, in words; None when all are
    plausible."""
    conf = merge_conf(default_conf, conf, "model check")
    side = max(camera.width, camera.height)
    for f in (camera.params[i] for i in camera.focal_length_idxs()):
        if not conf["min_focal_ratio"] <= f / side <= conf["max_focal_ratio"]:
            plausible = f"{conf['min_focal_ratio']}-{conf['max_focal_ratio']} x"
            return (
                f"focal length {f:.0f} px = {f / side:.3g} x "
                f"the image side (plausible: {plausible})"
            )
    return None


def focal_problems(rec: pycolmap.Reconstruction, conf: dict) -> list[str]:
    problems = []
    used = Counter(rec.images[i].camera_id for i in rec.reg_image_ids())
    for camera_id, count in sorted(used.items()):
        problem = implausible_focal(rec.cameras[camera_id], conf)
        if problem is not None:
            names = sorted(
                rec.images[i].name
                for i in rec.reg_image_ids()
                if rec.images[i].camera_id == camera_id
            )
            more = " ..." if len(names) > 3 else ""
            problems.append(f"{problem} for {', '.join(names[:3])}{more} ({count} image(s))")
    return problems


def reprojection_errors(rec: pycolmap.Reconstruction) -> dict[int, float]:
    """Mean reprojection error (px) of each registered image over its triangulated observations."""
    out = {}
    for image_id in rec.reg_image_ids():
        image = rec.images[image_id]
        obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in image.points2D if p.has_point3D()]
        if not obs:
            continue
        xy = np.array([o[0] for o in obs])
        xyz = np.array([o[1] for o in obs])
        cam_pts = (
            xyz @ image.cam_from_world().rotation.matrix().T + image.cam_from_world().translation
        )
        proj = np.asarray(rec.cameras[image.camera_id].img_from_cam(cam_pts))
        err = np.linalg.norm(proj - xy, axis=1)
        out[image_id] = float(np.nanmean(np.where(cam_pts[:, 2] > 0, err, np.inf)))
    return out


def covisibility(rec: pycolmap.Reconstruction) -> Counter:
    """Shared 3D points of each pair of registered images (image_id_a < image_id_b)."""
    shared = Counter()
    for point in rec.points3D.values():
        ids = sorted({el.image_id for el in point.track.elements})
        for k, a in enumerate(ids):
            for b in ids[k + 1 :]:
                shared[a, b] += 1
    return shared


def pose_jump_problems(rec: pycolmap.Reconstruction, conf: dict) -> list[str]:
    best: dict[int, tuple[int, int]] = {}  # image -> (shared points, neighbour)
    for (a, b), n in covisibility(rec).items():
        if n >= conf["min_shared_points"]:
            for x, y in ((a, b), (b, a)):
                if n > best.get(x, (0, 0))[0]:
                    best[x] = (n, y)
    # optical axis in world
    axis = {i: rec.images[i].cam_from_world().rotation.matrix()[2] for i in rec.reg_image_ids()}
    problems, seen = [], set()
    for image_id, (n, other) in sorted(best.items()):
        angle = float(np.degrees(np.arccos(np.clip(axis[image_id] @ axis[other], -1, 1))))
        if angle > conf["max_view_angle_deg"] and frozenset((image_id, other)) not in seen:
            seen.add(frozenset((image_id, other)))
            problems.append(
                f"pose jump: {rec.images[image_id].name} looks {angle:.0f}° away "
                f"from {rec.images[other].name}, its best-connected neighbour ({n} "
                f"shared points; plausible: <= {conf['max_view_angle_deg']:.0f}°)"
            )
    return problems


def check_model(rec: pycolmap.Reconstruction, conf: dict | None = None) -> list[str]:
    """Problems of one model, one sentence each; [] for a plausible model."""
    conf = merge_conf(default_conf, conf, "model check")
    problems = focal_problems(rec, conf)
    for image_id, err in sorted(reprojection_errors(rec).items()):
        if not err <= conf["max_reprojection_error"]:
            problems.append(
                f"reprojection error {err:.1f} px (plausible: <= "
                f"{conf['max_reprojection_error']} px) in {rec.images[image_id].name}"
            )
    return problems + pose_jump_problems(rec, conf)


def check_each(
    models: dict[int, pycolmap.Reconstruction], conf: dict | None = None
) -> dict[int, list[str]]:
    """Each model's problems ([] for a plausible model), by its index."""
    conf = merge_conf(default_conf, conf, "model check")
    return {index: check_model(rec, conf) for index, rec in sorted(models.items())}


def check_models(
    models: dict[int, pycolmap.Reconstruction],
    conf: dict | None = None,
    each: dict[int, list[str]] | None = None,
) -> dict:
    """``{"ok", "problems", "conf"}`` for report.json; problems are prefixed with the model's folder
    sparse/N. ``each``: ``check_each``'s result, when it was computed already."""
    conf = merge_conf(default_conf, conf, "model check")
    each = check_each(models, conf) if each is None else each
    problems = [f"sparse/{index}: {p}" for index, found in sorted(each.items()) for p in found]
    return {"ok": not problems, "problems": problems, "conf": conf}
