"""What ``localize`` reads and writes in a workspace: its files, the photos' names in localize.db,
localized.json with each photo's verdict, and for the report the model with the cameras of the
photos it placed."""

from __future__ import annotations

import json
import os
from pathlib import Path

from .. import database as dbio
from .. import features
from ..log import logger
from ..mapping import model_folder
from ..workspace import read_marker

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

PLACED, UNCERTAIN, NOT_PLACED = "placed", "uncertain", "not placed"


def db_name(path: Path) -> str:
    """A photo's name in localize.db: its absolute path without the anchor (the database's image
    folder)."""
    path = Path(path).resolve()
    return path.relative_to(path.anchor).as_posix()


def image_root() -> Path:
    """localize.db's image folder: the file system's root, so that any photo has a name there."""
    return Path(Path.cwd().resolve().anchor)


def open_workspace(workspace: Path, model: int = 0) -> tuple[Path, dict, Path]:
    """(workspace, report.json, sparse/``model``) of a finished ``reconstruct`` run; one-line errors
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
    return path, report, model_folder(path, model)


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


def copy_model_images(src: Path, dst: Path, names: dict[str, str]) -> None:
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
