"""Filter weights: safetensors round trip, config checks, clear errors."""

import json

import pytest
import torch
from safetensors.torch import save_file

from colmap_guided.coarse import (
    CoarseMatcher,
    CoarseNet,
    load_filter_weights,
    read_filter_weights,
    save_filter_weights,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def make_net(**conf):
    return CoarseNet({"pretrained": False, **conf})


def test_round_trip(tmp_path):
    torch.manual_seed(0)
    net = make_net()
    path = save_filter_weights(
        net,
        tmp_path / "f.safetensors",
        resize_max=400,
        training={"loss": "epipolar", "iterations": 7},
    )
    other = make_net()
    config = load_filter_weights(other, path)
    for a, b in zip(net.filter.parameters(), other.filter.parameters()):
        assert torch.equal(a, b)
    assert (
        config["backbone"] == "efficientnet-lite0"
        and config["layer"] == "_blocks.10"
        and config["feature_channels"] == 112
    )
    assert (
        config["channels"] == [16, 16, 1]
        and config["kernel_sizes"] == [3, 3, 3]
        and config["resize_max"] == 400
    )
    assert config["training"] == {"loss": "epipolar", "iterations": 7}


def test_mismatch_is_a_clear_error(tmp_path):
    path = save_filter_weights(make_net(), tmp_path / "f.safetensors", resize_max=400)
    with pytest.raises(ValueError, match="channels: weights \\[16, 16, 1\\] vs network \\[8, 1\\]"):
        load_filter_weights(make_net(channels=(8, 1), kernel_sizes=(3, 3)), path)
    with pytest.raises(ValueError, match="mutual_after"):
        load_filter_weights(make_net(mutual_after=False), path)
    with pytest.raises(
        ValueError, match="backbone: weights 'efficientnet-lite0' vs network 'resnet101'"
    ):
        load_filter_weights(make_net(backbone="resnet101"), path)


def test_missing_and_foreign_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="mode='raw'"):
        read_filter_weights(tmp_path / "absent.safetensors")
    with pytest.raises(FileNotFoundError):
        CoarseMatcher({"mode": "filter", "weights": tmp_path / "absent.safetensors"})
    save_file({"x": torch.zeros(1)}, str(tmp_path / "plain.safetensors"))
    with pytest.raises(ValueError, match="no coarse-filter config"):
        read_filter_weights(tmp_path / "plain.safetensors")
    save_file(
        {"x": torch.zeros(1)},
        str(tmp_path / "old.safetensors"),
        metadata={"config": json.dumps({"format": "v0"})},
    )
    with pytest.raises(ValueError, match="re-export"):
        read_filter_weights(tmp_path / "old.safetensors")
    (tmp_path / "junk.safetensors").write_bytes(b"not a tensor file")
    with pytest.raises(ValueError, match="not a readable safetensors file"):
        read_filter_weights(tmp_path / "junk.safetensors")


def test_matcher_loads_filter_weights(tmp_path):
    torch.manual_seed(1)
    net = make_net()
    path = save_filter_weights(net, tmp_path / "f.safetensors", resize_max=512)
    cm = CoarseMatcher({"mode": "filter", "weights": path, "device": "cpu"})
    assert cm.impl == "sparse" and cm.weights_config["resize_max"] == 512
    assert torch.equal(cm.net.filter.weights[1], net.filter.weights[1])
    with pytest.raises(ValueError, match="trained on efficientnet-lite0"):
        CoarseMatcher({"mode": "filter", "weights": path, "backbone": "resnet101"})


def test_raw_net_has_no_filter_to_save(tmp_path):
    with pytest.raises(ValueError, match="raw mode"):
        save_filter_weights(make_net(filter=False), tmp_path / "f.safetensors", resize_max=512)


@pytest.mark.parametrize(
    "name", ["coarse_filter.safetensors", "coarse_filter_permissive.safetensors"]
)
def test_shipped_weights_load_and_record_their_training(name):
    """Both shipped filters load for the default backbone; the permissive one was trained only on
    the permissively licensed scenes, and neither saw the held-out evaluation scenes."""
    from colmap_guided.coarse import DEFAULT_WEIGHTS
    from colmap_guided.train.scenes import PERMISSIVE_SCENES, VAL_SCENES

    path = DEFAULT_WEIGHTS.parent / name
    matcher = CoarseMatcher({"weights": str(path), "device": "cpu"})
    training = matcher.weights_config["training"]
    assert matcher.weights_config["backbone"] == CoarseMatcher.default_conf["backbone"]
    assert training["supervision"] == "epipolar" and training["iterations"] == 440
    assert not set(training["train_scenes"]) & set(VAL_SCENES)
    if "permissive" in name:
        assert sorted(training["train_scenes"]) == sorted(PERMISSIVE_SCENES)


def test_every_file_of_the_package_data_folders_is_installed():
    """The model card, the weights and the training curve it shows, and the report page's script and
    style sheet, are package data (a wheel has them)."""
    from fnmatch import fnmatchcase

    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

    from colmap_guided.paths import REPO_ROOT

    globs = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]["colmap_guided"]
    package = REPO_ROOT / "colmap_guided"
    folders = (package / "weights", package / "assets")
    files = [
        p.relative_to(package).as_posix()
        for f in folders
        for p in f.iterdir()
        if p.is_file() and not p.name.startswith(".")
    ]
    assert "coarse_filter_curves.png" in (package / "weights" / "MODEL_CARD.md").read_text()
    assert [f for f in files if not any(fnmatchcase(f, g) for g in globs)] == []


def test_a_finetuned_backbone_travels_with_its_filter(tmp_path):
    """`train --finetune_backbone` exports the backbone's feature layers with the filter and loading
    applies them; a filter without them leaves the backbone as built; the pipeline's feature cache
    tells them apart."""
    torch.manual_seed(0)
    tuned = make_net()
    with torch.no_grad():
        for p in tuned.backbone.parameters():
            p.add_(0.05 * torch.randn_like(p))
    path = save_filter_weights(tuned, tmp_path / "tuned.safetensors", resize_max=512, backbone=True)
    plain = save_filter_weights(tuned, tmp_path / "plain.safetensors", resize_max=512)
    tensors, _ = read_filter_weights(path)
    stored = {k for k in tensors if k.startswith("backbone.")}
    assert (
        "backbone._blocks.10._project_conv.weight" in stored
        and "backbone._blocks.11._project_conv.weight" not in stored
    )
    # the classifier is not used
    assert not {"backbone._fc.weight", "backbone._conv_head.weight"} & stored

    x = torch.rand(1, 3, 64, 96) * 255
    loaded = make_net()
    load_filter_weights(loaded, path)
    assert torch.equal(
        loaded.extract_features(loaded.normalize(x)), tuned.extract_features(tuned.normalize(x))
    )
    untouched = make_net()
    before = {k: v.clone() for k, v in untouched.backbone.state_dict().items()}
    load_filter_weights(untouched, plain)
    assert all(torch.equal(before[k], v) for k, v in untouched.backbone.state_dict().items())

    image = (torch.rand(80, 112, 3) * 255).to(torch.uint8).numpy()
    cache = tmp_path / "coarse.h5"
    imagenet = CoarseMatcher({"weights": plain, "device": "cpu", "cache_path": cache})
    finetuned = CoarseMatcher({"weights": path, "device": "cpu", "cache_path": cache})
    assert imagenet.features_key != finetuned.features_key
    a = imagenet.extract(image, "photo.jpg").features
    b = finetuned.extract(image, "photo.jpg").features  # not imagenet's cached features
    assert not torch.allclose(a, b)
    assert torch.equal(
        CoarseMatcher({"weights": path, "device": "cpu", "cache_path": cache})
        .extract(None, "photo.jpg")
        .features,
        b,
    )
    with pytest.raises(ValueError, match="carry the backbone they were trained with"):
        CoarseMatcher(
            {"weights": path, "device": "cpu", "backbone_weights": tmp_path / "other.pth"}
        )
