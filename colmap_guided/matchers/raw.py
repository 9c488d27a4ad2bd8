"""Unguided matching: mutual nearest neighbour + Lowe's ratio test.

This is the paper's "ratio test + bidirectional check" baseline (Table 2, "Raw"). The similarity
matrix is built in row chunks, so memory stays at ``chunk_size x M`` floats even for 20k x 20k
keypoints, and it runs on CPU or GPU (torch).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from colmap_guided.matchers.base import ImageData, Matcher

# mask_fn(rows) -> (allowed A->B, allowed B->A), both (len(rows), M) bool; None allows every pair.
MaskFn = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


def resolve_device(device: str | None) -> torch.device:
    """'auto' (or None) picks CUDA when available, otherwise the named device."""
    if device in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def normalize_descriptors(
    desc: np.ndarray | torch.Tensor, device: torch.device | str
) -> torch.Tensor:
    """uint8 (COLMAP database SIFT, RootSIFT x ~512) or float descriptors -> float32, unit L2 norm
    (a copy: database arrays may be read-only)."""
    d = (
        desc.to(device, torch.float32)
        if isinstance(desc, torch.Tensor)
        else torch.tensor(desc, dtype=torch.float32, device=device)
    )
    return torch.nn.functional.normalize(d, dim=-1)


def sim_to_dist(sim: torch.Tensor) -> torch.Tensor:
    """Euclidean distance between unit vectors from their dot product."""
    return torch.sqrt(torch.clamp(2.0 - 2.0 * sim, min=0.0))


def ratio_pass(best: torch.Tensor, second: torch.Tensor, ratio: float | None) -> torch.Tensor:
    """Lowe's test on Euclidean distances: d1 < ratio * d2 (a lone candidate, d2 = inf, passes)."""
    if ratio is None:
        return torch.isfinite(best)
    return sim_to_dist(best) < ratio * sim_to_dist(second)


def _top2_merge(
    v1: torch.Tensor, i1: torch.Tensor, v2: torch.Tensor, c: torch.Tensor, ci: torch.Tensor
):
    """Merge a running (best value, best index, second value) per column with a chunk's top-2
    (2, M)."""
    vals = torch.cat([v1[None], v2[None], c], 0)
    idx = torch.cat([i1[None], i1[None], ci], 0)
    top, pos = vals.topk(2, dim=0)
    return top[0], idx.gather(0, pos[:1])[0], top[1]


def mutual_nn_match(
    desc_a: torch.Tensor,
    desc_b: torch.Tensor,
    ratio: float | None = 0.8,
    chunk_size: int = 1024,
    mask_fn: MaskFn | None = None,
) -> torch.Tensor:
    """Mutual nearest neighbours of unit descriptors, each direction passing the ratio test.

    A pair (i, j) is kept when j is i's nearest neighbour in B, i is j's nearest neighbour in A, and
    both passes the ratio test (``ratio=None`` disables it). ``mask_fn`` restricts the candidates
    per direction (used by the epipolar-guided baseline); masked-out pairs are never nearest
    neighbours. Returns (K, 2) int64 indices, sorted by index in A.
    """
    n, m = desc_a.shape[0], desc_b.shape[0]
    dev = desc_a.device
    if n == 0 or m == 0:
        return torch.empty((0, 2), dtype=torch.int64, device=dev)
    neg = torch.tensor(-torch.inf, device=dev)
    row_best = torch.full((n,), -torch.inf, device=dev)
    row_idx = torch.zeros(n, dtype=torch.int64, device=dev)
    row_second = torch.full((n,), -torch.inf, device=dev)
    col_best = torch.full((m,), -torch.inf, device=dev)
    col_idx = torch.zeros(m, dtype=torch.int64, device=dev)
    col_second = torch.full((m,), -torch.inf, device=dev)
    for start in range(0, n, chunk_size):
        rows = torch.arange(start, min(start + chunk_size, n), device=dev)
        sim = desc_a[rows] @ desc_b.T
        sim_ab, sim_ba = sim, sim
        if mask_fn is not None:
            mask_ab, mask_ba = mask_fn(rows)
            sim_ab, sim_ba = torch.where(mask_ab, sim, neg), torch.where(mask_ba, sim, neg)
        k = min(2, m)
        top, pos = sim_ab.topk(k, dim=1)
        row_best[rows], row_idx[rows] = top[:, 0], pos[:, 0]
        if k == 2:
            row_second[rows] = top[:, 1]
        ctop, cpos = sim_ba.topk(min(2, len(rows)), dim=0)
        if ctop.shape[0] == 1:
            ctop = torch.cat([ctop, torch.full_like(ctop, -torch.inf)], 0)
            cpos = torch.cat([cpos, cpos], 0)
        col_best, col_idx, col_second = _top2_merge(
            col_best, col_idx, col_second, ctop, cpos + start
        )
    ok_a = ratio_pass(row_best, row_second, ratio) & torch.isfinite(row_best)
    ok_b = ratio_pass(col_best, col_second, ratio) & torch.isfinite(col_best)
    ia = torch.arange(n, device=dev)
    mutual = ok_a & ok_b[row_idx] & (col_idx[row_idx] == ia)
    return torch.stack([ia[mutual], row_idx[mutual]], 1)


# Lowe's ratio of the raw and guided matchers on ALIKED: 0.9 verified more related pairs than
# SIFT's 0.8 and no unrelated one (docs/RESULTS.md).
ALIKED_RATIO = 0.9


class RawMatcher(Matcher):
    """Mutual nearest neighbour + ratio test on all keypoints (the unguided baseline)."""

    name = "raw"
    feature_defaults = {"aliked": {"ratio": ALIKED_RATIO}}
    default_conf = {
        "ratio": 0.8,  # Lowe's ratio on Euclidean descriptor distance, both directions; None = off
        "device": "auto",  # 'auto' = CUDA when available, else CPU; or any torch device string
        "chunk_size": 1024,  # rows of A per similarity block: memory ~ chunk_size * len(B) floats
        # also drop matches whose descriptors' cosine similarity
        # is below this (learned features); None = off
        "min_similarity": None,
    }

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        self.device = resolve_device(self.conf["device"])

    def match(self, a: ImageData, b: ImageData) -> np.ndarray:
        da = normalize_descriptors(a.descriptors, self.device)
        db = normalize_descriptors(b.descriptors, self.device)
        m = mutual_nn_match(da, db, self.conf["ratio"], self.conf["chunk_size"])
        if self.conf["min_similarity"] is not None:
            m = m[(da[m[:, 0]] * db[m[:, 1]]).sum(1) >= self.conf["min_similarity"]]
        return m.cpu().numpy().astype(np.uint32)
