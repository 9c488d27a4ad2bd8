"""Database io: the COLMAP SQLite database read and written through pycolmap only; the only module
that calls ``pycolmap.Database`` (images, cameras, rigs, frames, keypoints, descriptors, matches,
two-view geometries).

Every write of a pair (matches, then its two-view geometry) is its own transaction, so a run killed
at any moment leaves a database that a rerun continues from (pairs already written are skipped).
"""

from __future__ import annotations

import contextlib
import sqlite3
from pathlib import Path
from typing import Callable, Iterator, TypeVar

import numpy as np
import pycolmap

from .image_data import ImageData


class DatabaseError(ValueError):
    """A database that cannot be used as asked; the message says what to do."""


COLMAP_TABLES = {"cameras", "images", "keypoints", "descriptors", "matches", "two_view_geometries"}
BUSY_TIMEOUT_S = 30.0  # how long to wait for another program's lock on the database
ANOTHER = "pass another --database_path or a new --output (the file is left as it is)"
# how COLMAP says it could not open the database: its open sets no SQLite busy timeout
COLMAP_OPEN_FAILED = ("database factory", "locked", "busy")
OPEN_TRIES = 10
T = TypeVar("T")


@contextlib.contextmanager
def sqlite_connection(path: Path, read_only: bool = False) -> Iterator[sqlite3.Connection]:
    """A plain SQLite connection to ``path`` whose errors are one line saying what to do."""
    uri = f"{path.resolve().as_uri()}?mode={'ro' if read_only else 'rw'}"  # never creates the file
    try:
        with contextlib.closing(sqlite3.connect(uri, uri=True, timeout=BUSY_TIMEOUT_S)) as conn:
            yield conn
    except sqlite3.Error as err:
        if "locked" in str(err) or "busy" in str(err):
            what = "is locked by another program; close it (COLMAP's GUI, a run) and run again"
        elif isinstance(err, sqlite3.OperationalError):  # cannot open, read-only, I/O
            what = f"cannot be opened as a COLMAP database; {ANOTHER}"
        else:  # not SQLite, or damaged
            what = f"is not a COLMAP database, or a damaged one; {ANOTHER}"
        raise DatabaseError(f"{path} {what} (SQLite: {err}).") from err


def check_database(path: Path) -> None:
    """Refuse a file that is not a COLMAP database (empty, not SQLite, damaged, another program's
    SQLite) without writing to it: pycolmap would add its tables to an empty or foreign file."""
    path = Path(path)
    with sqlite_connection(path, read_only=True) as conn:
        tables = {
            name for (name,) in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")
        }
    if not COLMAP_TABLES <= tables:
        kind = (
            "an empty file"
            if path.stat().st_size == 0
            else "an SQLite file without COLMAP's tables"
        )
        raise DatabaseError(f"{path} is {kind}, not a COLMAP database; {ANOTHER}.")


@contextlib.contextmanager
def open_database(path: Path, must_exist: bool = True) -> Iterator[pycolmap.Database]:
    """The COLMAP database at ``path``, checked first; created when absent unless ``must_exist``."""
    path = Path(path)
    if must_exist and not path.is_file():
        raise DatabaseError(
            f"No COLMAP database at {path}: run `colmap feature_extractor` "
            "(or `python -m colmap_guided reconstruct`) first."
        )
    if path.exists():
        check_database(path)
    try:
        db = colmap_opening(path, lambda: pycolmap.Database.open(str(path)))
    except DatabaseError:
        raise
    except Exception as err:  # pycolmap raises RuntimeError / ValueError for a file it cannot open
        first = str(err).splitlines()[0]
        raise DatabaseError(
            f"{path} is not a readable COLMAP database; {ANOTHER} ({first})."
        ) from err
    try:
        yield db
    finally:
        db.close()


def colmap_opening(path: Path, call: Callable[[], T]) -> T:
    """``call()``, a COLMAP function that opens the database at ``path``, tried again once another
    connection's lock is gone (COLMAP fails at once where SQLite would wait)."""
    for _ in range(OPEN_TRIES - 1):
        try:
            return call()
        except (RuntimeError, ValueError) as err:
            if not path.exists() or not any(word in str(err) for word in COLMAP_OPEN_FAILED):
                raise
            with sqlite_connection(path) as conn:  # waits for the lock, or says why it cannot
                conn.execute("BEGIN IMMEDIATE")
                conn.rollback()
    return call()


@contextlib.contextmanager
def transaction(db: pycolmap.Database) -> Iterator[None]:
    """Writes inside the block are one transaction: all of them are in the database, or none."""
    with pycolmap.DatabaseTransaction(db):
        yield


def images_by_name(db: pycolmap.Database) -> dict[str, pycolmap.Image]:
    return {image.name: image for image in db.read_all_images()}


def image_names(db: pycolmap.Database) -> dict[int, str]:
    """image_id -> name of every image."""
    return {image.image_id: image.name for image in db.read_all_images()}


def images_with_keypoints(
    db: pycolmap.Database, descriptors: bool = False
) -> dict[str, pycolmap.Image]:
    """name -> image of the images whose keypoints (and, with ``descriptors``, descriptors) are
    written."""
    return {
        image.name: image
        for image in db.read_all_images()
        if db.exists_keypoints(image.image_id)
        and (not descriptors or db.exists_descriptors(image.image_id))
    }


def read_image(db: pycolmap.Database, name: str) -> pycolmap.Image | None:
    return db.read_image_with_name(name)


def read_camera(db: pycolmap.Database, camera_id: int) -> pycolmap.Camera:
    return db.read_camera(camera_id)


def write_camera(db: pycolmap.Database, camera: pycolmap.Camera) -> int:
    """Adds ``camera``; returns its new camera_id."""
    return db.write_camera(camera)


def update_camera(db: pycolmap.Database, camera: pycolmap.Camera) -> None:
    db.update_camera(camera)


def add_image(db: pycolmap.Database, name: str, camera: pycolmap.Camera) -> int:
    """A camera's image with its rig (one per camera, shared) and frame, as COLMAP's feature
    extractor writes them."""
    rig = db.read_rig_with_sensor(camera.sensor_id)
    if rig is not None:
        rig_id = rig.rig_id
    else:
        rig = pycolmap.Rig()
        rig.add_ref_sensor(camera.sensor_id)
        rig_id = db.write_rig(rig)
    image_id = db.write_image(pycolmap.Image(name=name, camera_id=camera.camera_id))
    frame = pycolmap.Frame()
    frame.rig_id = rig_id
    frame.add_data_id(db.read_image(image_id).data_id)
    db.write_frame(frame)
    return image_id


def read_keypoints(db: pycolmap.Database, image_id: int) -> np.ndarray:
    """(N, k) float32 keypoints of an image: x, y (COLMAP's pixel convention), then its shape
    columns."""
    keypoints = np.asarray(db.read_keypoints(image_id), np.float32)
    return keypoints.reshape(-1, keypoints.shape[1] if keypoints.ndim == 2 else 2)


def has_keypoints(db: pycolmap.Database, image_id: int) -> bool:
    return db.exists_keypoints(image_id)


def num_keypoints(db: pycolmap.Database, image_id: int) -> int:
    """Keypoints of an image; 0 when none are written."""
    return db.num_keypoints_for_image(image_id) if db.exists_keypoints(image_id) else 0


XFEAT = (
    "XFEAT"  # COLMAP has no XFeat type: its 64 float32 per row are stored untyped, 256 bytes wide
)


def kind_name(descriptors: pycolmap.FeatureDescriptors) -> str:
    """The extractor type's name ('SIFT', 'ALIKED_N16ROT', ...; XFEAT for untyped 256-byte rows)."""
    if (
        descriptors.type == pycolmap.FeatureExtractorType.UNDEFINED
        and np.asarray(descriptors.data).shape[1] == 4 * 64
    ):
        return XFEAT
    return descriptors.type.name


def descriptor_type(db: pycolmap.Database) -> str | None:
    """The extractor type of the database's descriptors (``kind_name``; the first image with
    descriptors tells), None when there are none."""
    for image in db.read_all_images():
        if db.exists_descriptors(image.image_id):
            return kind_name(db.read_descriptors(image.image_id))
    return None


def read_descriptors(db: pycolmap.Database, image_id: int) -> tuple[np.ndarray, str]:
    """(N, D) descriptors (see ``descriptor_array``) and the name of their extractor type
    (``kind_name``)."""
    descriptors = db.read_descriptors(image_id)
    return descriptor_array(descriptors), kind_name(descriptors)


def write_features(
    db: pycolmap.Database,
    image_id: int,
    keypoints: np.ndarray,
    descriptors: np.ndarray | None,
    kind: str = "SIFT",
) -> None:
    """Keypoints (and descriptors of extractor type ``kind``) of an image; call inside
    ``transaction`` when other writes belong with them. Learned descriptors (float32) are stored as
    COLMAP stores its own."""
    db.write_keypoints(image_id, np.ascontiguousarray(keypoints, np.float32))
    if descriptors is None:
        return
    if kind == XFEAT:
        rows = (
            np.ascontiguousarray(descriptors, np.float32)
            .view(np.uint8)
            .reshape(len(descriptors), -1)
        )
        db.write_descriptors(
            image_id, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.UNDEFINED, rows)
        )
        return
    kind = getattr(pycolmap.FeatureExtractorType, kind)
    if descriptors.dtype == np.uint8:
        db.write_descriptors(
            image_id, pycolmap.FeatureDescriptors(kind, np.ascontiguousarray(descriptors))
        )
    else:
        db.write_descriptors(
            image_id,
            pycolmap.FeatureDescriptors.from_float(
                pycolmap.FeatureDescriptorsFloat(
                    kind, np.ascontiguousarray(descriptors, np.float32)
                )
            ),
        )


def replace_features(path: Path, features: dict[int, tuple[np.ndarray, np.ndarray, str]]) -> None:
    """Replace the keypoints and descriptors of images {image_id: (keypoints, descriptors, kind)}
    (COLMAP writes an image's rows once: the old ones are deleted first). Before matching only:
    matches index the keypoints."""
    with sqlite_connection(path) as connection:
        for image_id in features:
            connection.execute("DELETE FROM keypoints WHERE image_id = ?", (image_id,))
            connection.execute("DELETE FROM descriptors WHERE image_id = ?", (image_id,))
        connection.commit()
    with open_database(path) as db, transaction(db):
        for image_id, (keypoints, descriptors, kind) in features.items():
            write_features(db, image_id, keypoints, descriptors, kind)


def check_image_folder(db: pycolmap.Database, image_path: Path) -> None:
    """Refuse a database whose images are not in ``image_path`` (a database of another folder)."""
    database_images = db.read_all_images()
    names = [image.name for image in database_images]
    missing = [name for name in names if not (Path(image_path) / name).is_file()]
    if missing:
        raise DatabaseError(
            f"{len(missing)}/{len(names)} images of the database are not in "
            f"{image_path} (e.g. {missing[0]!r}): pass the --image_path the "
            "database was made from, or --overwrite to start a new database."
        )
    # Same names, other photos (IMG_0001.jpg of another folder): the sizes give it away
    # (header reads only).
    from .images import image_size

    for image in database_images:
        camera = db.read_camera(image.camera_id)
        try:
            size = image_size(Path(image_path) / image.name)
        except Exception:  # noqa: BLE001 - unreadable now: judged by extraction, not here
            continue
        if size != (camera.width, camera.height):
            raise DatabaseError(
                f"{image.name} in {image_path} is {size[0]}x{size[1]} pixels "
                f"but {camera.width}x{camera.height} in the database: the "
                "database was made from other photos; pass the --image_path "
                "it was made from, or --overwrite to start a new database."
            )


def descriptor_array(descriptors: pycolmap.FeatureDescriptors) -> np.ndarray:
    """(N, D) descriptors as their extractor made them: uint8 for SIFT (and untyped databases),
    float32 for learned features (COLMAP stores those as the bytes of float32 rows)."""
    if kind_name(descriptors) == XFEAT:
        data = np.ascontiguousarray(descriptors.data)
        return data.view(np.float32).reshape(len(data), -1)
    if descriptors.type in (
        pycolmap.FeatureExtractorType.SIFT,
        pycolmap.FeatureExtractorType.UNDEFINED,
    ):
        return np.asarray(descriptors.data)
    return np.asarray(descriptors.to_float().data, np.float32)


def check_feature_type(path: Path, expected: str) -> None:
    """Refuse to add features of another kind (``kind_name``) to a database (SIFT and ALIKED cannot
    be matched together)."""
    with open_database(path) as db:
        for image in db.read_all_images():
            if db.exists_descriptors(image.image_id):
                kind = kind_name(db.read_descriptors(image.image_id))
                if kind != expected and {kind, expected} != {"SIFT", "UNDEFINED"}:
                    raise DatabaseError(
                        f"{path} holds {kind} features ({image.name}), not {expected}: "
                        "pass another --output, or --overwrite to start a new database."
                    )
                return


def read_image_data(db: pycolmap.Database, image: pycolmap.Image, image_path: Path) -> ImageData:
    camera = db.read_camera(image.camera_id)
    keypoints = read_keypoints(db, image.image_id)
    descriptors, _ = read_descriptors(db, image.image_id)
    if len(keypoints) != len(descriptors):
        raise DatabaseError(
            f"Image {image.name}: {len(keypoints)} keypoints but {len(descriptors)} "
            "descriptors; rerun feature extraction (--overwrite)."
        )
    return ImageData(
        name=image.name,
        image_id=image.image_id,
        path=(Path(image_path) / image.name).resolve(),
        keypoints=keypoints,
        descriptors=descriptors,
        width=camera.width,
        height=camera.height,
        camera=camera,
    )


def pair_has_matches(db: pycolmap.Database, id_a: int, id_b: int) -> bool:
    return db.exists_matches(id_a, id_b)


def pair_is_verified(db: pycolmap.Database, id_a: int, id_b: int) -> bool:
    return db.exists_two_view_geometry(id_a, id_b)


def read_two_view_geometry(
    db: pycolmap.Database, id_a: int, id_b: int
) -> pycolmap.TwoViewGeometry | None:
    """The pair's two-view geometry (inlier_matches index a's and b's keypoints); None when not
    verified."""
    return (
        db.read_two_view_geometry(id_a, id_b) if db.exists_two_view_geometry(id_a, id_b) else None
    )


def pair_match_counts(db: pycolmap.Database) -> dict[tuple[int, int], int]:
    """(image_id_a, image_id_b) -> number of matches of every matched pair."""
    pair_ids, counts = db.read_num_matches()
    return {_image_pair(p): int(n) for p, n in zip(pair_ids, counts)}


def written_pairs(path: Path) -> list[tuple[int, int]]:
    """(image_id_a, image_id_b) of every pair with a two-view geometry in the database at ``path``:
    matched and verified, with inliers or none (pycolmap reads only those with a geometry)."""
    with sqlite_connection(path, read_only=True) as conn:
        rows = conn.execute("SELECT pair_id FROM two_view_geometries").fetchall()
    return [_image_pair(pair_id) for (pair_id,) in rows]


def pair_inlier_counts(db: pycolmap.Database) -> dict[tuple[int, int], int]:
    """(image_id_a, image_id_b) -> verified inliers of every pair that verified (a pair whose
    geometry holds no inlier is not in it)."""
    pair_ids, counts = db.read_two_view_geometry_num_inliers()
    return {_image_pair(p): int(n) for p, n in zip(pair_ids, counts)}


def _image_pair(pair_id: int) -> tuple[int, int]:
    id_a, id_b = pycolmap.pair_id_to_image_pair(pair_id)
    return int(id_a), int(id_b)


def write_pair_matches(db: pycolmap.Database, id_a: int, id_b: int, matches: np.ndarray) -> None:
    """Write one pair's matches atomically, replacing what was there (so reruns never duplicate)."""
    write_pairs_matches(db, [(id_a, id_b, matches, None)])


def write_pairs_matches(
    db: pycolmap.Database,
    batch: list[tuple[int, int, np.ndarray, pycolmap.TwoViewGeometry | None]],
) -> None:
    """``write_pair_matches`` for a batch of (id_a, id_b, matches, geometry) in one transaction;
    a geometry (None: none yet) is written with its matches, so the pair counts as verified."""
    with pycolmap.DatabaseTransaction(db):
        for id_a, id_b, matches, geometry in batch:
            if db.exists_matches(id_a, id_b):
                db.delete_matches(id_a, id_b)
            if db.exists_two_view_geometry(id_a, id_b):
                db.delete_two_view_geometry(id_a, id_b)
            db.write_matches(
                id_a, id_b, np.ascontiguousarray(matches, dtype=np.uint32).reshape(-1, 2)
            )
            if geometry is not None:
                db.write_two_view_geometry(id_a, id_b, geometry)


def write_pair_geometry(
    db: pycolmap.Database, id_a: int, id_b: int, geometry: pycolmap.TwoViewGeometry
) -> None:
    with pycolmap.DatabaseTransaction(db):
        if db.exists_two_view_geometry(id_a, id_b):
            db.delete_two_view_geometry(id_a, id_b)
        db.write_two_view_geometry(id_a, id_b, geometry)


def delete_pairs(db: pycolmap.Database, id_pairs: list[tuple[int, int]]) -> None:
    """Remove the matches and two-view geometries of ``id_pairs`` (a later match writes them
    anew)."""
    with pycolmap.DatabaseTransaction(db):
        for id_a, id_b in id_pairs:
            if db.exists_matches(id_a, id_b):
                db.delete_matches(id_a, id_b)
            if db.exists_two_view_geometry(id_a, id_b):
                db.delete_two_view_geometry(id_a, id_b)


def clear_matches(db: pycolmap.Database) -> None:
    with pycolmap.DatabaseTransaction(db):
        db.clear_matches()
        db.clear_two_view_geometries()


def read_pair_matches(db: pycolmap.Database, id_a: int, id_b: int) -> np.ndarray:
    """Matches of (id_a, id_b) as indices into a's and b's keypoints, whatever order COLMAP stored
    them in."""
    return np.asarray(db.read_matches(id_a, id_b), np.uint32).reshape(-1, 2)


def read_verified_inliers(
    db: pycolmap.Database, image_ids: set[int] | None = None
) -> dict[tuple[int, int], np.ndarray]:
    """(image_id_a, image_id_b) -> (N, 2) inlier matches (indices into a's and b's keypoints) of
    every verified pair, or of the pairs between ``image_ids``."""
    out = {}
    for pair_id, geometry in zip(*db.read_two_view_geometries()):
        key = _image_pair(pair_id)
        inliers = np.asarray(geometry.inlier_matches, np.int64).reshape(-1, 2)
        if len(inliers) and (image_ids is None or set(key) <= image_ids):
            out[key] = inliers
    return out


def num_verified_pairs(db: pycolmap.Database) -> int:
    """Pairs with inlier matches (COLMAP's count also includes pairs whose verification failed)."""
    _, num_inliers = db.read_two_view_geometry_num_inliers()
    return sum(n > 0 for n in num_inliers)


def remove_orphans(path: Path) -> tuple[int, int]:
    """Remove the cameras and rigs that a killed feature extraction left without images; returns
    (cameras, rigs).

    COLMAP's image reader writes an image's camera and rig before its extractor threads write the
    image, so a kill leaves up to a queue's worth of cameras without images. Removing them (and
    rewinding the id counters to the largest id in use) makes the resumed extraction give the ids an
    uninterrupted run gives. Cameras in a rig that has frames are kept. Call it while no pycolmap
    connection is open.
    """
    path = Path(path)
    if not path.is_file():
        return 0, 0
    check_database(path)
    with sqlite_connection(path) as conn:
        tables = {
            name for (name,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
        }
        if not {"rigs", "rig_sensors", "frames", "cameras", "images", "sqlite_sequence"} <= tables:
            return 0, 0  # a database of an older COLMAP: nothing of this kind to clean
        with conn:
            rigs = [
                r
                for (r,) in conn.execute(
                    "SELECT rig_id FROM rigs WHERE rig_id NOT IN (SELECT rig_id FROM frames)"
                )
            ]
            conn.executemany("DELETE FROM rig_sensors WHERE rig_id = ?", [(r,) for r in rigs])
            conn.executemany("DELETE FROM rigs WHERE rig_id = ?", [(r,) for r in rigs])
            cameras = [
                c
                for (c,) in conn.execute(
                    "SELECT camera_id FROM cameras WHERE camera_id NOT IN (SELECT "
                    "camera_id FROM images) AND camera_id NOT IN (SELECT "
                    "ref_sensor_id FROM rigs WHERE ref_sensor_type = 0) AND camera_id "
                    "NOT IN (SELECT sensor_id FROM rig_sensors WHERE sensor_type = 0)"
                )
            ]
            conn.executemany("DELETE FROM cameras WHERE camera_id = ?", [(c,) for c in cameras])
            if rigs or cameras:
                for table, key in (("rigs", "rig_id"), ("cameras", "camera_id")):
                    conn.execute(
                        "UPDATE sqlite_sequence SET seq = (SELECT "
                        f"COALESCE(MAX({key}), 0) FROM {table}) WHERE name = ?",
                        (table,),
                    )
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
