"""SIFT on archival prints: faded photos get SIFT on a contrast-stretched grey copy, stored as
COLMAP stores SIFT."""

import shutil

import numpy as np
import pycolmap
from PIL import Image

from colmap_guided import features
from colmap_guided.database import open_database
from colmap_guided.features import sift
from colmap_guided.reconstruct import reconstruct

FADED = ("view_000.jpg", "view_002.jpg", "view_004.jpg", "view_006.jpg")


def _faded_scene(synthetic_scene, tmp_path, contrast=0.15):
    """The synthetic scene with half of its photos faded to ``contrast`` of their grey-level spread
    (a print faded to a grey of ~40 levels)."""
    scene = tmp_path / "faded"
    shutil.copytree(synthetic_scene.image_dir, scene / "images")
    for name in FADED:
        rgb = np.asarray(Image.open(scene / "images" / name)).astype(np.float32)
        rgb = 128 + contrast * (rgb - rgb.mean())
        Image.fromarray(np.clip(rgb + 0.5, 0, 255).astype(np.uint8)).save(
            scene / "images" / name, quality=95
        )
    return scene


def _keypoints(database):
    with open_database(database) as db:
        return {image.name: db.read_keypoints(image.image_id) for image in db.read_all_images()}


def test_faded_prints_register_with_the_default_features(synthetic_scene, tmp_path):
    scene = _faded_scene(synthetic_scene, tmp_path)
    features.extract_features(
        tmp_path / "colmap.db", scene / "images", conf={"stretch_contrast_below": None}
    )
    result = reconstruct(scene, matcher="raw")
    plain, ours = _keypoints(tmp_path / "colmap.db"), _keypoints(result["database_path"])
    for (
        name
    ) in FADED:  # COLMAP's absolute peak threshold keeps a few dozen; the stretched copy thousands
        assert len(plain[name]) < 100 and len(ours[name]) > 1000, (
            name,
            len(plain[name]),
            len(ours[name]),
        )
    # photos with a normal contrast keep COLMAP's own extraction
    for name in set(ours) - set(FADED):
        np.testing.assert_array_equal(ours[name], plain[name])
    assert result["num_registered"] == 8
    # The database is COLMAP's: its own mapper (its stricter default thresholds) maps the faded
    # photos too.
    models = pycolmap.incremental_mapping(
        result["database_path"], scene / "images", tmp_path / "sparse"
    )
    largest = max(models.values(), key=lambda m: m.num_reg_images())
    assert sum(image.name in FADED for image in largest.images.values()) >= 3


def test_prepared_extraction_stores_sift_as_colmap_does(synthetic_scene, tmp_path):
    names = ["view_001.jpg", "view_003.jpg"]
    conf = features.check_conf({"num_threads": 1})
    options = sift.extraction_options(conf)
    sift._extract_chunk(
        tmp_path / "colmap.db", synthetic_scene.image_dir, names, conf, None, options
    )
    sift._extract_prepared(
        tmp_path / "ours.db", synthetic_scene.image_dir, names, conf, None, options
    )
    with open_database(tmp_path / "colmap.db") as a, open_database(tmp_path / "ours.db") as b:
        for name in names:
            ia, ib = a.read_image_with_name(name), b.read_image_with_name(name)
            np.testing.assert_array_equal(
                a.read_keypoints(ia.image_id), b.read_keypoints(ib.image_id)
            )
            np.testing.assert_array_equal(
                a.read_descriptors(ia.image_id).data, b.read_descriptors(ib.image_id).data
            )
            assert (
                a.read_camera(ia.camera_id).params.tolist()
                == b.read_camera(ib.camera_id).params.tolist()
            )


def test_noise_level_measures_grain_in_grey_levels():
    rng = np.random.default_rng(0)
    smooth = np.tile(np.linspace(0.2, 0.8, 400, dtype=np.float32), (300, 1))
    assert sift.noise_level(smooth) < 0.5
    for sigma in (3.0, 10.0):
        grainy = smooth + rng.normal(0, sigma / 255, smooth.shape).astype(np.float32)
        assert abs(sift.noise_level(grainy) - sigma) < 0.1 * sigma
