"""SIFT keypoints and descriptors into the COLMAP database: COLMAP's own extractor (pycolmap), with
the same defaults and options as `colmap feature_extractor`.

Archival prints (``stretch_contrast_below``, ``smooth_noise_above``): COLMAP's SIFT peak threshold
is absolute, so a print faded to a narrow grey range loses most detections. Such photos get SIFT
(pycolmap's own extractor, same options) on a prepared grey copy in memory, stretched to the full
range and/or smoothed; the photo file is only read, and keypoints and descriptors are stored exactly
as COLMAP stores SIFT (identical arrays for an unprepared copy at full size), so ``colmap mapper``
and ``match`` read the database as usual.
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from PIL import Image

from .. import database as dbio
from .. import images
from ..database import open_database
from ..log import colmap_quiet, logger, progress
from .cameras import camera_key, import_new, reader_options, skip_unread

# COLMAP's grey conversion (Rec. 709 luma, rounded to 8 bits): its SIFT keypoints are reproduced
# exactly.
GREY_WEIGHTS = np.array([0.2126, 0.7152, 0.0722], np.float32)
# COLMAP's CPU SIFT needs about this many bytes per pixel of the (downscaled) image it works on
# (measured, pycolmap 4.2.1: 3.0 GB peak for one 3200x3200 image, 0.34 GB for 780x1063).
SIFT_BYTES_PER_PIXEL = 300


def _available_memory() -> int | None:
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def extraction_threads(conf: dict, max_pixels: int | None = None) -> int:
    """Extraction threads: COLMAP runs one image per thread, each needing ~300 bytes per SIFT pixel
    (3 GB at the default max_image_size 3200): with 'auto', no more threads than the free memory
    holds."""
    if conf.get("num_threads", "auto") != "auto":
        return int(conf["num_threads"])
    cores = os.cpu_count() or 1
    pixels = max_pixels or conf["max_image_size"] ** 2
    free = _available_memory()
    if free is None:
        return cores
    threads = max(1, min(cores, int(0.8 * free // (SIFT_BYTES_PER_PIXEL * pixels))))
    if threads < cores:
        logger.debug(
            "Extracting with %d thread(s) of %d: %.1f GB free, ~%.1f GB per thread.",
            threads,
            cores,
            free / 1e9,
            SIFT_BYTES_PER_PIXEL * pixels / 1e9,
        )
    return threads


def extraction_options(
    conf: dict, max_pixels: int | None = None
) -> pycolmap.FeatureExtractionOptions:
    options = pycolmap.FeatureExtractionOptions()
    options.max_image_size = conf["max_image_size"]
    options.sift.max_num_features = conf["max_num_features"]
    options.num_threads = extraction_threads(conf, max_pixels)
    return options


def _extract_chunk(
    database_path: Path,
    image_path: Path,
    names: list[str],
    conf: dict,
    existing_camera_id: int | None,
    options: pycolmap.FeatureExtractionOptions,
) -> None:
    """One pycolmap.extract_features call on a few images (onto ``existing_camera_id`` if given)."""
    reader, mode = reader_options(conf, existing_camera_id)
    import_new(database_path, image_path, names, reader, mode)
    try:
        with colmap_quiet():
            dbio.colmap_opening(
                database_path,
                lambda: pycolmap.extract_features(
                    database_path,
                    image_path,
                    image_names=names,
                    camera_mode=mode,
                    reader_options=reader,
                    extraction_options=options,
                ),
            )
    except dbio.DatabaseError:
        raise
    except Exception as err:  # noqa: BLE001 - pycolmap raises RuntimeError/ValueError from C++
        raise RuntimeError(
            f"COLMAP feature extraction failed on {names[0]}... "
            f"({err}); rerun with --verbose to see COLMAP's log."
        ) from err


def noise_level(grey: np.ndarray) -> float:
    """Standard deviation of the noise of a float grey image in [0, 1], in grey levels of 255
    (Immerkaer, "Fast noise variance estimation", CVIU 1996: the mean absolute response to a
    Laplacian difference mask). Measured on the historical proxy: 0.5-2.4 on modern photos, 7-15 on
    grainy prints."""
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    response = cv2.filter2D(np.ascontiguousarray(grey, np.float32), -1, kernel)[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2) * np.mean(np.abs(response)) / 6 * 255) if response.size else 0.0


def sift_grey(path: Path, max_image_size: int) -> np.ndarray:
    """The grey image COLMAP's SIFT works on: float32 in [0, 1] (Rec. 709 luma rounded to 8 bits, as
    COLMAP: the same keypoints and descriptors at full size), the longer side downscaled to
    ``max_image_size``."""
    width, height = images.image_size(path)
    scale = min(1.0, max_image_size / max(width, height))
    # a JPEG 4x SIFT's size or more: decoded reduced
    rgb = images.read_image(path, 2 * max_image_size)
    box = images.decoded_box((width, height), rgb.shape)
    grey = np.empty(rgb.shape[:2], np.uint8)
    for row in range(0, len(grey), 256):  # in bands of rows: no float copy of a large scan
        grey[row : row + 256] = np.round(rgb[row : row + 256].astype(np.float32) @ GREY_WEIGHTS)
    del rgb
    # COLMAP's resampling differs slightly: 2062 vs its 2067 keypoints on a photo at 500 px
    if scale < 1.0:
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        # (a non-JPEG scan 4x SIFT's size or more is box-reduced in float first: Pillow's
        # reducing_gap)
        grey = (
            Image.fromarray(grey)
            .convert("F")
            .resize(size, Image.BILINEAR, box=box, reducing_gap=2.0)
        )
    return np.asarray(grey, np.float32) * np.float32(1 / 255)


def prepared_grey(path: Path, conf: dict) -> tuple[np.ndarray | None, list[str]]:
    """SIFT's grey image of an archival photo prepared for detection (``stretch_contrast_below``,
    ``smooth_noise_above``), and the steps applied; (None, []) when the photo needs none (COLMAP's
    own extraction then)."""
    if conf["stretch_contrast_below"] is None and conf["smooth_noise_above"] is None:
        return None, []
    grey, steps = sift_grey(path, conf["max_image_size"]), []
    if conf["stretch_contrast_below"] is not None:
        low, high = np.percentile(grey, [1, 99])
        if high - low < conf["stretch_contrast_below"]:
            low, high = np.percentile(grey, [0.5, 99.5])
            grey = np.clip((grey - low) / max(high - low, 1 / 255), 0, 1).astype(np.float32)
            steps.append("stretched")
    if conf["smooth_noise_above"] is not None and noise_level(grey) > conf["smooth_noise_above"]:
        grey = cv2.GaussianBlur(grey, (0, 0), 1.0)
        steps.append("smoothed")
    return (grey if steps else None), steps


def _extract_prepared(
    database_path: Path,
    image_path: Path,
    names: list[str],
    conf: dict,
    existing_camera_id: int | None,
    options: pycolmap.FeatureExtractionOptions,
) -> None:
    """SIFT on prepared grey images (``prepared_grey``) through pycolmap's own extractor: cameras
    and images made by COLMAP's reader (as in ``_extract_chunk``), keypoints in the photo's pixels
    and uint8 descriptors stored as COLMAP stores them, so `colmap mapper` reads the database as
    usual."""
    reader, mode = reader_options(conf, existing_camera_id)
    import_new(database_path, image_path, names, reader, mode)
    extractor = pycolmap.FeatureExtractor.create(options)
    with open_database(database_path) as db:
        for name in names:
            image = dbio.read_image(db, name)
            if image is None:
                continue  # COLMAP could not read it: reported by extract_features
            grey, steps = prepared_grey(image_path / name, conf)
            if grey is None:  # cannot happen: chunks are made of prepared photos
                grey = sift_grey(image_path / name, conf["max_image_size"])
            keypoints, descriptors = extractor.extract_from_float32_array(grey)
            camera = dbio.read_camera(db, image.camera_id)
            sx, sy = camera.width / grey.shape[1], camera.height / grey.shape[0]
            if (sx, sy) != (1.0, 1.0):
                for keypoint in keypoints:
                    # COLMAP's FeatureKeypoint::Rescale, as its extractor does
                    keypoint.rescale(sx, sy)
            rows = np.array(
                [(k.x, k.y, k.a11, k.a12, k.a21, k.a22) for k in keypoints], np.float32
            ).reshape(-1, 6)
            with dbio.transaction(db):
                dbio.write_features(db, image.image_id, rows, dbio.descriptor_array(descriptors))
            logger.debug(
                "%s: SIFT on a %s grey image, %d keypoints.",
                name,
                " and ".join(steps),
                len(keypoints),
            )


def _sift_pixels(image_path: Path, names: list[str], conf: dict) -> int | None:
    """Largest number of pixels SIFT works on among ``names`` (each photo downscaled to
    max_image_size)."""
    pixels = []
    for name in names:
        with contextlib.suppress(Exception):
            width, height = images.image_size(Path(image_path) / name)
            scale = min(1.0, conf["max_image_size"] / max(width, height))
            pixels.append(int(width * height * scale * scale))
    return max(pixels) if pixels else None


def _database_cameras(database_path: Path) -> tuple[dict[str, int], dict[str, int]]:
    """Camera ids of the images already extracted and of every image row, by name."""
    if not database_path.exists():
        return {}, {}
    with open_database(database_path) as db:
        done = {
            name: image.camera_id
            for name, image in dbio.images_with_keypoints(db, descriptors=True).items()
        }
        # every image row, extracted or not (a killed run leaves rows import_new wrote)
        rows = {name: image.camera_id for name, image in dbio.images_by_name(db).items()}
    return done, rows


def _camera_keys(
    image_path: Path, todo: list[str], rows: dict[str, int], mode: str
) -> tuple[dict[str, object], dict[object, int]]:
    """Each photo's camera key (None: a camera of its own), and the camera id of each known key."""
    if mode == "per_image":
        return dict.fromkeys(todo), {}
    keys = {name: camera_key(image_path, name, mode) for name in todo}
    known = {}
    if any(key is not None for key in keys.values()):
        # COLMAP's reader does not share a camera with a row it did not write
        for name, camera_id in rows.items():
            known.setdefault(camera_key(image_path, name, mode), camera_id)
        known.pop(None, None)
    return keys, known


def _joins_chunk(name: str, camera_id: int | None, same: bool, prepared, keys, known) -> bool:
    """Whether ``name`` is extracted like the chunk: the same way, onto the same kind of camera."""
    if prepared[name] != same:
        return False
    key = keys[name]
    if camera_id is not None:  # onto a camera already in the database
        return key is not None and known.get(key) == camera_id
    return key is None or key not in known  # COLMAP makes (and shares) the cameras itself


def _chunks(todo: list[str], size: int, prepared: dict[str, bool], keys, known):
    """Runs of at most ``size`` photos and their camera id; ``known`` is read afresh per run."""
    i = 0
    while i < len(todo):
        camera_id, same = known.get(keys[todo[i]]), prepared[todo[i]]
        j = i + 1
        while j < min(len(todo), i + size) and _joins_chunk(
            todo[j], camera_id, same, prepared, keys, known
        ):
            j += 1
        yield todo[i:j], camera_id
        i = j


def _remember_cameras(database_path: Path, run: list[str], keys, known) -> None:
    """Add the cameras COLMAP made for the keyed photos of ``run`` to ``known``."""
    if not any(keys[name] is not None for name in run):
        return
    with open_database(database_path) as db:
        for name in run:
            image = dbio.read_image(db, name) if keys[name] is not None else None
            if image is not None:
                known.setdefault(keys[name], image.camera_id)


def _extract_todo(
    database_path: Path, image_path: Path, todo: list[str], rows: dict[str, int], conf: dict
) -> dict[str, bool]:
    """Extract ``todo`` chunk by chunk; whether each photo got SIFT on a prepared grey copy."""
    keys, known = _camera_keys(image_path, todo, rows, conf["camera_mode"])
    # A few images per pycolmap call (one per thread, twice): the bar moves, and nothing but
    # pycolmap touches the database meanwhile (COLMAP opens it without a busy timeout).
    options = extraction_options(conf, _sift_pixels(image_path, todo, conf))
    prepared = {name: bool(prepared_grey(image_path / name, conf)[1]) for name in todo}
    if any(prepared.values()):
        logger.info(
            "%d photo(s) get SIFT on a contrast-stretched "
            "and/or smoothed grey copy (archival prints).",
            sum(prepared.values()),
        )
    size = max(2, 2 * options.num_threads)
    with progress(desc="extract", unit="img", total=len(todo)) as bar:
        for run, camera_id in _chunks(todo, size, prepared, keys, known):
            # a chunk is extracted one way: COLMAP's, or on prepared grey images
            (_extract_prepared if prepared[run[0]] else _extract_chunk)(
                database_path, image_path, run, conf, camera_id, options
            )
            if camera_id is None:
                _remember_cameras(database_path, run, keys, known)
            bar.update(len(run))
    return prepared


def extract(
    database_path: Path, image_path: Path, image_names: list[str], conf: dict, check: bool = True
) -> dict:
    """SIFT for the ``image_names`` not yet in the database (``conf``: a checked feature conf).
    Photos that COLMAP would have put on a camera already in the database (same folder in
    ``per_folder``, same EXIF camera and size in ``auto``, all in ``single``) are extracted onto
    that camera, so a rerun after a kill gives the same cameras as one uninterrupted run."""
    done, rows = _database_cameras(database_path)
    todo = [name for name in image_names if name not in done]
    skipped: dict[str, str] = {}
    if todo and check:
        todo, skipped = images.check_images(image_path, todo, conf["image_checks"])
    if not done and not todo:
        reasons = "; ".join(f"{name}: {reason}" for name, reason in list(skipped.items())[:3])
        raise ValueError(
            f"None of the {len(image_names)} image(s) in {image_path} can "
            f"be used ({reasons}{' ...' if len(skipped) > 3 else ''})."
        )
    start = time.time()
    prepared: dict[str, bool] = {}
    if todo:
        logger.info(
            "Extracting SIFT for %d images (%d already in the database)", len(todo), len(done)
        )
        prepared = _extract_todo(database_path, image_path, todo, rows, conf)
    with open_database(database_path) as db:
        present = set(dbio.images_with_keypoints(db))
    skip_unread(todo, present, skipped)
    return {
        "num_extracted": sum(name in present for name in todo),
        "prepared": sorted(name for name in todo if name in present and prepared.get(name)),
        "skipped": skipped,
        "time": time.time() - start,
    }
