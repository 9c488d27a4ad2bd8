"""Filter weights on disk: safetensors with a JSON config in the metadata, checked on load.

The config records what the filter was trained with (backbone, its layer and channels, the filter's
channels and kernel sizes, the soft mutual-NN placement, the training resolution) plus free-form
``training`` info (data, loss, iterations, date) for the model card. A filter trained with its
backbone (``train --finetune_backbone``) carries the backbone's feature layers too
(tensors ``backbone.*``), and loading applies them; without them the backbone keeps its ImageNet
weights. Loading weights into a network built differently is a one-line error saying what to change.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from colmap_guided.coarse.backbone import BACKBONES
from colmap_guided.coarse.model import CoarseNet

DEFAULT_WEIGHTS = Path(__file__).resolve().parent.parent / "weights" / "coarse_filter.safetensors"
FORMAT = "colmap_guided.coarse_filter/1"
BACKBONE_PREFIX = "backbone."  # tensors of a fine-tuned backbone's feature layers
# Config keys that must agree between the weights and the network that loads them.
_ARCH_KEYS = (
    "backbone",
    "layer",
    "feature_channels",
    "channels",
    "kernel_sizes",
    "mutual_before",
    "mutual_after",
)


def filter_config(net: CoarseNet, resize_max: int, training: dict | None = None) -> dict:
    """The config stored with ``net``'s filter weights."""
    spec = BACKBONES[net.conf["backbone"]]
    return {
        "format": FORMAT,
        "backbone": spec.name,
        "layer": spec.layer,
        "feature_channels": spec.channels,
        "stride": spec.stride,
        "channels": list(net.conf["channels"]),
        "kernel_sizes": list(net.conf["kernel_sizes"]),
        "mutual_before": bool(net.conf["mutual_before"]),
        "mutual_after": bool(net.conf["mutual_after"]),
        "resize_max": int(resize_max),
        "training": training or {},
    }


def save_filter_weights(
    net: CoarseNet,
    path: str | Path,
    resize_max: int,
    training: dict | None = None,
    backbone: bool = False,
) -> Path:
    """Write ``net``'s filter to ``path`` (.safetensors) with its config; with ``backbone``
    (a fine-tuned one) also the backbone's feature layers."""
    if net.filter is None:
        raise ValueError(
            "This CoarseNet is in raw mode (filter=False): there are no filter weights to save"
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors = dict(net.filter.state_dict())
    if backbone:
        tensors |= {BACKBONE_PREFIX + k: v for k, v in net.backbone.feature_state_dict().items()}
    tensors = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    save_file(
        tensors,
        str(path),
        metadata={"config": json.dumps(filter_config(net, resize_max, training))},
    )
    return path


def fingerprint(state: dict[str, torch.Tensor]) -> str:
    """A short hash of a state dict's names and values (which backbone computed cached features)."""
    digest = hashlib.sha256()
    for key in sorted(state):
        digest.update(key.encode())
        digest.update(state[key].detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:12]


def has_backbone(tensors: dict[str, torch.Tensor]) -> bool:
    """Whether weights read by ``read_filter_weights`` carry a fine-tuned backbone."""
    return any(k.startswith(BACKBONE_PREFIX) for k in tensors)


def read_filter_weights(path: str | Path | None = None) -> tuple[dict[str, torch.Tensor], dict]:
    """(filter state dict, config) from ``path`` (default: ``DEFAULT_WEIGHTS``). A missing file
    raises FileNotFoundError, so that callers can fall back to raw mode."""
    path = Path(path) if path else DEFAULT_WEIGHTS
    if not path.is_file():
        raise FileNotFoundError(
            f"Coarse filter weights {path}: no such file; pass the path of "
            "trained filter weights (.safetensors), train them (python "
            "-m colmap_guided.train), or use mode='raw' (no filter)"
        )
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            # f.keys(): safe_open is not a dict
            tensors = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118
    except (SafetensorError, OSError) as e:
        raise ValueError(
            f"{path} is not a readable safetensors file ({type(e).__name__}): "
            "download or train the filter weights again"
        ) from None
    if "config" not in meta:
        raise ValueError(
            f"{path} has no coarse-filter config in its "
            "metadata: re-save it with save_filter_weights"
        )
    config = json.loads(meta["config"])
    if config.get("format") != FORMAT:
        raise ValueError(
            f"{path} has format {config.get('format')!r}, expected {FORMAT!r}: "
            "re-export it with this version"
        )
    return tensors, config


def check_config(config: dict, net: CoarseNet, path: str | Path) -> None:
    """Raise a one-line ValueError if ``net`` is not built the way the weights were trained."""
    expected = filter_config(net, config.get("resize_max", 0))
    diff = [
        f"{k}: weights {config.get(k)!r} vs network {expected[k]!r}"
        for k in _ARCH_KEYS
        if config.get(k) != expected[k]
    ]
    if diff:
        raise ValueError(
            f"Coarse filter weights {path} do not fit this network ({'; '.join(diff)}): "
            "build it with the weights' settings or use other weights"
        )


def load_filter_weights(net: CoarseNet, path: str | Path | None = None) -> dict:
    """Load filter weights (and the fine-tuned backbone they carry, if any) into ``net`` after
    checking the config; returns the config."""
    if net.filter is None:
        raise ValueError(
            "This CoarseNet is in raw mode (filter=False): "
            "build it with filter=True to load weights"
        )
    tensors, config = read_filter_weights(path)
    check_config(config, net, path or DEFAULT_WEIGHTS)
    backbone = {
        k.removeprefix(BACKBONE_PREFIX): v
        for k, v in tensors.items()
        if k.startswith(BACKBONE_PREFIX)
    }
    net.filter.load_state_dict(
        {k: v for k, v in tensors.items() if not k.startswith(BACKBONE_PREFIX)}
    )
    if backbone:
        if set(backbone) != set(net.backbone.feature_state_dict()):
            raise ValueError(
                f"Coarse filter weights {path or DEFAULT_WEIGHTS}: their backbone tensors "
                f"are not {config['backbone']}'s feature layers; export them again"
            )
        net.backbone.load_state_dict(backbone, strict=False)
    return config


def net_conf_from_config(config: dict) -> dict:
    """CoarseNet options that rebuild the network the weights were trained with."""
    return {
        "backbone": config["backbone"],
        "channels": tuple(config["channels"]),
        "kernel_sizes": tuple(config["kernel_sizes"]),
        "mutual_before": config["mutual_before"],
        "mutual_after": config["mutual_after"],
    }
