"""Database io: the COLMAP SQLite database read and written through pycolmap only.

Every write of a pair (matches, then its two-view geometry) is its own transaction, so a run killed at
any moment leaves a database that a rerun continues from (pairs already written are skipped).
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator

import numpy as np
import pycolmap

from .matchers.base import ImageData


class DatabaseError(ValueError):
    """A database that cannot be used as asked; the message says what to do."""


@contextlib.contextmanager
def open_database(path: Path, must_exist: bool = True) -> Iterator[pycolmap.Database]:
    path = Path(path)
    if must_exist and not path.is_file():
        raise DatabaseError(f"No COLMAP database at {path}: run `colmap feature_extractor` (or `python -m colmap_guided reconstruct`) first.")
    try:
        db = pycolmap.Database.open(str(path))
    except Exception as err:  # pycolmap raises RuntimeError / ValueError for a corrupt file
        raise DatabaseError(f"{path} is not a readable COLMAP database ({err}); delete it or pass --overwrite.") from err
    try:
        yield db
    finally:
        db.close()


def images_by_name(db: pycolmap.Database) -> dict[str, pycolmap.Image]:
    return {image.name: image for image in db.read_all_images()}


def check_image_folder(db: pycolmap.Database, image_path: Path) -> None:
    """Refuse a database whose images are not in ``image_path`` (a database of another folder)."""
    database_images = db.read_all_images()
    names = [image.name for image in database_images]
    missing = [name for name in names if not (Path(image_path) / name).is_file()]
    if missing:
        raise DatabaseError(
            f"{len(missing)}/{len(names)} images of the database are not in {image_path} (e.g. {missing[0]!r}): "
            "pass the --image_path the database was made from, or --overwrite to start a new database."
        )
    # Same names, other photos (IMG_0001.jpg of another folder): the sizes give it away (header reads only).
    from .images import image_size

    for image in database_images:
        camera = db.read_camera(image.camera_id)
        try:
            size = image_size(Path(image_path) / image.name)
        except Exception:  # noqa: BLE001 - unreadable now: judged by extraction, not here
            continue
        if size != (camera.width, camera.height):
            raise DatabaseError(
                f"{image.name} in {image_path} is {size[0]}x{size[1]} pixels but {camera.width}x{camera.height} in the database: "
                "the database was made from other photos; pass the --image_path it was made from, or --overwrite to start a new database."
            )


def descriptor_array(descriptors: pycolmap.FeatureDescriptors) -> np.ndarray:
    """(N, D) descriptors as their extractor made them: uint8 for SIFT (and untyped databases), float32
    for learned features (COLMAP stores those as the bytes of float32 rows)."""
    if descriptors.type in (pycolmap.FeatureExtractorType.SIFT, pycolmap.FeatureExtractorType.UNDEFINED):
        return np.asarray(descriptors.data)
    return np.asarray(descriptors.to_float().data, np.float32)


def check_feature_type(path: Path, expected: pycolmap.FeatureExtractorType) -> None:
    """Refuse to add features of another kind to a database (SIFT and ALIKED cannot be matched together)."""
    with open_database(path) as db:
        for image in db.read_all_images():
            if db.exists_descriptors(image.image_id):
                kind = db.read_descriptors(image.image_id).type
                if kind != expected and {kind, expected} != {pycolmap.FeatureExtractorType.SIFT, pycolmap.FeatureExtractorType.UNDEFINED}:
                    raise DatabaseError(f"{path} holds {kind.name} features ({image.name}), not {expected.name}: pass another --output, or --overwrite to start a new database.")
                return


def read_image_data(db: pycolmap.Database, image: pycolmap.Image, image_path: Path) -> ImageData:
    camera = db.read_camera(image.camera_id)
    keypoints = np.asarray(db.read_keypoints(image.image_id), np.float32)
    descriptors = descriptor_array(db.read_descriptors(image.image_id))
    if len(keypoints) != len(descriptors):
        raise DatabaseError(f"Image {image.name}: {len(keypoints)} keypoints but {len(descriptors)} descriptors; rerun feature extraction (--overwrite).")
    return ImageData(
        name=image.name,
        image_id=image.image_id,
        path=(Path(image_path) / image.name).resolve(),
        keypoints=keypoints.reshape(-1, keypoints.shape[1] if keypoints.ndim == 2 else 2),
        descriptors=descriptors,
        width=camera.width,
        height=camera.height,
        camera=camera,
    )


def pair_has_matches(db: pycolmap.Database, id_a: int, id_b: int) -> bool:
    return db.exists_matches(id_a, id_b)


def pair_is_verified(db: pycolmap.Database, id_a: int, id_b: int) -> bool:
    return db.exists_two_view_geometry(id_a, id_b)


def write_pair_matches(db: pycolmap.Database, id_a: int, id_b: int, matches: np.ndarray) -> None:
    """Write one pair's matches atomically, replacing what was there (so reruns never duplicate)."""
    write_pairs_matches(db, [(id_a, id_b, matches)])


def write_pairs_matches(db: pycolmap.Database, batch: list[tuple[int, int, np.ndarray]]) -> None:
    """``write_pair_matches`` for a batch of (id_a, id_b, matches) in one transaction."""
    with pycolmap.DatabaseTransaction(db):
        for id_a, id_b, matches in batch:
            if db.exists_matches(id_a, id_b):
                db.delete_matches(id_a, id_b)
            if db.exists_two_view_geometry(id_a, id_b):
                db.delete_two_view_geometry(id_a, id_b)
            db.write_matches(id_a, id_b, np.ascontiguousarray(matches, dtype=np.uint32).reshape(-1, 2))


def write_pair_geometry(db: pycolmap.Database, id_a: int, id_b: int, geometry: pycolmap.TwoViewGeometry) -> None:
    with pycolmap.DatabaseTransaction(db):
        if db.exists_two_view_geometry(id_a, id_b):
            db.delete_two_view_geometry(id_a, id_b)
        db.write_two_view_geometry(id_a, id_b, geometry)


def clear_matches(db: pycolmap.Database) -> None:
    with pycolmap.DatabaseTransaction(db):
        db.clear_matches()
        db.clear_two_view_geometries()


def read_pair_matches(db: pycolmap.Database, id_a: int, id_b: int) -> np.ndarray:
    """Matches of (id_a, id_b) as indices into a's and b's keypoints, whatever order COLMAP stored them in."""
    return np.asarray(db.read_matches(id_a, id_b), np.uint32).reshape(-1, 2)


def num_verified_pairs(db: pycolmap.Database) -> int:
    """Pairs with inlier matches (COLMAP's count also includes pairs whose verification failed)."""
    _, num_inliers = db.read_two_view_geometry_num_inliers()
    return sum(n > 0 for n in num_inliers)


def remove_orphans(path: Path) -> tuple[int, int]:
    """Remove the cameras and rigs that a killed feature extraction left without images; returns (cameras, rigs).

    COLMAP's image reader writes an image's camera and rig before its extractor threads write the image,
    so a kill leaves up to a queue's worth of cameras without images. Removing them (and rewinding the id
    counters to the largest id in use) makes the resumed extraction give the ids an uninterrupted run
    gives. Cameras in a rig that has frames are kept. Call it while no pycolmap connection is open.
    """
    import sqlite3

    path = Path(path)
    if not path.is_file():
        return 0, 0
    with contextlib.closing(sqlite3.connect(str(path), timeout=30.0)) as conn:
        tables = {name for (name,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if not {"rigs", "rig_sensors", "frames", "cameras", "images", "sqlite_sequence"} <= tables:
            return 0, 0  # a database of an older COLMAP: nothing of this kind to clean
        with conn:
            rigs = [r for (r,) in conn.execute("SELECT rig_id FROM rigs WHERE rig_id NOT IN (SELECT rig_id FROM frames)")]
            conn.executemany("DELETE FROM rig_sensors WHERE rig_id = ?", [(r,) for r in rigs])
            conn.executemany("DELETE FROM rigs WHERE rig_id = ?", [(r,) for r in rigs])
            cameras = [
                c
                for (c,) in conn.execute(
                    "SELECT camera_id FROM cameras WHERE camera_id NOT IN (SELECT camera_id FROM images)"
                    " AND camera_id NOT IN (SELECT ref_sensor_id FROM rigs WHERE ref_sensor_type = 0)"
                    " AND camera_id NOT IN (SELECT sensor_id FROM rig_sensors WHERE sensor_type = 0)"
                )
            ]
            conn.executemany("DELETE FROM cameras WHERE camera_id = ?", [(c,) for c in cameras])
            if rigs or cameras:
                for table, key in (("rigs", "rig_id"), ("cameras", "camera_id")):
                    conn.execute(f"UPDATE sqlite_sequence SET seq = (SELECT COALESCE(MAX({key}), 0) FROM {table}) WHERE name = ?", (table,))
    return len(cameras), len(rigs)


def database_summary(db: pycolmap.Database) -> dict:
    return {
        "num_images": db.num_images(),
        "num_cameras": db.num_cameras(),
        "num_keypoints": db.num_keypoints(),
        "num_matched_pairs": db.num_matched_image_pairs(),
        "num_matches": db.num_matches(),
        "num_verified_pairs": num_verified_pairs(db),
        "num_inlier_matches": db.num_inlier_matches(),
    }

