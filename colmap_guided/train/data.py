"""Training data for the coarse network (paper §4.3): ``CoarseTrainData`` (scenes, views, the
feature cache and the seeded batch sampler) and ``collate`` (batches of tensors for the dense path).

Positives: SfM pairs (``scenes``) and synthetic homography pairs (``augment``); negatives pair
images of two different scenes (half of each batch for the image and epipolar supervisions). Either
image of a pair may be an archival version: with a frozen backbone the features of ``n_variants``
versions of each image (version 0 clean, odd versions an archival print, even ones a small soft scan
of one, seeded by the view's name) are cached (``cache``), and every draw picks a version.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from colmap_guided import archival, paths
from colmap_guided.coarse.backbone import BACKBONES, DEFAULT_BACKBONE, build_backbone
from colmap_guided.coarse.geometry import ImageGeometry, resize_geometry, resize_image, stack_padded
from colmap_guided.conf import merge_conf
from colmap_guided.geometry import apply_h
from colmap_guided.images import read_image
from colmap_guided.log import logger
from colmap_guided.train.augment import (
    random_epipole,
    random_homography,
    soft_scan,
    variant_seed,
    warp_image,
)
from colmap_guided.train.cache import FeatureCache
from colmap_guided.train.geometry import ideal_pixels, induced_fundamental, scale_fundamental
from colmap_guided.train.scenes import (
    VAL_SCENES,
    SfmImage,
    SfmPair,
    SfmScene,
    all_scenes,
    load_scene,
    subset_scene,
)
from colmap_guided.train.views import (
    PairSample,
    View,
    cells_in_window,
    crop_sample,
    inside,
    plain_centres,
)


class CoarseTrainData:
    """Scenes, views, positive/negative pairs, the feature cache, and a seeded batch sampler."""

    # an option's comment is the help of its flag in python -m colmap_guided.train
    default_conf = {
        "backbone": DEFAULT_BACKBONE,  # feature backbone, a name of coarse.backbone.BACKBONES
        # long side of training images (the pipeline's resize_max; paper: 401 px), a multiple of
        # the backbone's stride
        "resolution": 512,
        "min_shared": 30,  # positive pair: at least this many common 3D points (paper §4.3)
        "train_scenes": None,  # None: every scene with a model except val_scenes
        "val_scenes": VAL_SCENES,  # held-out scenes of the validation PCK
        # at most this many images per scene (cache budget; small subsets for smoke tests)
        "max_images_per_scene": None,
        # cached versions of each image: 0 clean, odd k archival print, even k > 0 small soft
        # scan of one
        "n_variants": 3,
        "archival_prob": 0.5,  # chance that a side of a pair is an archival version
        "archival_strength": 1.0,
        "n_synthetic": 1,  # homography views cached per training photo
        # share of positives that are synthetic homography pairs (0: SfM only, 1: synthetic only)
        "synthetic_ratio": 0.3,
        "homography_strength": 1.0,
        "max_matches": 256,  # ground-truth matches kept per pair (point loss, PCK)
        "val_pairs_per_scene": 16,  # validation pairs per held-out scene
        # training crop: at most this many feature cells per grid side (CPU budget), see
        # crop_sample; None: whole grids
        "max_cells": None,
        # feature cache folder; None: ~/.cache/colmap_guided/train_features ($COLMAP_GUIDED_CACHE)
        "cache_dir": None,
    }

    def __init__(self, conf: dict | None = None):
        self.conf = c = merge_conf(self.default_conf, conf, "data")
        self.spec = BACKBONES[c["backbone"]]
        val = list(c["val_scenes"])
        train = (
            c["train_scenes"]
            if c["train_scenes"] is not None
            else [s for s in all_scenes() if s not in val]
        )
        overlap = set(train) & set(val)
        if overlap:
            raise ValueError(f"Scenes both in training and validation: {sorted(overlap)}")
        self.train_scenes, self.val_scenes = list(train), val
        self.scenes: dict[str, SfmScene] = {}
        for name in self.train_scenes + self.val_scenes:
            scene = load_scene(name, c["min_shared"])
            if c["max_images_per_scene"]:
                scene = subset_scene(scene, c["max_images_per_scene"])
            self.scenes[name] = scene
        self.train_scenes = [s for s in self.train_scenes if self.scenes[s].pairs]
        if not self.train_scenes:
            raise ValueError("No training scene has a positive pair")
        self.views: dict[str, View] = {}
        for name in self.train_scenes:
            for im in self.scenes[name].images.values():
                for k in range(c["n_variants"]):
                    self._image_view(im, k)
                for k in range(c["n_synthetic"]):
                    self._synthetic_view(im, k)
        # adds the (clean) views of the validation pairs only
        self.val_samples = self._make_val_samples()
        cache_dir = Path(c["cache_dir"]) if c["cache_dir"] else paths.cache_dir("train_features")
        tag = (
            f"{c['backbone']}_l2_r{c['resolution']}_a"
            f"{c['archival_strength']:g}_h{c['homography_strength']:g}"
        )
        self.cache = FeatureCache(cache_dir / f"{tag}.h5")
        n_pairs = sum(len(self.scenes[s].pairs) for s in self.train_scenes)
        logger.info(
            "Training data: %d scenes, %d positive pairs, "
            "%d views; validation: %d scenes, %d pairs.",
            len(self.train_scenes),
            n_pairs,
            len(self.views),
            len(self.val_scenes),
            len(self.val_samples),
        )

    # -------------------------------------------------------------------------------- views
    def geometry_of(self, width: int, height: int) -> ImageGeometry:
        return resize_geometry(
            width, height, self.conf["resolution"], self.spec.stride, self.spec.cell_offset
        )

    def _image_view(self, im: SfmImage, k: int) -> View:
        key = f"img/{im.scene}/{im.name}/v{k}"
        if key not in self.views:
            geom = self.geometry_of(im.width, im.height)
            centres = geom.cell_centers()  # original pixels
            ideal = ideal_pixels(im.camera, centres) * geom.scale
            self.views[key] = View(
                key, im.scene, im.name, geom, ideal.reshape(geom.grid_height, geom.grid_width, 2)
            )
        return self.views[key]

    def _synthetic_view(self, im: SfmImage, k: int) -> View:
        key = f"syn/{im.scene}/{im.name}/h{k}"
        if key not in self.views:
            src = self.geometry_of(im.width, im.height)
            out_w, out_h = src.resized_width, src.resized_height
            rng = np.random.default_rng(variant_seed(key))
            H = random_homography(
                im.width, im.height, out_w, out_h, rng, self.conf["homography_strength"]
            )
            geom = ImageGeometry(
                out_w, out_h, out_w, out_h, self.spec.stride, self.spec.cell_offset
            )
            self.views[key] = View(key, im.scene, im.name, geom, plain_centres(geom), H)
        return self.views[key]

    def render(self, key: str) -> np.ndarray:
        """The resized uint8 RGB network input of a view (deterministic: seeds come from the
        key)."""
        view = self.views[key]
        im = self.scenes[view.scene].images[view.name]
        rgb = read_image(im.path)
        if (rgb.shape[1], rgb.shape[0]) != (im.width, im.height):
            raise ValueError(
                f"{im.path} is {rgb.shape[1]}x{rgb.shape[0]}, its model says {im.width}x{im.height}"
            )
        kind, k = key.split("/")[0], int(key.rsplit("/", 1)[1][1:])
        if kind == "img":
            out = resize_image(rgb, view.geometry)
            if k > 0:
                rng = np.random.default_rng(variant_seed(key))
                if k % 2 == 0:
                    out = soft_scan(out, rng)
                out = archival.degrade(out, rng, self.conf["archival_strength"])
            return out
        out = warp_image(rgb, view.H, view.geometry.resized_width, view.geometry.resized_height)
        rng = np.random.default_rng(variant_seed(key, "archival"))
        if rng.random() < self.conf["archival_prob"]:
            out = archival.degrade(out, rng, self.conf["archival_strength"])
        return out

    def build_cache(
        self, backbone: torch.nn.Module | None = None, keys: list[str] | None = None
    ) -> int:
        """Compute and store the frozen-backbone features of every view missing from the cache."""
        keys = [k for k in (keys or sorted(self.views)) if k not in self.cache]
        if not keys:
            return 0
        backbone = backbone if backbone is not None else build_backbone(self.conf["backbone"])
        backbone.eval()
        logger.info("Caching backbone features of %d views in %s ...", len(keys), self.cache.path)
        chunk: dict[str, np.ndarray] = {}
        for i, key in enumerate(
            tqdm(keys, desc="features", mininterval=10, disable=len(keys) < 20)
        ):
            rgb = self.render(key)
            x = torch.from_numpy(rgb).permute(2, 0, 1).float()[None]
            with torch.inference_mode():
                chunk[key] = backbone(backbone.normalize(x))[0].numpy()
            if len(chunk) == 25 or i == len(keys) - 1:
                self.cache.put_many(chunk)
                chunk = {}
        return len(keys)

    def features(self, key: str) -> torch.Tensor:
        return torch.from_numpy(self.cache.get(key).astype(np.float32))

    # -------------------------------------------------------------------------------- pairs
    def sfm_sample(
        self, pair: SfmPair, va: int = 0, vb: int = 0, rng: np.random.Generator | None = None
    ) -> PairSample:
        scene = self.scenes[pair.scene]
        a = self._image_view(scene.images[pair.a], va)
        b = self._image_view(scene.images[pair.b], vb)
        F = scale_fundamental(pair.F, a.geometry.scale, b.geometry.scale)
        pts_a, pts_b = pair.xy_a, pair.xy_b
        m = self.conf["max_matches"]
        if len(pts_a) > m:
            idx = (rng if rng is not None else np.random.default_rng(0)).choice(
                len(pts_a), m, replace=False
            )
            pts_a, pts_b = pts_a[idx], pts_b[idx]
        return PairSample(a, b, True, "sfm", F, pts_a, pts_b)

    def synthetic_sample(
        self, image: SfmImage, k: int, va: int, rng: np.random.Generator
    ) -> PairSample:
        a = self._image_view(image, va)
        b = self._synthetic_view(image, k)
        # A resized -> B
        Ha = b.H @ np.diag([1 / a.geometry.scale[0], 1 / a.geometry.scale[1], 1.0])
        F = induced_fundamental(Ha, random_epipole(b.geometry.width, b.geometry.height, rng))
        # Exact matches: A's cell centres seen in B, and B's cell centres seen in A
        # (inside both images).
        ca = a.geometry.cell_centers()
        cb = b.geometry.cell_centers()
        ca_b = apply_h(b.H, ca)
        cb_a = apply_h(np.linalg.inv(b.H), cb)
        in_b = inside(ca_b, b.geometry)
        in_a = inside(cb_a, a.geometry)
        pts_a = np.concatenate([ca[in_b], cb_a[in_a]])
        pts_b = np.concatenate([ca_b[in_b], cb[in_a]])
        m = self.conf["max_matches"]
        if len(pts_a) > m:
            idx = rng.choice(len(pts_a), m, replace=False)
            pts_a, pts_b = pts_a[idx], pts_b[idx]
        # xy_ideal of an image view is undistorted; H relates observed pixels, so use plain centres.
        a_plain = View(a.key, a.scene, a.name, a.geometry, plain_centres(a.geometry))
        return PairSample(a_plain, b, True, "synthetic", F, pts_a, pts_b)

    def negative_sample(self, rng: np.random.Generator) -> PairSample:
        s1, s2 = rng.choice(len(self.train_scenes), 2, replace=False)
        views = []
        for s in (s1, s2):
            scene = self.scenes[self.train_scenes[s]]
            names = sorted(scene.images)
            im = scene.images[names[rng.integers(len(names))]]
            views.append(self._image_view(im, self._variant(rng)))
        empty = np.zeros((0, 2))
        return PairSample(views[0], views[1], False, "negative", np.zeros((3, 3)), empty, empty)

    def _variant(self, rng: np.random.Generator) -> int:
        n = self.conf["n_variants"]
        return int(rng.integers(1, n)) if n > 1 and rng.random() < self.conf["archival_prob"] else 0

    def sample_batch(
        self, rng: np.random.Generator, batch_size: int, n_negative: int
    ) -> list[PairSample]:
        """``batch_size`` pairs: ``n_negative`` negatives, the rest positives
        (a share synthetic)."""
        c = self.conf
        samples = []
        for i in range(batch_size):
            if i < n_negative and len(self.train_scenes) > 1:
                samples.append(self.negative_sample(rng))
                continue
            scene = self.scenes[self.train_scenes[rng.integers(len(self.train_scenes))]]
            if c["n_synthetic"] > 0 and rng.random() < c["synthetic_ratio"]:
                names = sorted(scene.images)
                im = scene.images[names[rng.integers(len(names))]]
                s = self.synthetic_sample(
                    im, int(rng.integers(c["n_synthetic"])), self._variant(rng), rng
                )
            else:
                pair = scene.pairs[rng.integers(len(scene.pairs))]
                s = self.sfm_sample(pair, self._variant(rng), self._variant(rng), rng)
            samples.append(s.swapped() if rng.random() < 0.5 else s)
        if c["max_cells"]:
            samples = [crop_sample(s, c["max_cells"], rng) for s in samples]
        return samples

    def _make_val_samples(self) -> list[PairSample]:
        """Fixed validation pairs: up to ``val_pairs_per_scene`` per held-out scene, clean
        images."""
        rng = np.random.default_rng(12345)
        out = []
        for name in self.val_scenes:
            pairs = self.scenes[name].pairs
            n = min(len(pairs), self.conf["val_pairs_per_scene"])
            for i in sorted(rng.choice(len(pairs), n, replace=False)) if n else []:
                out.append(self.sfm_sample(pairs[i], 0, 0, np.random.default_rng(i)))
        return out


def collate(
    samples: list[PairSample], data: CoarseTrainData | None = None, with_features: bool = True
) -> dict:
    """Tensors for a batch: padded features and masks, F, cell centres, GT cell matches, labels.

    Views with a window are cropped to it. Flat cell indices of ``matches`` (row * width + col) use
    the padded grid width of the batch, as the losses expect; GT matches outside a window are
    dropped.
    """
    out: dict = {"samples": samples, "positive": torch.tensor([s.positive for s in samples])}
    if with_features:
        out["feat_a"], out["mask_a"] = stack_padded(
            [s.a.crop(data.features(s.a.key)) for s in samples]
        )
        out["feat_b"], out["mask_b"] = stack_padded(
            [s.b.crop(data.features(s.b.key)) for s in samples]
        )
    ha = max(s.a.grid[2] for s in samples)
    wa = max(s.a.grid[3] for s in samples)
    hb = max(s.b.grid[2] for s in samples)
    wb = max(s.b.grid[3] for s in samples)
    n = len(samples)
    xy_a = torch.zeros(n, ha, wa, 2, dtype=torch.float64)
    xy_b = torch.zeros(n, hb, wb, 2, dtype=torch.float64)
    k = max([len(s.pts_a) for s in samples] + [1])
    matches = torch.full((n, k, 2), -1, dtype=torch.long)
    for i, s in enumerate(samples):
        xa, xb = s.a.crop_xy(), s.b.crop_xy()
        xy_a[i, : xa.shape[0], : xa.shape[1]] = torch.from_numpy(np.ascontiguousarray(xa))
        xy_b[i, : xb.shape[0], : xb.shape[1]] = torch.from_numpy(np.ascontiguousarray(xb))
        if len(s.pts_a):
            ra, ca, ina = cells_in_window(s.a, s.pts_a)
            rb, cb, inb = cells_in_window(s.b, s.pts_b)
            keep = ina & inb
            m = int(keep.sum())
            matches[i, :m, 0] = torch.from_numpy(ra[keep] * wa + ca[keep])
            matches[i, :m, 1] = torch.from_numpy(rb[keep] * wb + cb[keep])
    out.update(
        F=torch.from_numpy(np.stack([s.F for s in samples])), xy_a=xy_a, xy_b=xy_b, matches=matches
    )
    return out
