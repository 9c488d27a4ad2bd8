"""CoarseMatcher: the coarse matching network as the guided matcher uses it.

    cm = CoarseMatcher({"mode": "raw"})     # or the default mode='filter' with trained weights
    fa = cm.extract_path(path_a, name="a")  # backbone once per image, cached by name
    res = cm.match(fa, fb)                  # CoarseResult
    xy_b, score, fb_err = res.flow_ab(xy_a)

Files are read by ``colmap_guided.images.read_image`` (the project's one reader: COLMAP's frame,
EXIF orientation NOT applied, 16-bit scaled), so keypoints and the coarse flow share one frame and
pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import torch

from colmap_guided.coarse.backbone import BACKBONES, DEFAULT_BACKBONE
from colmap_guided.coarse.flow import CoarseResult
from colmap_guided.coarse.geometry import ImageGeometry, as_rgb, resize_geometry, resize_image
from colmap_guided.coarse.model import CoarseNet
from colmap_guided.coarse.weights import (
    DEFAULT_WEIGHTS,
    fingerprint,
    has_backbone,
    load_filter_weights,
    net_conf_from_config,
    read_filter_weights,
)
from colmap_guided.conf import merge_conf
from colmap_guided.images import image_size, read_image

PRECISIONS = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}


@dataclass
class CoarseFeatures:
    """Backbone features of one image: L2-normalised (C, h, w) on the matcher's device +
    geometry."""

    features: torch.Tensor
    geometry: ImageGeometry
    name: str | None = None


class CoarseMatcher:
    """Coarse matches and flow between images (paper §4.1), with a per-image feature cache."""

    default_conf = {
        "backbone": DEFAULT_BACKBONE,  # stride-16 features: efficientnet-lite{0,1,2} or resnet101
        "backbone_weights": None,  # path overriding the backbone's ImageNet weights
        "resize_max": 512,  # long side of the network input (grid at most 32x32)
        "mode": "filter",  # 'filter': learned filter (needs weights) | 'raw': correlation only
        "weights": None,  # filter weights; None: colmap_guided/weights/coarse_filter.safetensors
        "device": "auto",  # 'auto' (cuda if available) | 'cpu' | 'cuda' | 'cuda:N'
        "impl": "auto",  # filter: 'dense' | 'sparse' | 'auto' (dense on CUDA, sparse on CPU)
        # sparse filter: best cells kept per cell and direction (README: cost vs accuracy)
        "sparse_k": 3,
        "sparse_radius": 1,  # sparse filter: also the (2r+1)^2 cells around each cell's best match
        "raw_temperature": 0.02,  # raw mode: softmax temperature of the scores
        "cache_path": None,  # optional .h5 file caching backbone features across runs
        # dense filter: 'float32' | 'float16' | 'bfloat16' (autocast; README: accuracy)
        "precision": "float32",
        # CPU: torch threads the pipeline sets while matching (restored after); None: leave as is
        "num_threads": 1,
    }

    def __init__(self, conf: dict | None = None):
        self.conf = conf = merge_conf(self.default_conf, conf, "CoarseMatcher")
        if conf["mode"] not in ("filter", "raw"):
            raise ValueError(f"mode must be 'filter' or 'raw', got {conf['mode']!r}")
        self.device = torch.device(
            "cuda"
            if conf["device"] == "auto" and torch.cuda.is_available()
            else "cpu"
            if conf["device"] == "auto"
            else conf["device"]
        )
        impl = (
            conf["impl"]
            if conf["impl"] != "auto"
            else ("dense" if self.device.type == "cuda" else "sparse")
        )
        if impl not in ("dense", "sparse"):
            raise ValueError(f"impl must be 'dense', 'sparse' or 'auto', got {conf['impl']!r}")
        self.impl = impl
        if conf["precision"] not in PRECISIONS:
            raise ValueError(
                f"precision must be one of {sorted(PRECISIONS)}, got {conf['precision']!r}"
            )
        self.dtype = PRECISIONS[conf["precision"]]
        # The sparse filter is hundreds of small ops; on shared cores every OpenMP barrier waits for
        # a descheduled thread. On the 2-core dev machine (load ~5-10) one thread was 3-8x faster
        # than two for the sparse filter and 2.4x faster for the backbone (README.md). Set around
        # matching only.
        self.torch_threads = conf["num_threads"] if self.device.type == "cpu" else None
        net_conf = {
            "backbone": conf["backbone"],
            "backbone_weights": conf["backbone_weights"],
            "raw_temperature": conf["raw_temperature"],
            "filter": conf["mode"] == "filter",
        }
        self.weights_config = None
        if conf["mode"] == "filter":
            # FileNotFoundError → caller falls back
            tensors, self.weights_config = read_filter_weights(conf["weights"])
            if has_backbone(tensors) and conf["backbone_weights"]:
                raise ValueError(
                    f"Filter weights {conf['weights'] or DEFAULT_WEIGHTS} carry the backbone "
                    f"they were trained with: drop backbone_weights={conf['backbone_weights']!r} "
                    "or use weights without a backbone"
                )
            wanted = net_conf_from_config(self.weights_config)
            if wanted["backbone"] != conf["backbone"]:
                raise ValueError(
                    f"Filter weights {conf['weights'] or DEFAULT_WEIGHTS} were "
                    f"trained on {wanted['backbone']}, not {conf['backbone']}: "
                    f"set backbone={wanted['backbone']!r} or use other weights"
                )
            net_conf.update(wanted)
        self.net = CoarseNet(net_conf)
        if conf["mode"] == "filter":
            load_filter_weights(self.net, conf["weights"])
        self.net.to(self.device).eval()
        self.spec = BACKBONES[conf["backbone"]]
        # Which features: the backbone, its weights (ImageNet, a file, or fine-tuned with the
        # filter) and input size.
        self.features_key = (
            f"{self.spec.name}_{conf['resize_max']}_"
            f"{fingerprint(self.net.backbone.feature_state_dict())}"
        )
        self.cache: dict[str, CoarseFeatures] = {}

    # -- features -------------------------------------------------------------------------------

    def geometry(self, width: int, height: int) -> ImageGeometry:
        return resize_geometry(
            width, height, self.conf["resize_max"], self.spec.stride, self.spec.cell_offset
        )

    @torch.no_grad()
    def extract(
        self, image: np.ndarray, name: str | None = None, size: tuple[int, int] | None = None
    ) -> CoarseFeatures:
        """Features of a uint8 HxW (gray) or HxWx3 (RGB) image. With ``name``, cached in memory (and
        in ``cache_path`` if set): later calls with the same name return the cache without the
        image.
        ``size``: the (width, height) of the photo that ``image`` is a reduced decode of."""
        if name is not None and name in self.cache:
            return self.cache[name]
        if name is not None and self.conf["cache_path"]:
            cached = self._read_h5(name)
            if cached is not None:
                self.cache[name] = cached
                return cached
        if image is None:
            raise ValueError(
                f"No cached coarse features for {name!r}: pass the image (or extract_path)"
            )
        rgb = as_rgb(image)
        geo = self.geometry(*(size or (rgb.shape[1], rgb.shape[0])))
        x = torch.from_numpy(resize_image(rgb, geo)).to(self.device).permute(2, 0, 1)[None].float()
        feats = CoarseFeatures(self.net.extract_features(self.net.normalize(x))[0], geo, name)
        if name is not None:
            self.cache[name] = feats
            if self.conf["cache_path"]:
                self._write_h5(feats)
        return feats

    def extract_path(self, path: str | Path, name: str | None = None) -> CoarseFeatures:
        """``extract(read_image(path), name)``, reading the file only on a cache miss."""
        key = name or str(path)
        if key in self.cache:
            return self.cache[key]
        # A JPEG 8x the network's input or more is decoded reduced: photos to 4095 px read as
        # before.
        return self.extract(read_image(path, 4 * self.conf["resize_max"]), key, image_size(path))

    def release(self, name: str) -> None:
        """Drop image ``name`` from the in-memory cache."""
        self.cache.pop(name, None)

    def _read_h5(self, name: str) -> CoarseFeatures | None:
        path = Path(self.conf["cache_path"])
        if not path.is_file():
            return None
        with h5py.File(path, "r") as f:
            group = f.get(f"{self.features_key}/{name}")
            if group is None:
                return None
            geo = ImageGeometry(
                **{
                    k: (float if k == "cell_offset" else int)(group.attrs[k])
                    for k in ImageGeometry.__dataclass_fields__
                }
            )
            feats = torch.from_numpy(group["features"][()]).to(self.device, torch.float32)
        return CoarseFeatures(feats, geo, name)

    def _write_h5(self, feats: CoarseFeatures) -> None:
        path = Path(self.conf["cache_path"])
        path.parent.mkdir(parents=True, exist_ok=True)
        with h5py.File(path, "a") as f:
            key = f"{self.features_key}/{feats.name}"
            if key in f:
                del f[key]
            group = f.create_group(key)
            group.create_dataset("features", data=feats.features.cpu().numpy())
            for k, v in feats.geometry.to_dict().items():
                group.attrs[k] = v

    # -- matching -------------------------------------------------------------------------------

    def match(self, fa: CoarseFeatures, fb: CoarseFeatures) -> CoarseResult:
        """Coarse matches and flow of one pair (A = fa, B = fb)."""
        grid = self.net.match(
            fa.features,
            fb.features,
            self.impl,
            self.conf["sparse_k"],
            self.conf["sparse_radius"],
            self.dtype,
        )
        return CoarseResult(fa.geometry, fb.geometry, grid)

    def match_pairs(self, pairs: list[tuple[CoarseFeatures, CoarseFeatures]]) -> list[CoarseResult]:
        """``match`` for many pairs; pairs of equal grid shapes are batched in the dense filter."""
        if self.impl == "sparse" or self.net.filter is None:
            return [self.match(fa, fb) for fa, fb in pairs]
        results: list[CoarseResult | None] = [None] * len(pairs)
        groups: dict[tuple, list[int]] = {}
        for i, (fa, fb) in enumerate(pairs):
            groups.setdefault((tuple(fa.features.shape), tuple(fb.features.shape)), []).append(i)
        for idx in groups.values():
            grids = self.net.match_batch(
                torch.stack([pairs[i][0].features for i in idx]),
                torch.stack([pairs[i][1].features for i in idx]),
                self.dtype,
            )
            for i, grid in zip(idx, grids):
                results[i] = CoarseResult(pairs[i][0].geometry, pairs[i][1].geometry, grid)
        return results

    def describe(self) -> dict:
        return {
            "conf": self.conf,
            "impl": self.impl,
            "device": str(self.device),
            "weights_config": self.weights_config,
        }
