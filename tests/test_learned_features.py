"""ALIKED features (paper §4.4): extraction, the database as pycolmap stores them, matching and mapping on them."""

import subprocess
import sys

import numpy as np
import pycolmap
import pytest
import torch

from colmap_guided import database as dbio
from colmap_guided import learned_features as lf
from colmap_guided.features import extract_features
from colmap_guided.reconstruct import reconstruct


@pytest.fixture(scope="module")
def aliked():
    try:
        path = lf.weights_path(lf.default_conf)
    except FileNotFoundError as err:
        pytest.skip(str(err))
    model, device = lf.load_model({**lf.default_conf, "weights": str(path), "device": "cpu"})
    return model, device, path


def test_extraction_keypoints_inside_unit_descriptors_deterministic(aliked, synthetic_scene):
    model, device, _ = aliked
    conf = {**lf.default_conf, "max_num_keypoints": 500}
    path = synthetic_scene.image_dir / synthetic_scene.names[0]
    kp, desc = lf.extract_image(model, device, path, conf)
    kp2, desc2 = lf.extract_image(model, device, path, conf)
    width, height = pycolmap.Bitmap.read(str(path), False).width, pycolmap.Bitmap.read(str(path), False).height
    assert 100 < len(kp) <= 500 and kp.shape[1] == 6 and desc.shape == (len(kp), 128) and desc.dtype == np.float32
    assert (kp[:, 0] > 0).all() and (kp[:, 0] < width).all() and (kp[:, 1] > 0).all() and (kp[:, 1] < height).all()
    np.testing.assert_allclose(np.linalg.norm(desc, axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(kp, kp2)
    np.testing.assert_array_equal(desc, desc2)
    assert len(np.unique(np.round(kp[:, :2]), axis=0)) == len(kp)  # NMS: one keypoint per location


def test_deformable_conv_samples_the_shifted_pixel():
    """A deformable conv whose offsets are a constant (dy, dx) equals the plain conv of the shifted image."""
    conv = lf.DeformConv(2, 3)
    torch.nn.init.zeros_(conv.offset_conv.weight)
    with torch.no_grad():
        conv.offset_conv.bias.copy_(torch.tensor([1.0, 2.0] * 9))  # every tap moved 1 down, 2 right
    x = torch.randn(1, 2, 12, 16)
    out = conv(x)
    shifted = torch.nn.functional.pad(x[..., 1:, 2:], (0, 2, 0, 1))
    ref = torch.nn.functional.conv2d(shifted, conv.regular_conv.weight, padding=1)
    torch.testing.assert_close(out[..., 1:-2, 1:-3], ref[..., 1:-2, 1:-3], atol=1e-5, rtol=1e-5)


def test_database_holds_aliked_as_pycolmap_does(aliked, synthetic_scene, tmp_path):
    _, _, path = aliked
    db_path = tmp_path / "database.db"
    names = synthetic_scene.names[:2]
    out = extract_features(db_path, synthetic_scene.image_dir, names, {"type": "aliked", "aliked": {"weights": str(path), "max_num_keypoints": 300}})
    assert out["num_extracted"] == 2 and not out["skipped"]
    model, device = lf.load_model({**lf.default_conf, "weights": str(path), "max_num_keypoints": 300})
    with dbio.open_database(db_path) as db:
        images = dbio.images_by_name(db)
        assert sorted(images) == sorted(names) and db.num_cameras() >= 1
        for name in names:
            image = images[name]
            stored = db.read_descriptors(image.image_id)
            assert stored.type == pycolmap.FeatureExtractorType.ALIKED_N16ROT
            assert stored.data.dtype == np.uint8 and stored.data.shape[1] == 128 * 4  # float32 bytes, as COLMAP's extractor
            kp, desc = lf.extract_image(model, device, synthetic_scene.image_dir / name, {**lf.default_conf, "max_num_keypoints": 300})
            np.testing.assert_array_equal(stored.to_float().data, desc)
            np.testing.assert_array_equal(np.asarray(db.read_keypoints(image.image_id)), kp)
            data = dbio.read_image_data(db, image, synthetic_scene.image_dir)
            assert data.descriptors.dtype == np.float32 and data.descriptors.shape == (len(kp), 128)
    # A second run finds everything done; SIFT into the same database is refused.
    assert extract_features(db_path, synthetic_scene.image_dir, names, {"type": "aliked", "aliked": {"weights": str(path)}})["num_extracted"] == 0
    with pytest.raises(dbio.DatabaseError, match="ALIKED_N16ROT features"):
        extract_features(db_path, synthetic_scene.image_dir, names, {"type": "sift"})


@pytest.mark.parametrize("matcher", ["raw", "guided"])
def test_reconstruct_with_aliked_registers_the_synthetic_scene(aliked, synthetic_scene, tmp_path, matcher):
    _, _, path = aliked
    result = reconstruct(synthetic_scene.image_dir.parent, output=tmp_path / matcher, matcher=matcher, feature_conf={"type": "aliked", "aliked": {"weights": str(path)}})
    assert result["num_registered"] == len(synthetic_scene.names) == 8
    assert result["options"]["features"]["type"] == "aliked"
    assert result["mean_reprojection_error"] < 1.5


def test_colmap_guided_matcher_refuses_aliked_in_one_line(aliked, synthetic_scene, tmp_path):
    _, _, path = aliked
    with pytest.raises(ValueError, match="SIFT"):
        reconstruct(synthetic_scene.image_dir.parent, output=tmp_path / "gc", matcher="guided_colmap", feature_conf={"type": "aliked", "aliked": {"weights": str(path), "max_num_keypoints": 200}})


def test_bad_weights_path_is_one_line_before_any_work(synthetic_scene, tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "colmap_guided", "reconstruct", str(synthetic_scene.image_dir.parent), "--output", str(out), "--features", "aliked", "--aliked_weights", str(tmp_path / "nope.pth")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "ALIKED weights not found" in lines[0] and "--aliked_weights" in lines[0], proc.stderr
    assert not out.exists()
    not_weights = tmp_path / "bad.pth"
    not_weights.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="not an ALIKED weights file"):
        lf.load_model({**lf.default_conf, "weights": str(not_weights)})
