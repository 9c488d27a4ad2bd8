"""After stage 5: localize new photos in an existing model, without rebuilding it.

    python -m colmap_guided localize WORKSPACE PHOTOS... [--add] [--num_images 10]

"Where was this old photo taken?" For each new photo: retrieval of the model's most similar images
(GeM descriptors of the matcher's backbone, as ``--pairs retrieval``), the workspace's matcher
between the photo and those images (guided, as ``reconstruct`` picks it for the database's
features), COLMAP's two-view verification, 2D-3D correspondences through the model's tracks, then
absolute pose estimation with an unknown focal length (LO-RANSAC + refinement, pycolmap) and a pose
check (inliers, reprojection error, the model check's focal length rule).

The model (WORKSPACE/sparse/0), database.db and the photos are only read. What localize writes in
the workspace, recorded in its marker (so ``reconstruct --overwrite`` removes it):

- ``localize.db``: a COLMAP database with the new photos' keypoints and matches and a copy of the
  keypoints of the model's images they were matched with; image names are absolute paths without the
  leading '/'. A killed run continues from it; photos already in ``localized.json`` are not redone.
- ``localized.json``: one entry per photo: pose, focal length, inliers, matched model images, a
  verdict; in a georeferenced workspace (``georeference``) also latitude, longitude and heading.
- ``localize_pairs.txt``, ``localize_retrieval.npz``: the pairs matched, the model's retrieval
  descriptors.
- ``sparse_localized/0`` with ``--add``: a new model version, the model with the placed photos
  registered, their points triangulated and bundle adjustment run; sparse/0 is left as it was.
- ``report.html`` is written again with a section on the localized photos.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pycolmap

from . import database as dbio
from . import features, geoframe, images, match, model_check
from .conf import merge_conf
from .localized import NOT_PLACED, PLACED, UNCERTAIN
from .log import colmap_quiet, logger
from .matchers import AUTO, get_matcher, resolve_auto
from .matchers.base import scoped_torch_threads
from .pairs import write_pairs
from .workspace import Workspace, model_digest, read_marker

DATABASE = "localize.db"
RESULTS = "localized.json"
PAIRS = "localize_pairs.txt"
RETRIEVAL = "localize_retrieval.npz"
ADDED = "sparse_localized"
WRITES = (
    DATABASE,
    f"{DATABASE}-wal",
    f"{DATABASE}-shm",
    f"{DATABASE}-journal",
    PAIRS,
    RESULTS,
    f"{RESULTS}.partial",
    RETRIEVAL,
    f"{RETRIEVAL}.partial.npz",
    ADDED,
    f"{ADDED}.partial",
)

default_conf = {
    "num_images": 10,  # model images matched with each photo (the retrieval's top k)
    # fewer pose inliers: not placed (the project's mapper registers a photo from 15)
    "min_inliers": 15,
    "placed_inliers": 30,  # fewer: uncertain (COLMAP's mapper registers a photo from 30)
    "max_error": 12.0,  # RANSAC threshold in pixels (COLMAP mapper's abs_pose_max_error)
    # mean over inliers, px
    "max_reprojection_error": model_check.default_conf["max_reprojection_error"],
    "random_seed": 0,  # a rerun gives the same poses
    # Triangulation of new points with --add (COLMAP's triangulator: 1.5° and 4 px).
    "min_tri_angle_deg": 1.5,
    "max_tri_error": 4.0,
}


def db_name(path: Path) -> str:
    """A photo's name in localize.db: its absolute path without the anchor (the database's image
    folder)."""
    path = Path(path).resolve()
    return path.relative_to(path.anchor).as_posix()


def _root() -> Path:
    """localize.db's image folder: the file system's root, so that any photo has a name there."""
    return Path(Path.cwd().resolve().anchor)


def open_workspace(workspace: Path) -> tuple[Path, dict, Path]:
    """(workspace, report.json, sparse/0) of a finished ``reconstruct`` run; one-line errors
    otherwise."""
    path = Path(workspace).expanduser().resolve()
    if not path.is_dir():
        raise FileNotFoundError(
            f"No workspace at {path}: pass the --output folder of a `reconstruct` run."
        )
    marker = read_marker(path)
    if marker is None or marker["kind"] != "reconstruct":
        raise ValueError(
            f"{path} is not a workspace written by "
            "`reconstruct`: pass the --output folder of a run."
        )
    if not (path / "report.json").is_file():
        raise FileNotFoundError(
            f"No report.json in {path}: run `python -m colmap_guided reconstruct` to the end first."
        )
    report = json.loads((path / "report.json").read_text(encoding="utf-8"))
    model_dir = path / "sparse" / "0"
    if not any((model_dir / f"images.{ext}").is_file() for ext in ("bin", "txt")):
        raise ValueError(
            f"{path} holds no model (sparse/0): reconstruct made none to localize photos in."
        )
    return path, report, model_dir


def list_photos(photos: list[Path]) -> tuple[list[Path], dict[str, str]]:
    """(photo files, {given path: why it is left out}); a folder stands for the photos in it."""
    found, bad = [], {}
    for given in photos:
        path = Path(given).expanduser()
        if path.is_dir():
            try:
                found += [(path / name).resolve() for name in features.list_images(path)]
            except FileNotFoundError as err:
                bad[str(given)] = str(err)
        elif path.is_file():
            found.append(path.resolve())
        else:
            bad[str(given)] = "no such file"
    return list(dict.fromkeys(found)), bad


def load_results(path: Path, digest: str) -> dict:
    """localized.json's entries by photo, when they were made against this model (else none)."""
    try:
        saved = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    if saved.get("model_sha256") != digest:
        if saved.get("photos"):
            logger.info(
                "The model changed since %s was written: its %d photo(s) are localized again.",
                path.name,
                len(saved["photos"]),
            )
        return {}
    return {entry["photo"]: entry for entry in saved.get("photos", [])}


def write_results(path: Path, results: dict, header: dict) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(
        json.dumps({**header, "photos": list(results.values())}, indent=1) + "\n", encoding="utf-8"
    )
    os.replace(tmp, path)


def _copy_model_images(src: Path, dst: Path, names: dict[str, str]) -> None:
    """Model images' cameras, keypoints and descriptors from database.db into localize.db
    ({model name: db name}); same keypoint order, so a keypoint's index is its point2D index in the
    model."""
    with dbio.open_database(dst, must_exist=False) as out:
        todo = {m: n for m, n in names.items() if dbio.read_image(out, n) is None}
        if not todo:
            return
        with dbio.open_database(src) as db:
            for model_name, name in todo.items():
                image = dbio.read_image(db, model_name)
                if image is None:
                    raise ValueError(
                        f"{model_name} of the model is not in database.db: "
                        "run reconstruct again (--overwrite)."
                    )
                camera = dbio.read_camera(db, image.camera_id)
                keypoints = dbio.read_keypoints(db, image.image_id)
                descriptors, kind = dbio.read_descriptors(db, image.image_id)
                with dbio.transaction(out):
                    camera.camera_id = dbio.write_camera(out, camera)
                    image_id = dbio.add_image(out, name, camera)
                    dbio.write_features(out, image_id, keypoints, descriptors, kind)


def _retrieve(
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
    root = _root()
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


def _pose_json(camera: pycolmap.Camera, pose: pycolmap.Rigid3d) -> dict:
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


def localize(
    workspace: Path,
    photos: list[Path],
    matcher: str = AUTO,
    matcher_conf: dict | None = None,
    conf: dict | None = None,
    add: bool = False,
) -> dict:
    """Localize ``photos`` (files or folders) in the model of a ``reconstruct`` workspace; returns
    localized.json's content ({"photos": [...], ...}) and, with ``add``, the new model's folder."""
    conf = merge_conf(default_conf, conf, "localize")
    if conf["num_images"] < 1:
        raise ValueError(f"--num_images must be at least 1, got {conf['num_images']}.")
    path, report, model_dir = open_workspace(workspace)
    image_path = Path(report["image_path"])
    rec = pycolmap.Reconstruction(str(model_dir))
    digest = model_digest(model_dir)
    with dbio.open_database(path / "database.db") as db:
        feature_type = features.database_feature_type(db)
    name, _, matcher_conf = resolve_auto(matcher, AUTO, matcher_conf, feature_type)
    chosen = get_matcher(name, matcher_conf)
    features.check_matcher_features(chosen, feature_type)
    files, bad = list_photos(photos)
    for given, reason in bad.items():
        logger.warning("Skipped %s: %s.", given, reason)
    if not files:
        raise FileNotFoundError(
            f"None of the {len(photos)} photo path(s) given is a photo or a folder of photos."
        )
    ws = Workspace.claim(path, "reconstruct", keep=(image_path,))
    ws.record(*WRITES)
    header = {
        "model": str(model_dir),
        "model_sha256": digest,
        "image_path": str(image_path),
        "matcher": chosen.describe(),
    }
    results = load_results(path / RESULTS, digest)
    todo = {
        db_name(p): p
        for p in files
        if str(p) not in results or results[str(p)]["status"] == "skipped"
    }
    if len(todo) < len(files):
        logger.info(
            "%d of %d photo(s) already localized (%s); not redone.",
            len(files) - len(todo),
            len(files),
            RESULTS,
        )
    database = path / DATABASE
    start = time.time()
    if todo:
        feature_conf = {
            **(report.get("options") or {}).get("features", {}),
            "type": feature_type,
            "camera_mode": "per_image",
        }
        model_files = {
            rec.images[i].name: image_path / rec.images[i].name for i in rec.reg_image_ids()
        }
        # A photo that is itself one of the model's images keeps the model's keypoints
        # (not extracted again).
        own = {m: db_name(f) for m, f in model_files.items() if db_name(f) in todo}
        if own:
            _copy_model_images(path / "database.db", database, own)
        root = _root()
        usable, unusable = images.check_images(root, list(todo), feature_conf.get("image_checks"))
        if usable:
            features.extract_features(database, root, usable, feature_conf, check=False)
        for name, reason in unusable.items():
            logger.warning("Skipped %s: %s.", todo[name], reason)
            results[str(todo[name])] = {
                "photo": str(todo[name]),
                "status": "skipped",
                "confidence": f"not placed: {reason}",
            }
        usable = {n: p for n, p in todo.items() if n not in unusable}
        retrieved = _retrieve(chosen, ws, model_files, usable, conf["num_images"]) if usable else {}
        wanted = sorted({m for models in retrieved.values() for m in models})
        _copy_model_images(
            path / "database.db", database, {m: db_name(model_files[m]) for m in wanted}
        )
        pairs = [
            (n, db_name(model_files[m]))
            for n, models in retrieved.items()
            for m in models
            if db_name(model_files[m]) != n
        ]
        if pairs:
            write_pairs(ws.path / PAIRS, pairs)
            match.match_database(database, root, ws.path / PAIRS, chosen)
        model_ids = {db_name(model_files[rec.images[i].name]): i for i in rec.reg_image_ids()}
        # extraction and matching, shared evenly
        elapsed = (time.time() - start) / max(1, len(usable))
        with dbio.open_database(database) as db:
            rows = dbio.images_by_name(db)
            verified = verified_pairs(db, set(usable), model_ids)
            for name, photo in usable.items():
                tic = time.time()
                entry = localize_one(db, rec, rows[name], verified[name], conf)
                entry = {
                    "photo": str(photo),
                    **entry,
                    "time_s": round(elapsed + time.time() - tic, 2),
                }
                results[str(photo)] = entry
                write_results(path / RESULTS, results, header)
                logger.info("%s: %s", photo.name, entry["confidence"])
    geoframe.add_places(path, results.values())
    write_results(path / RESULTS, results, header)
    out = {
        **header,
        "photos": [results[str(p)] for p in files if str(p) in results],
        "skipped": bad,
        "results_path": str(path / RESULTS),
    }
    if add and any(e["status"] == PLACED for e in results.values()):
        out["added_model"] = str(add_to_model(ws, rec, database, results, conf))
    elif add:
        logger.warning("No photo is placed: no new model version written (--add).")
    _rewrite_html(ws)
    return out


def localize_one(
    db, rec: pycolmap.Reconstruction, image: pycolmap.Image, pairs: list, conf: dict
) -> dict:
    """One photo's entry of localized.json (``pairs``: its ``verified_pairs``)."""
    corrs, matched = correspondences(rec, pairs)
    camera = dbio.read_camera(db, image.camera_id)
    pose = None
    if len(corrs) >= max(4, conf["min_inliers"]):
        pose = estimate_pose(camera, dbio.read_keypoints(db, image.image_id), corrs, rec, conf)
    status, words = verdict(len(corrs), matched, pose, camera, conf)
    entry = {
        "status": status,
        "confidence": words,
        "num_correspondences": len(corrs),
        "matched_images": matched,
    }
    if pose is not None:
        entry.update(
            num_inliers=len(pose["inliers"]),
            reprojection_error=round(pose["reprojection_error"], 3),
            **_pose_json(camera, pose["cam_from_world"]),
        )
    return entry


def _rewrite_html(ws: Workspace) -> None:
    """report.html again, with the localized photos (only where reconstruct wrote it)."""
    if not ws.owns("report.html"):
        return
    from .html_report import rewrite_report

    try:
        rewrite_report(ws.path)
    except Exception as err:  # noqa: BLE001
        # localized.json is complete; a failed page must not hide it
        logger.warning("Could not write the HTML report again (%s); %s is complete.", err, RESULTS)


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
            image, pairs = images[name], verified[name]
            corrs, _ = correspondences(rec, pairs)
            camera = dbio.read_camera(db, image.camera_id)
            keypoints = dbio.read_keypoints(db, image.image_id)
            # seeded: the pose of localized.json
            pose = estimate_pose(camera, keypoints, corrs, rec, conf)
            if pose is None:
                continue
            camera.camera_id, image_id = next_camera, next_image
            next_camera, next_image = next_camera + 1, next_image + 1
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
            _triangulate(new, image_id, pairs, conf)
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    with colmap_quiet():
        pycolmap.bundle_adjustment(new, options)
    partial, final = ws.path / f"{ADDED}.partial", ws.path / ADDED
    for folder in (partial, final):
        if folder.exists():
            ws.remove(folder.name)
    (partial / "0").mkdir(parents=True)
    new.write(str(partial / "0"))
    os.replace(partial, final)
    logger.info(
        "New model version with %d more photo(s): %s (sparse/0 unchanged).",
        new.num_reg_images() - rec.num_reg_images(),
        final / "0",
    )
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


def summary_text(out: dict) -> str:
    lines = []
    for entry in out["photos"]:
        extra = (
            f" ({entry['num_inliers']} inliers, focal {entry['focal_length']:.0f} px)"
            if entry.get("num_inliers")
            else ""
        )
        best = entry.get("matched_images") or []
        near = (
            f", nearest model photo {best[0]['image']} ({best[0]['matches']} matches)"
            if best
            else ""
        )
        lines.append(f"{Path(entry['photo']).name}: {entry['confidence']}{extra}{near}")
    lines.extend(
        f"{given}: not placed: {reason}" for given, reason in out.get("skipped", {}).items()
    )
    placed = sum(e["status"] == PLACED for e in out["photos"])
    lines.append(
        f"Placed {placed} of {len(out['photos']) + len(out.get('skipped', {}))} photo(s). "
        f"Results: {out['results_path']}"
    )
    if out.get("added_model"):
        lines.append(f"Model with the placed photos: {out['added_model']}")
    return "\n".join(lines)
