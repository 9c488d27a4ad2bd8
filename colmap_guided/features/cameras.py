"""Cameras and image rows of the feature stage, made by COLMAP's own image reader (all feature
types).

Camera grouping (``camera_mode``):
- ``auto`` (default, as COLMAP): images share a camera when their EXIF make, model and focal length
  and their size agree. Photos without that EXIF (most scans; opensfm_lund) get a camera each, i.e.
  the same as ``per_image`` (checked with pycolmap 4.2.1: 3 lund photos -> 3 cameras); the baseline
  registered 17/29 of opensfm_lund with ``single`` and 2/29 with a camera per image.
- ``single``, ``per_folder`` (one camera per sub-folder: a good choice for mixed archives sorted by
  source), ``per_image`` (every photo its own camera, e.g. scans of prints from unknown cameras).
"""

from __future__ import annotations

import posixpath
from pathlib import Path

import pycolmap
from PIL import Image

from .. import database as dbio
from ..log import colmap_quiet, logger

CAMERA_MODES = {
    "auto": pycolmap.CameraMode.AUTO,
    "single": pycolmap.CameraMode.SINGLE,
    "per_folder": pycolmap.CameraMode.PER_FOLDER,
    "per_image": pycolmap.CameraMode.PER_IMAGE,
}


def camera_key(image_path: Path, name: str, mode: str):
    """Which photos COLMAP's reader puts on one camera: equal keys share it (None: a camera of its
    own)."""
    if mode == "per_image":
        return None
    if mode == "single":
        return ""
    if mode == "per_folder":
        return posixpath.dirname(name)
    # auto: the same EXIF make, model and focal length, and the same size
    # (COLMAP's ExifCameraModel).
    try:
        with Image.open(Path(image_path) / name) as im:
            exif = im.getexif()
            sub = exif.get_ifd(0x8769)
            make, model, focal = (
                exif.get(0x010F),
                exif.get(0x0110),
                sub.get(0xA405) or sub.get(0x920A),
            )
            if make and model and focal:
                return (str(make).strip(), str(model).strip(), float(focal), im.size)
    except Exception:  # noqa: BLE001 - no usable EXIF: a camera of its own, as in COLMAP
        pass
    return None


def reader_options(
    conf: dict, existing_camera_id: int | None = None
) -> tuple[pycolmap.ImageReaderOptions, pycolmap.CameraMode]:
    """COLMAP's image reader options and camera mode (onto ``existing_camera_id`` if given)."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = conf["camera_model"]
    if existing_camera_id is None:
        return reader, CAMERA_MODES[conf["camera_mode"]]
    reader.existing_camera_id = existing_camera_id
    return reader, pycolmap.CameraMode.SINGLE


def import_new(
    database_path: Path,
    image_path: Path,
    names: list[str],
    reader: pycolmap.ImageReaderOptions,
    mode: pycolmap.CameraMode,
) -> None:
    """Write the image rows (and cameras) of the ``names`` not yet in the database, in the order
    given, by COLMAP's own reader (the database is created if needed). COLMAP's extractor reuses
    them; left to it, image ids would follow the order in which its threads finish, and a rerun
    would give another database (other pairs, another model)."""
    with dbio.open_database(database_path, must_exist=False) as db:
        new = [name for name in names if dbio.read_image(db, name) is None]
    if new:
        with colmap_quiet():
            dbio.colmap_opening(
                database_path,
                lambda: pycolmap.import_images(
                    database_path, image_path, mode, image_names=new, options=reader
                ),
            )


def skip_unread(names: list[str], present, skipped: dict[str, str]) -> None:
    """Record in ``skipped`` (and log) each of ``names`` that COLMAP's reader did not bring into
    the database (``present``): the same reason for every feature type."""
    for name in names:
        if name not in present:
            skipped[name] = (
                "COLMAP could not read it (unsupported variant of the format, "
                "or a size that differs from its camera's); convert it to JPEG"
            )
            logger.warning("Skipped %s: %s.", name, skipped[name])
