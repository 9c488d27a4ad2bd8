"""Photos placed on cheap or thin evidence, checked before they count.

A cheap decision keeps a pair's matches without the full matcher where they verify with many inliers
(``escalate.KEEPS``); on a damaged print such matches can verify and still pull the photo to a wrong
pose, and a photo that observes few 3D points rests on little. After mapping, such a photo (its
pairs with its model's photos all kept cheaply, or fewer than ``check_points`` 3D points observed)
gets its ``check_pairs`` most similar pairs with the model's photos that the full matcher did not
match (kept cheaply, deferred or gated) matched by the full matcher, and its pose is estimated again
from the model's 3D points that the full matcher's matches reach. It keeps its place only where the
two poses agree; elsewhere it is taken out of the model, and escalation's mapping, continued on the
full matcher's matches, may place it again.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from . import database as dbio
from .escalate import read_kept
from .image_data import PairKey
from .log import colmap_quiet, logger
from .mapping import registered

# Two poses of a photo are one where they differ by less than this rotation and their centres by
# less than this fraction of the photo's median depth (the evaluation's bounds of a correct pose).
MAX_ROTATION_DEG = 5.0
MAX_CENTER_FRAC = 0.1
# what the report adds to the reason of a photo the check took out and mapping did not place again
TAKEN_OUT = " Mapping placed it ({why}), but the full matcher's matches did not confirm that pose."


def to_check(
    rec: pycolmap.Reconstruction, verified, ids: dict, kept: set[frozenset], min_points: int
) -> dict:
    """{name: why} of the model's photos that the check takes: every ``verified`` pair (database
    ids; ``ids``: name -> id) with another photo of the model kept by a cheap decision (``kept``),
    or fewer than ``min_points`` 3D points observed."""
    names = {rec.images[i].name: i for i in rec.reg_image_ids()}
    by_id = {ids[name]: name for name in names}
    partners: dict[str, list[str]] = {name: [] for name in names}
    for a, b in verified:
        if a in by_id and b in by_id:
            partners[by_id[a]].append(by_id[b])
            partners[by_id[b]].append(by_id[a])
    why = {}
    for name, image_id in names.items():
        if partners[name] and all(frozenset((name, o)) in kept for o in partners[name]):
            why[name] = "placed through cheaply kept pairs only"
        elif rec.images[image_id].num_points3D < min_points:
            why[name] = f"observes {rec.images[image_id].num_points3D} 3D points"
    return why


def pairs_to_check(
    name: str, model: set[str], selected, db, ids: dict, kept: set[frozenset], num: int
) -> list[PairKey]:
    """The photo's ``num`` most similar ``selected`` pairs with other photos of the ``model`` that
    the full matcher did not match: kept cheaply or not matched at all."""
    todo = []
    for a, b in selected:
        other = b if a == name else a if b == name else None
        if other is None or other not in model:
            continue
        if frozenset((a, b)) in kept or not dbio.pair_has_matches(db, ids[a], ids[b]):
            todo.append((ids[a], ids[b], a, b))
            if len(todo) == num:
                break
    return todo


def pose_again(
    rec: pycolmap.Reconstruction, image_id: int, db, ids: dict, min_inliers: int, kept=frozenset()
):
    """The photo's pose from its verified matches with the model's other photos (not those of
    pairs ``kept`` by a cheap decision: the full matcher's only) that reach the model's 3D points:
    those seen by two photos besides it (independent of its own pose), or, where they are fewer
    than ``min_inliers``, by one. Returns (cam_from_world, the 3D points of the 2D-3D inliers,
    their number), or None when fewer than ``min_inliers`` agree. ``ids``: database image id by
    name."""
    image = rec.images[image_id]
    keypoints = dbio.read_keypoints(db, ids[image.name])[:, :2].astype(np.float64)
    found: dict[int, tuple[int, int]] = {}  # keypoint of the photo -> (3D point, other observers)
    for other_id in rec.reg_image_ids():
        name = rec.images[other_id].name
        if other_id == image_id or frozenset((image.name, name)) in kept:
            continue
        geometry = dbio.read_two_view_geometry(db, ids[image.name], ids[name])
        if geometry is None:
            continue
        points2D = rec.images[other_id].points2D
        for k, j in np.asarray(geometry.inlier_matches, np.int64).reshape(-1, 2):
            if k not in found and points2D[j].has_point3D():
                point = points2D[j].point3D_id
                track = rec.points3D[point].track.elements
                found[int(k)] = point, sum(el.image_id != image_id for el in track)
    for observers in (2, 1):
        chosen = [(k, point) for k, (point, n) in found.items() if n >= observers]
        if len(chosen) >= min_inliers:
            break
    else:
        return None
    xy = keypoints[[k for k, _ in chosen]]
    xyz = np.array([rec.points3D[point].xyz for _, point in chosen])
    with colmap_quiet():
        estimate = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, rec.cameras[image.camera_id])
    if estimate is None or estimate["num_inliers"] < min_inliers:
        return None
    inliers = np.asarray(estimate["inlier_mask"], bool)
    return estimate["cam_from_world"], xyz[inliers], int(inliers.sum())


def differences(old: pycolmap.Rigid3d, new: pycolmap.Rigid3d, points: np.ndarray) -> tuple:
    """(rotation in degrees, centre distance as a fraction of the median depth of ``points`` in
    the old pose) between two poses of a photo."""
    r_old, r_new = old.rotation.matrix(), new.rotation.matrix()
    cos = np.clip((np.trace(r_new @ r_old.T) - 1) / 2, -1.0, 1.0)
    centre = lambda pose: -pose.rotation.matrix().T @ pose.translation  # noqa: E731
    depth = abs(np.median((points @ r_old.T + old.translation)[:, 2]))
    return float(np.degrees(np.arccos(cos))), float(
        np.linalg.norm(centre(old) - centre(new)) / max(depth, 1e-12)
    )


def check_models(
    database_path: Path,
    models: dict,
    selected,
    kept_path: Path | None,
    conf: dict,
    rematch,
) -> tuple[set[str], dict]:
    """The check of every model's photos (``to_check``): their pairs (``pairs_to_check``) matched
    by ``rematch(todo)`` (the full matcher), then each photo taken out of its model where its pose
    again (``pose_again``) is missing or differs (``differences``) by ``MAX_ROTATION_DEG`` or
    ``MAX_CENTER_FRAC`` or more. ``conf``: escalation's check_pairs and check_points, and mapping's
    abs_pose_min_num_inliers. Returns the pairs matched (name_a, name_b) and a record for the
    report."""
    record = {"checked": {}, "pairs": 0, "taken_out": {}}
    if not conf["check_pairs"]:
        return set(), record
    kept = read_kept(kept_path)
    with dbio.open_database(database_path) as db:
        ids = {name: image.image_id for name, image in dbio.images_by_name(db).items()}
        verified = dbio.pair_inlier_counts(db)
        checked, todo, matched = {}, [], set()
        for key, rec in models.items():
            model = registered(rec)
            for name, why in to_check(rec, verified, ids, kept, conf["check_points"]).items():
                pairs = pairs_to_check(name, model, selected, db, ids, kept, conf["check_pairs"])
                if pairs:
                    checked[name] = (key, why)
                    todo += [p for p in pairs if p[2:] not in matched]
                    matched.update(p[2:] for p in pairs)
    record.update(checked={name: {"why": why} for name, (_, why) in sorted(checked.items())})
    record["pairs"] = len(todo)
    if not todo:
        return set(), record
    logger.info("Checking %d photo(s) placed on cheap or thin evidence", len(checked))
    rematch(todo)
    kept = read_kept(kept_path)
    with dbio.open_database(database_path) as db:
        for name, (key, why) in checked.items():
            rec = models[key]
            image = next(rec.images[i] for i in rec.reg_image_ids() if rec.images[i].name == name)
            min_inliers = conf["abs_pose_min_num_inliers"]
            again = pose_again(rec, image.image_id, db, ids, min_inliers, kept)
            if again is not None:
                turn, moved = differences(image.cam_from_world(), *again[:2])
                record["checked"][name].update(
                    rotation_deg=round(turn, 3), centre_frac=round(moved, 4), inliers=again[2]
                )
            if again is None or turn >= MAX_ROTATION_DEG or moved >= MAX_CENTER_FRAC:
                record["taken_out"][name] = why
                rec.deregister_frame(image.frame_id)
    logger.info(
        "%d photo(s) taken out: the full matcher's matches put them elsewhere",
        len(record["taken_out"]),
    )
    return matched, record
