"""``localize``'s run: the photos' features, retrieval and matching in localize.db, then each
photo's pose and verdict into localized.json, the model version with ``--add`` and the report
page."""

from __future__ import annotations

import time
from pathlib import Path

import pycolmap

from .. import database as dbio
from .. import escalate, features, geoframe, images, match
from ..log import logger
from ..pairs import write_pairs
from ..pipeline import MatcherConf
from ..workspace import Workspace, model_digest
from .add import add_to_model
from .pose import correspondences, estimate_pose, pose_json, retrieve, verdict, verified_pairs
from .results import (
    DATABASE,
    PAIRS,
    PLACED,
    RESULTS,
    WRITES,
    copy_model_images,
    db_name,
    image_root,
    list_photos,
    load_results,
    open_workspace,
    write_results,
)


def localize_photos(
    workspace: Path,
    photos: list[Path],
    matcher: str,
    matcher_conf: dict | None,
    conf: dict,
    add: bool,
    model: int = 0,
) -> dict:
    """``localize`` with ``conf`` complete (merged over ``default_conf``), in sparse/``model``."""
    if conf["num_images"] < 1:
        raise ValueError(f"--num_images must be at least 1, got {conf['num_images']}.")
    path, report, model_dir = open_workspace(workspace, model)
    image_path = Path(report["image_path"])
    rec = pycolmap.Reconstruction(str(model_dir))
    digest = model_digest(model_dir)
    chosen, feature_type = _matcher(path, matcher, matcher_conf)
    files, bad = _photo_files(photos)
    ws = Workspace.claim(path, "reconstruct", keep=(image_path,))
    ws.record(*WRITES)
    header = {
        "model": str(model_dir),
        "model_sha256": digest,
        "image_path": str(image_path),
        "matcher": chosen.describe(),
    }
    results = load_results(path / RESULTS, digest)
    todo = _todo(files, results)
    if todo:
        feature_conf = {
            **(report.get("options") or {}).get("features", {}),
            "type": feature_type,
            "camera_mode": "per_image",
        }
        _localize_todo(ws, rec, image_path, chosen, feature_conf, todo, results, header, conf)
    geoframe.add_places(path, results.values(), model)
    write_results(path / RESULTS, results, header)
    out = {
        **header,
        "photos": [results[str(p)] for p in files if str(p) in results],
        "skipped": bad,
        "results_path": str(path / RESULTS),
    }
    if add and any(e["status"] == PLACED for e in results.values()):
        out["added_model"] = str(add_to_model(ws, rec, path / DATABASE, results, conf))
    elif add:
        logger.warning("No photo is placed: no new model version written (--add).")
    _rewrite_html(ws)
    return out


def _matcher(path: Path, matcher: str, matcher_conf: dict | None) -> tuple:
    """(the matcher, database.db's feature type): ``auto`` is the one reconstruct picks for the
    workspace database's features, with its cheap decisions off (no escalation undoes them
    here)."""
    with dbio.open_database(path / "database.db") as db:
        feature_type = features.database_feature_type(db)
    chosen = MatcherConf(matcher, matcher_conf or {}).resolve(feature_type).build()
    chosen = escalate.full_matcher(chosen)
    features.check_matcher_features(chosen, feature_type)
    return chosen, feature_type


def _photo_files(photos: list[Path]) -> tuple[list[Path], dict[str, str]]:
    """``list_photos``, each path left out a warning; none found is a one-line error."""
    files, bad = list_photos(photos)
    for given, reason in bad.items():
        logger.warning("Skipped %s: %s.", given, reason)
    if not files:
        raise FileNotFoundError(
            f"None of the {len(photos)} photo path(s) given is a photo or a folder of photos."
        )
    return files, bad


def _todo(files: list[Path], results: dict) -> dict[str, Path]:
    """{db name: photo} of the photos not in localized.json yet, or skipped there."""
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
    return todo


def _localize_todo(
    ws: Workspace,
    rec: pycolmap.Reconstruction,
    image_path: Path,
    chosen,
    feature_conf: dict,
    todo: dict[str, Path],
    results: dict,
    header: dict,
    conf: dict,
) -> None:
    """Each photo of ``todo`` localized into ``results``; localized.json written after each."""
    start = time.time()
    model_files = {rec.images[i].name: image_path / rec.images[i].name for i in rec.reg_image_ids()}
    usable = _extract(ws.path, model_files, todo, feature_conf, results)
    _match(ws, chosen, model_files, usable, conf["num_images"])
    model_ids = {db_name(model_files[rec.images[i].name]): i for i in rec.reg_image_ids()}
    # extraction and matching, shared evenly
    elapsed = (time.time() - start) / max(1, len(usable))
    with dbio.open_database(ws.path / DATABASE) as db:
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
            write_results(ws.path / RESULTS, results, header)
            logger.info("%s: %s", photo.name, entry["confidence"])


def _extract(
    path: Path,
    model_files: dict[str, Path],
    todo: dict[str, Path],
    feature_conf: dict,
    results: dict,
) -> dict[str, Path]:
    """The usable photos of ``todo``, their features in localize.db; the others skipped in
    ``results``."""
    # A photo that is itself one of the model's images keeps the model's keypoints
    # (not extracted again).
    own = {m: db_name(f) for m, f in model_files.items() if db_name(f) in todo}
    if own:
        copy_model_images(path / "database.db", path / DATABASE, own)
    root = image_root()
    usable, unusable = images.check_images(root, list(todo), feature_conf.get("image_checks"))
    if usable:
        features.extract_features(path / DATABASE, root, usable, feature_conf, check=False)
    for name, reason in unusable.items():
        logger.warning("Skipped %s: %s.", todo[name], reason)
        results[str(todo[name])] = {
            "photo": str(todo[name]),
            "status": "skipped",
            "confidence": f"not placed: {reason}",
        }
    return {n: p for n, p in todo.items() if n not in unusable}


def _match(
    ws: Workspace, chosen, model_files: dict[str, Path], usable: dict[str, Path], k: int
) -> None:
    """``usable`` matched with their ``k`` retrieved model images in localize.db."""
    retrieved = retrieve(chosen, ws, model_files, usable, k) if usable else {}
    wanted = sorted({m for models in retrieved.values() for m in models})
    copy_model_images(
        ws.path / "database.db", ws.path / DATABASE, {m: db_name(model_files[m]) for m in wanted}
    )
    pairs = [
        (n, db_name(model_files[m]))
        for n, models in retrieved.items()
        for m in models
        if db_name(model_files[m]) != n
    ]
    if pairs:
        write_pairs(ws.path / PAIRS, pairs)
        match.match_database(ws.path / DATABASE, image_root(), ws.path / PAIRS, chosen)


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
            **pose_json(camera, pose["cam_from_world"]),
        )
    return entry


def _rewrite_html(ws: Workspace) -> None:
    """report.html again, with the localized photos (only where reconstruct wrote it)."""
    if not ws.owns("report.html"):
        return
    from ..html_report import rewrite_report

    try:
        rewrite_report(ws.path)
    except Exception as err:  # noqa: BLE001
        # localized.json is complete; a failed page must not hide it
        logger.warning("Could not write the HTML report again (%s); %s is complete.", err, RESULTS)


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
