"""The coarse matching network (paper §4.1, built on NCNet): features → 4D correlation → symmetric
4D neighbourhood-consensus filter → s^{A→B}, s^{B→A} → coarse matches.

Volumes are laid out (B, hA, wA, hB, wB): ``volume[n, i, j, k, l]`` relates cell (row i, col j) of A
to cell (row k, col l) of B. Grids are flattened row-major (cell index ``row * width + col``).

Decisions (documented for the trainer and the guided matcher):
- Filter input: ReLU of the correlation. NCNet correlates post-ReLU ResNet features, so its volume
  is non-negative; EfficientNet's block outputs are linear, so their cosine can be negative, and the
  clamp restores NCNet's setting (the argmax is unchanged).
- NCNet's soft mutual-nearest-neighbour step ``c * (c / max_A c) * (c / max_B c)`` is applied before
  and after the filter, as in NCNet (conf ``mutual_before`` / ``mutual_after``, both stored with the
  weights). Before, it damps ambiguous correlations the filter would otherwise spread; after, it
  makes the output favour mutual matches, which is what the guided matcher relies on.
- Symmetry (paper §4.3, "feeding the images in both orders ... average"): running the filter on the
  transposed volume and transposing back equals running it with every kernel's (kI, kJ) and (kK, kL)
  dims swapped, so both orders run in one pass as a 2-group network; the output is their mean.
  Exact.
- Raw mode (``filter=False``, the paper's guided-VGG4-style baseline): the volume is the correlation
  divided by ``raw_temperature``, no filter, no weights needed.
- ``forward`` (dense, differentiable, batched) and ``sparse_volume`` (one pair, differentiable) are
  the two training paths; ``match_sparse`` is the CPU inference path (Sparse-NCNet-style submanifold
  filter on ``sparse_support``: each cell's ``k`` best correlations in both directions plus the
  cells around its best match; entries outside read as 0). The same weights run in both; sparse
  approximates dense (README.md has the measured agreement), and weights trained on the sparse path
  see exactly what inference on the CPU sees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from colmap_guided.coarse.backbone import BACKBONES, DEFAULT_BACKBONE, build_backbone
from colmap_guided.coarse.conv4d import SparseNeighbourhood, conv4d, sparse_conv4d
from colmap_guided.conf import merge_conf


def correlation(feat_a: torch.Tensor, feat_b: torch.Tensor) -> torch.Tensor:
    """c_ijkl = <fA_ij, fB_kl> (paper §4.1) of (B, C, hA, wA) and (B, C, hB, wB) →
    (B, hA, wA, hB, wB)."""
    return torch.einsum("ncij,nckl->nijkl", feat_a, feat_b)


def soft_mutual_nn(volume: torch.Tensor, eps: float = 1e-5) -> torch.Tensor:
    """NCNet's soft mutual nearest neighbour filter on a non-negative (B, hA, wA, hB, wB) volume."""
    max_b = volume.amax(dim=(3, 4), keepdim=True)  # best in B for each A cell
    max_a = volume.amax(dim=(1, 2), keepdim=True)  # best in A for each B cell
    return volume * (volume / (max_a + eps)) * (volume / (max_b + eps))


def transpose_volume(volume: torch.Tensor) -> torch.Tensor:
    """Swap the roles of A and B: (B, hA, wA, hB, wB) → (B, hB, wB, hA, wA)."""
    return volume.permute(0, 3, 4, 1, 2)


class NeighConsensus(nn.Module):
    """Symmetric 4D filter: conv4d layers (1 → channels[0] → ... → channels[-1] = 1), ReLU after
    each, run in both image orders and averaged (paper §4.3: three layers, 16 channels, kernel
    3)."""

    def __init__(
        self, channels: tuple[int, ...] = (16, 16, 1), kernel_sizes: tuple[int, ...] = (3, 3, 3)
    ):
        super().__init__()
        if len(channels) != len(kernel_sizes) or channels[-1] != 1:
            raise ValueError(
                f"channels {channels} and kernel_sizes {kernel_sizes}: "
                "one kernel size per layer, last layer 1 channel"
            )
        self.channels, self.kernel_sizes = tuple(channels), tuple(kernel_sizes)
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        c_in = 1
        for c, k in zip(channels, kernel_sizes):
            w = torch.empty(c, c_in, k, k, k, k)
            nn.init.kaiming_uniform_(w, a=math.sqrt(5))  # nn.ConvNd's default initialisation
            bound = 1 / math.sqrt(c_in * k**4)
            self.weights.append(nn.Parameter(w))
            self.biases.append(nn.Parameter(torch.empty(c).uniform_(-bound, bound)))
            c_in = c

    def fused_layers(self) -> list[tuple[torch.Tensor, torch.Tensor, int]]:
        """(weight, bias, groups) per layer of the 2-group network computing both image orders:
        group 0 is the filter, group 1 the filter with A and B kernel dims swapped."""
        layers = []
        for idx, (w, b) in enumerate(zip(self.weights, self.biases)):
            wt = w.permute(0, 1, 4, 5, 2, 3)
            layers.append((torch.cat([w, wt]), torch.cat([b, b]), 1 if idx == 0 else 2))
        return layers

    def forward(self, volume: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Dense filter of (B, hA, wA, hB, wB); ``mask`` (same shape, bool) zeroes padded cells
        after each layer so that padded batches give the same values as single pairs."""
        x = volume.unsqueeze(1)
        m = None if mask is None else mask.unsqueeze(1).to(volume.dtype)
        for w, b, groups in self.fused_layers():
            x = F.relu(conv4d(x, w, b, groups))
            if m is not None:
                x = x * m
        return x.mean(dim=1)

    def forward_sparse(
        self, values: torch.Tensor, coords: torch.Tensor, shape: tuple[int, int, int, int]
    ) -> torch.Tensor:
        """Submanifold filter of N active entries (values (N,) at coords (N, 4) (i, j, k, l) of a
        volume of ``shape``): outputs at the active entries only, inactive ones read as 0 → (N,)."""
        nbhds = {k: SparseNeighbourhood(coords, shape, (k,) * 4) for k in set(self.kernel_sizes)}
        x = values.unsqueeze(1)
        for (w, b, groups), k in zip(self.fused_layers(), self.kernel_sizes):
            x = F.relu(sparse_conv4d(x, nbhds[k], w, b, groups))
        return x.mean(dim=1)


@dataclass
class GridMatches:
    """Coarse matches on the feature grids of one pair (argmax of s^{A→B} / s^{B→A}, paper §4.1)."""

    ab: np.ndarray  # (hA * wA,) int64: index of the matched B cell of each A cell
    score_ab: np.ndarray  # (hA * wA,) float32: s^{A→B} at the match (softmax probability)
    ba: np.ndarray  # (hB * wB,) int64
    score_ba: np.ndarray  # (hB * wB,) float32

    @property
    def mutual_ab(self) -> np.ndarray:
        """(hA * wA,) bool: the A cell's match matches back to it."""
        return self.ba[self.ab] == np.arange(len(self.ab))

    @property
    def mutual_ba(self) -> np.ndarray:
        return self.ab[self.ba] == np.arange(len(self.ba))


def _dense_matches(volume2d: torch.Tensor) -> GridMatches:
    """Argmax and softmax score per row and per column of a (NA, NB) volume."""

    def best(v: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        vmax, idx = v.max(dim=1)
        score = 1.0 / torch.exp(v - vmax[:, None]).sum(dim=1)
        return idx.cpu().numpy(), score.float().cpu().numpy()

    ab, sab = best(volume2d)
    ba, sba = best(volume2d.t())
    return GridMatches(ab, sab, ba, sba)


def sparse_best(
    rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, n_rows: int, n_cols: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per row, the column of the largest active value and its softmax probability over the whole
    row, inactive entries counting as 0 (values are non-negative): (n_rows,) long, (n_rows,) float.
    Differentiable in ``values`` (the sparse training path takes max s from it, paper eq. 3, 5)."""
    order = torch.argsort(values.detach(), descending=True, stable=True)
    order = order[torch.argsort(rows[order], stable=True)]  # grouped by row, largest first
    counts = torch.bincount(rows, minlength=n_rows)
    first = torch.cumsum(counts, 0) - counts
    if (counts == 0).any():
        raise ValueError("sparse support must hold at least one entry per row and column")
    vmax = values[order[first]]
    denom = torch.zeros(n_rows, dtype=values.dtype, device=values.device).index_add(
        0, rows, torch.exp(values - vmax[rows])
    )
    denom = denom + (n_cols - counts) * torch.exp(-vmax)
    return cols[order[first]], 1.0 / denom


def sparse_support(
    c2: torch.Tensor, shape: tuple[int, int, int, int], k: int, radius: int
) -> torch.Tensor:
    """Sorted linear indices (a * NB + b) of the entries of a (NA, NB) correlation the sparse filter
    runs on: the ``k`` best B cells of every A cell and the ``k`` best A cells of every B cell
    (Sparse-NCNet), plus the (2 radius + 1)^2 cells around each cell's best match in the other image
    (where the filtered peak moves when neighbourhood consensus corrects a match). Symmetric
    in A, B."""
    ha, wa, hb, wb = shape
    na, nb = c2.shape
    dev = c2.device
    support = torch.zeros(na * nb, dtype=torch.bool, device=dev)
    ia, ib = torch.arange(na, device=dev), torch.arange(nb, device=dev)
    support[(ia[:, None] * nb + c2.topk(min(k, nb), dim=1).indices).ravel()] = True
    support[(c2.topk(min(k, na), dim=0).indices * nb + ib[None, :]).ravel()] = True
    if radius > 0:
        d = torch.arange(-radius, radius + 1, device=dev)

        def around(
            best: torch.Tensor, h: int, w: int
        ) -> torch.Tensor:  # (n, (2r+1)^2) cells around best
            rows = (best // w)[:, None, None] + d[None, :, None]
            cols = (best % w)[:, None, None] + d[None, None, :]
            return (rows.clamp(0, h - 1) * w + cols.clamp(0, w - 1)).reshape(len(best), -1)

        support[(ia[:, None] * nb + around(c2.argmax(dim=1), hb, wb)).ravel()] = True
        support[(around(c2.argmax(dim=0), ha, wa) * nb + ib[:, None]).ravel()] = True
    return support.nonzero().squeeze(1)


class CoarseNet(nn.Module):
    """Backbone + correlation + neighbourhood-consensus filter (paper §4.1, §4.3).

    Training API (dense, differentiable w.r.t. the filter, and the backbone if unfrozen):
        feats = net.extract_features(net.normalize(images))
            # (B, C, h, w), L2-normalised; cacheable
        out = net(feat_a, feat_b, mask_a, mask_b)  # dict, see ``forward``
        loss = l(out["s_ab"]) + l(out["s_ba"])  # paper eq. (2)
    Inference: ``match(feat_a, feat_b, impl='dense'|'sparse', k=...)`` → ``GridMatches`` per pair.
    """

    default_conf = {
        "backbone": DEFAULT_BACKBONE,
        "backbone_weights": None,  # path overriding the backbone's ImageNet weights
        "pretrained": True,  # False: random backbone (wiring tests only)
        "filter": True,  # False: raw mode (correlation only, no weights)
        "channels": (16, 16, 1),
        "kernel_sizes": (3, 3, 3),
        "mutual_before": True,
        "mutual_after": True,
        "raw_temperature": 0.02,  # raw mode: softmax of correlation / temperature (scores only)
    }

    def __init__(self, conf: dict | None = None):
        super().__init__()
        self.conf = conf = merge_conf(self.default_conf, conf, "CoarseNet")
        self.backbone = build_backbone(
            conf["backbone"], conf["backbone_weights"], conf["pretrained"]
        )
        self.spec = BACKBONES[conf["backbone"]]  # stride, channels, cell_offset of the features
        self.filter = (
            NeighConsensus(tuple(conf["channels"]), tuple(conf["kernel_sizes"]))
            if conf["filter"]
            else None
        )

    def normalize(self, images: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) RGB in [0, 255] → the backbone's input normalisation."""
        return self.backbone.normalize(images)

    def extract_features(self, images: torch.Tensor) -> torch.Tensor:
        """Normalised images (B, 3, H, W), H and W multiples of 16 → L2-normalised
        (B, C, H/16, W/16)."""
        return F.normalize(self.backbone(images), dim=1)

    def filter_volume(self, corr: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """ReLU → [soft mutual NN] → symmetric 4D filter → [soft mutual NN], dense."""
        v = F.relu(corr)
        if self.conf["mutual_before"]:
            v = soft_mutual_nn(v)
        v = self.filter(v, mask)
        if self.conf["mutual_after"]:
            v = soft_mutual_nn(v)
        return v

    def forward(
        self,
        feat_a: torch.Tensor,
        feat_b: torch.Tensor,
        mask_a: torch.Tensor | None = None,
        mask_b: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """Dense pass on batched features (B, C, hA, wA), (B, C, hB, wB) (L2-normalised,
        zero-padded, with optional bool masks (B, hA, wA), (B, hB, wB) of the valid cells). Returns
        - ``corr``: correlation (B, hA, wA, hB, wB);
        - ``volume``: the filtered volume s (raw mode: corr / raw_temperature);
        - ``s_ab``: softmax of ``volume`` over B's cells (sums to 1 over (hB, wB)), s^{A→B};
        - ``s_ba``: softmax over A's cells, s^{B→A}. Padded cells get probability 0.
        """
        corr = correlation(feat_a, feat_b)
        n, ha, wa, hb, wb = corr.shape
        mask = None
        if mask_a is not None or mask_b is not None:
            ma = mask_a if mask_a is not None else corr.new_ones(n, ha, wa, dtype=torch.bool)
            mb = mask_b if mask_b is not None else corr.new_ones(n, hb, wb, dtype=torch.bool)
            mask = ma[:, :, :, None, None] & mb[:, None, None, :, :]
        volume = (
            corr / self.conf["raw_temperature"]
            if self.filter is None
            else self.filter_volume(corr, mask)
        )
        logits = volume if mask is None else volume.masked_fill(~mask, float("-inf"))
        flat = logits.reshape(n, ha * wa, hb * wb)
        s_ab = torch.softmax(flat, dim=2).nan_to_num(0.0).view(n, ha, wa, hb, wb)
        s_ba = torch.softmax(flat, dim=1).nan_to_num(0.0).view(n, ha, wa, hb, wb)
        return {"corr": corr, "volume": volume, "s_ab": s_ab, "s_ba": s_ba}

    @torch.no_grad()
    def match(
        self,
        feat_a: torch.Tensor,
        feat_b: torch.Tensor,
        impl: str = "dense",
        k: int = 3,
        radius: int = 1,
        dtype: torch.dtype = torch.float32,
    ) -> GridMatches:
        """Coarse matches of one pair of features (C, hA, wA), (C, hB, wB). ``impl``: 'dense' (whole
        volume; GPU) or 'sparse' (filter on ``sparse_support(k, radius)``; CPU). Raw mode ignores
        it."""
        if impl not in ("dense", "sparse"):
            raise ValueError(f"impl must be 'dense' or 'sparse', got {impl!r}")
        if impl == "sparse" and self.filter is not None:
            return self.match_sparse(correlation(feat_a[None], feat_b[None])[0], k, radius)
        return self.match_batch(feat_a[None], feat_b[None], dtype)[0]

    @torch.no_grad()
    def match_batch(
        self, feat_a: torch.Tensor, feat_b: torch.Tensor, dtype: torch.dtype = torch.float32
    ) -> list[GridMatches]:
        """Dense coarse matches of a batch of same-size pairs (B, C, hA, wA), (B, C, hB, wB).
        ``dtype`` float16/bfloat16 runs correlation and filter under autocast (GPU); argmax and
        scores in float32."""
        with torch.autocast(feat_a.device.type, dtype=dtype, enabled=dtype != torch.float32):
            corr = correlation(feat_a, feat_b)
            volume = (
                corr / self.conf["raw_temperature"]
                if self.filter is None
                else self.filter_volume(corr)
            )
        _, ha, wa, hb, wb = corr.shape
        return [_dense_matches(v.float().reshape(ha * wa, hb * wb)) for v in volume]

    def sparse_volume(
        self, corr: torch.Tensor, k: int, radius: int = 0
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The filtered volume of one pair's correlation (hA, wA, hB, wB) on
        ``sparse_support(k, radius)`` (Sparse-NCNet's idea): flat A cells ``a``, flat B cells ``b``
        and values ``v`` (N,) of the active entries; the rest of the volume reads as 0.
        Differentiable in the filter (and ``corr``): the CPU inference path and the sparse training
        path run exactly this. With k ≥ the grid sizes it equals the dense filter."""
        ha, wa, hb, wb = corr.shape
        na, nb = ha * wa, hb * wb
        c2 = F.relu(corr.reshape(na, nb))
        lin = sparse_support(c2.detach(), (ha, wa, hb, wb), k, radius)
        a, b = lin // nb, lin % nb
        v = c2.reshape(-1)[lin]
        if self.conf["mutual_before"]:
            v = self._sparse_mutual(v, a, b, na, nb)
        coords = torch.stack([a // wa, a % wa, b // wb, b % wb], dim=1)
        v = self.filter.forward_sparse(v, coords, (ha, wa, hb, wb))
        if self.conf["mutual_after"]:
            v = self._sparse_mutual(v, a, b, na, nb)
        return a, b, v

    def match_sparse(self, corr: torch.Tensor, k: int, radius: int = 0) -> GridMatches:
        """Coarse matches from ``sparse_volume``: argmax and softmax score per row and column."""
        ha, wa, hb, wb = corr.shape
        a, b, v = self.sparse_volume(corr, k, radius)
        ab, sab = sparse_best(a, b, v, ha * wa, hb * wb)
        ba, sba = sparse_best(b, a, v, hb * wb, ha * wa)
        return GridMatches(
            ab.cpu().numpy(), sab.float().cpu().numpy(), ba.cpu().numpy(), sba.float().cpu().numpy()
        )

    @staticmethod
    def _sparse_mutual(
        v: torch.Tensor, a: torch.Tensor, b: torch.Tensor, na: int, nb: int, eps: float = 1e-5
    ) -> torch.Tensor:
        """``soft_mutual_nn`` on sparse non-negative entries (inactive = 0 never changes a
        maximum)."""
        max_b = v.new_zeros(na).scatter_reduce(0, a, v, "amax")
        max_a = v.new_zeros(nb).scatter_reduce(0, b, v, "amax")
        return v * (v / (max_a[b] + eps)) * (v / (max_b[a] + eps))
