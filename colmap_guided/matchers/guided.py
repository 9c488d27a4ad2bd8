"""Guided keypoint matching (paper eq. 1): candidates only near the coarse match.

For a keypoint p^A with coarse match m^{A->B}(p^A), the match is

    j = argmin_{i : ||m^{A->B}(p^A) - p^B_i|| < W} ||f^A - f^B_i||        (eq. 1)

and symmetrically from B to A; mutual matches are kept, then an optional ratio test computed among
the candidates. B's keypoints are bucketed in a grid of cell W, so a query compares only the
keypoints of the 3x3 cells around its coarse match (never the dense N x M matrix); queries sharing a
cell share their candidates, and all cells go through a few padded batched matrix products of at
most ``max_pairs`` values each, so memory is bounded for 20k x 20k keypoints, on CPU or GPU. B -> A
is searched only for the B keypoints that some A keypoint chose (the others cannot be mutual).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import pycolmap
import torch

from colmap_guided import verify
from colmap_guided.coarse import CoarseMatcher
from colmap_guided.log import logger
from colmap_guided.matchers.base import ImageData, Matcher
from colmap_guided.matchers.raw import (
    ALIKED_RATIO,
    mutual_nn_match,
    normalize_descriptors,
    ratio_pass,
    resolve_device,
)


def _nearest_in_window(
    pred: torch.Tensor,
    desc_q: torch.Tensor,
    pts_t: torch.Tensor,
    desc_t: torch.Tensor,
    window: float,
    valid_q: torch.Tensor,
    max_pairs: int,
    rows: int = 16,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One direction of eq. 1: for each query, best and second-best candidate within ``window``.

    pred: (N, 2) coarse match of each query in the target image; pts_t: (M, 2) target keypoints.
    Target keypoints are bucketed in a grid of cell ``window``; queries whose coarse match falls in
    the same cell share their candidates (the 3x3 cells around it). Each cell's queries are cut in
    units of at most ``rows``; units, sorted by candidate count and padded, go through one batched
    matrix product per block of at most ``max_pairs`` gathered values, so a few blocks serve
    thousands of cells (no Python loop per cell) and memory stays bounded.
    Returns best similarity (N,), best target index (N,) and second-best similarity (N,); queries
    without any candidate get similarity -inf.
    """
    dev = pred.device
    n, m = pred.shape[0], pts_t.shape[0]
    best = torch.full((n,), -torch.inf, device=dev)
    best_idx = torch.zeros(n, dtype=torch.int64, device=dev)
    second = torch.full((n,), -torch.inf, device=dev)
    if n == 0 or m == 0:
        return best, best_idx, second

    queries, order, starts, lengths, n_cand, unit_start, unit_end = _window_units(
        pred, pts_t, window, valid_q, rows
    )
    found, found_at = _best_in_units(
        (desc_q, pred, desc_t, pts_t),
        (queries, order, starts, lengths, n_cand, unit_start),
        window,
        rows,
        max_pairs,
    )
    # Unit rows back to queries.
    row = unit_start[:, None] + torch.arange(rows, device=dev)
    real = row < unit_end[:, None]
    q = queries[row[real]]
    best[q], second[q] = found[0][real], found[1][real]
    # (a query without candidate: any index, best = -inf)
    best_idx[q] = order[found_at[real].clamp_(max=m - 1)]
    return best, best_idx, second


def _window_units(pred, pts_t, window: float, valid_q, rows: int) -> tuple:
    """The target keypoints bucketed in a grid of cell ``window``, the queries cut in units of at
    most ``rows`` sharing one cell, sorted by their candidates' count: (queries, target order,
    (U, 3) ranges of the sorted target order and their lengths, candidates, unit start and end)."""
    dev = pred.device
    # Target grid, cells sorted row-major: the three cells of one grid row around a query's cell are
    # one contiguous range of the sorted order.
    origin = pts_t.min(0).values
    tcell = torch.floor((pts_t - origin) / window).long()
    gw = int(tcell[:, 0].max()) + 1
    gh = int(tcell[:, 1].max()) + 1
    sorted_cell, order = torch.sort(tcell[:, 1] * gw + tcell[:, 0], stable=True)

    # Query cells; a coarse match more than one cell outside the grid has no candidate.
    qcell = (
        torch.floor((torch.nan_to_num(pred, nan=-1e9) - origin) / window)
        .clamp(-2, max(gw, gh) + 1)
        .long()
    )
    cx, cy = qcell[:, 0], qcell[:, 1]
    valid_q = (
        valid_q & torch.isfinite(pred).all(1) & (cx >= -1) & (cx <= gw) & (cy >= -1) & (cy <= gh)
    )
    queries = torch.nonzero(valid_q).flatten()
    key = (cy[queries] + 1) * (gw + 2) + (cx[queries] + 1)
    key, perm = torch.sort(key, stable=True)
    queries = queries[perm]
    group_key, group_size = torch.unique_consecutive(key, return_counts=True)
    gx, gy = group_key % (gw + 2) - 1, group_key // (gw + 2) - 1
    lo, hi = (gx - 1).clamp(min=0), (gx + 1).clamp(max=gw - 1)
    starts, lengths = [], []  # per group and grid row dy: a range of the sorted target order
    for dy in (-1, 0, 1):
        r = gy + dy
        s = torch.searchsorted(sorted_cell, r * gw + lo)
        e = torch.searchsorted(sorted_cell, r * gw + hi, right=True)
        starts.append(s)
        lengths.append(torch.where((r >= 0) & (r < gh), e - s, 0))
    starts, lengths = torch.stack(starts, 1), torch.stack(lengths, 1)  # (G, 3)

    # Units: up to ``rows`` queries of one group, sorted by candidate count.
    n_cand = lengths.sum(1)
    n_units = (group_size + rows - 1) // rows
    unit_group = torch.repeat_interleave(torch.arange(len(group_size), device=dev), n_units)
    unit_first = torch.repeat_interleave(torch.cumsum(n_units, 0) - n_units, n_units)
    group_first = torch.cumsum(group_size, 0) - group_size
    unit_start = (
        group_first[unit_group] + (torch.arange(len(unit_group), device=dev) - unit_first) * rows
    )
    unit_end = (group_first + group_size)[unit_group]
    by_count = torch.argsort(n_cand[unit_group])
    by_count = by_count[n_cand[unit_group[by_count]] > 0]
    unit_group, unit_start, unit_end = (
        unit_group[by_count],
        unit_start[by_count],
        unit_end[by_count],
    )
    starts, lengths, n_cand = starts[unit_group], lengths[unit_group], n_cand[unit_group]
    return queries, order, starts, lengths, n_cand, unit_start, unit_end


def _best_in_units(points: tuple, units: tuple, window: float, rows: int, max_pairs: int) -> tuple:
    """Best and second-best similarity (2, U, rows) of each unit row and the sorted target position
    of the best (U, rows): one batched product per block of at most ``max_pairs`` values."""
    desc_q, pred, desc_t, pts_t = points
    queries, order, starts, lengths, n_cand, unit_start = units
    dev, m, counts = pred.device, pts_t.shape[0], n_cand.tolist()

    # Descriptors and positions in sorted order once, so that blocks gather contiguous rows; a last
    # sentinel row (zero descriptor, infinitely far) pads units to their block's shape.
    def sorted_rows(x: torch.Tensor, at: torch.Tensor, pad: float) -> torch.Tensor:
        out = torch.empty(len(at) + 1, x.shape[1], dtype=x.dtype, device=dev)
        torch.index_select(x, 0, at, out=out[:-1])
        out[-1] = pad
        return out

    desc_q, pred = sorted_rows(desc_q, queries, 0.0), sorted_rows(pred, queries, torch.inf)
    desc_t, pts_t = sorted_rows(desc_t, order, 0.0), sorted_rows(pts_t, order, torch.inf)

    def rows_of(x: torch.Tensor, at: torch.Tensor) -> torch.Tensor:  # x[at], faster on CPU
        return x.index_select(0, at.flatten()).view(*at.shape, x.shape[1])

    w2 = float(window) ** 2
    per_cand = rows + desc_q.shape[1] + 4  # values gathered or computed per candidate of a unit
    # best and second-best similarity per unit row
    found = torch.empty(2, len(counts), rows, device=dev)
    # best's sorted target position
    found_at = torch.empty(len(counts), rows, dtype=torch.long, device=dev)
    i = 0
    while i < len(counts):  # blocks of units; the block's largest candidate count is its last
        j = i + 1
        while j < len(counts) and (j + 1 - i) * counts[j] * per_cand <= max_pairs:
            j += 1
        s, ln = starts[i:j], lengths[i:j]
        col = torch.arange(counts[j - 1], device=dev)[None]
        l0, l01 = ln[:, :1], ln[:, :1] + ln[:, 1:2]
        pos = torch.where(
            col < l0,
            s[:, :1] + col,
            torch.where(col < l01, s[:, 1:2] + col - l0, s[:, 2:] + col - l01),
        )
        # (U, C) candidates in sorted target order; m: sentinel
        pos = torch.where(col < n_cand[i:j, None], pos, m)
        # (U, rows)
        qpos = (unit_start[i:j, None] + torch.arange(rows, device=dev)).clamp_(max=len(queries))
        sim = torch.bmm(rows_of(desc_q, qpos), rows_of(desc_t, pos).transpose(1, 2))
        pq, pc = rows_of(pred, qpos), rows_of(pts_t, pos)
        d2 = (pq[..., 0, None] - pc[:, None, :, 0]).square_() + (
            pq[..., 1, None] - pc[:, None, :, 1]
        ).square_()
        sim.masked_fill_(d2 >= w2, -torch.inf)  # outside the window (or padding)
        top, at = sim.max(2)
        found[0, i:j], found_at[i:j] = top, pos.gather(1, at)
        found[1, i:j] = sim.scatter_(2, at[..., None], -torch.inf).amax(2)
        i = j
    return found, found_at


def guided_match(
    kpts_a: torch.Tensor,
    desc_a: torch.Tensor,
    kpts_b: torch.Tensor,
    desc_b: torch.Tensor,
    flow_ab: torch.Tensor,
    flow_ba: torch.Tensor,
    window_a: float,
    window_b: float,
    ratio: float | None = None,
    valid_ab: torch.Tensor | None = None,
    valid_ba: torch.Tensor | None = None,
    max_pairs: int = 1 << 20,
) -> torch.Tensor:
    """Mutual guided matches of eq. 1 given coarse flows in both directions.

    kpts_a (N, 2), kpts_b (M, 2): keypoint positions; desc_a, desc_b: unit-norm float descriptors
    (see ``normalize_descriptors``). flow_ab (N, 2): coarse match m^{A->B} of each keypoint of A in
    B's pixels; flow_ba (M, 2) the reverse. Candidates of p^A are B's keypoints strictly within
    ``window_b`` (B pixels) of flow_ab, candidates of p^B those within ``window_a`` of flow_ba.
    valid_ab / valid_ba (bool) drop keypoints whose coarse match is unreliable. ``ratio`` is Lowe's
    ratio test among the candidates, both directions (None = off; a lone candidate passes).
    Returns (K, 2) int64 indices (into A, into B), sorted by index in A.
    """
    dev = desc_a.device
    kpts_a, kpts_b = kpts_a[:, :2].to(dev, torch.float32), kpts_b[:, :2].to(dev, torch.float32)
    flow_ab, flow_ba = flow_ab.to(dev, torch.float32), flow_ba.to(dev, torch.float32)
    n, m = kpts_a.shape[0], kpts_b.shape[0]
    va = torch.ones(n, dtype=torch.bool, device=dev) if valid_ab is None else valid_ab.to(dev)
    vb = torch.ones(m, dtype=torch.bool, device=dev) if valid_ba is None else valid_ba.to(dev)
    best_ab, idx_ab, second_ab = _nearest_in_window(
        flow_ab, desc_a, kpts_b, desc_b, window_b, va, max_pairs
    )
    ok_a = torch.isfinite(best_ab) & ratio_pass(best_ab, second_ab, ratio)
    # Only B keypoints chosen by some A keypoint can be in a mutual match: B -> A for those alone.
    chosen = torch.zeros(m, dtype=torch.bool, device=dev)
    chosen[idx_ab[ok_a]] = True
    best_ba, idx_ba, second_ba = _nearest_in_window(
        flow_ba, desc_b, kpts_a, desc_a, window_a, vb & chosen, max_pairs
    )
    ok_b = torch.isfinite(best_ba) & ratio_pass(best_ba, second_ba, ratio)
    ia = torch.arange(n, device=dev)
    mutual = ok_a & ok_b[idx_ab] & (idx_ba[idx_ab] == ia)
    return torch.stack([ia[mutual], idx_ab[mutual]], 1)


@dataclass
class CoarseFlows:
    """The coarse network's guidance for one pair, at the keypoints of both images (numpy)."""

    flow_ab: np.ndarray  # (N, 2) m^{A->B} of A's keypoints, B pixels
    score_ab: np.ndarray  # (N,) coarse match score s^{A->B}
    fb_ab: np.ndarray  # (N,) forward-backward error, B pixels
    flow_ba: np.ndarray  # (M, 2) m^{B->A} of B's keypoints, A pixels
    score_ba: np.ndarray
    fb_ba: np.ndarray  # A pixels
    cell_a: float  # one coarse feature cell in A's / B's original pixels
    cell_b: float
    pair_score: (
        float  # eq. 3's image-level score: mean over cells of the best s, the smaller direction
    )


class GuidedMatcher(Matcher):
    """Eq. 1 guided by the coarse network of ``colmap_guided.coarse``.

    Backbone features are computed once per image and kept until ``release(name)``. Without filter
    weights (``weights=None`` and no shipped ``coarse_filter.safetensors``) it guides with the raw
    correlation of backbone features and says so with a WARNING.
    """

    name = "guided"
    # On ALIKED, min_agreement 0.6: its raw side (mutual NN of ALIKED descriptors) is the weaker
    # one, so a disagreeing guided side is kept down to 0.6. Historical proxy, 10 scenes x 3 seeds
    # (docs/RESULTS.md): runs below pycolmap's default pipeline 0 of 60 at 0.6, 4 at SIFT's 0.9.
    feature_defaults = {
        "aliked": {"ratio": ALIKED_RATIO, "raw_ratio": ALIKED_RATIO, "min_agreement": 0.6}
    }
    # applied after the coarse match
    flow_options = (
        "window_cells",
        "ratio",
        "raw_ratio",
        "min_score",
        "max_fb_cells",
        "raw_matches",
        "raw_min_inliers",
        "raw_below",
        "min_agreement",
    )
    default_conf = {
        # coarse filter weights; None = the shipped ones (raw-correlation fallback, with a WARNING)
        "weights": None,
        # 'auto' | 'filter' (weights required) | 'raw' (correlation only, untrained)
        "mode": "auto",
        "coarse": {},  # further CoarseMatcher options (backbone, resize_max, impl, cache_path, ...)
        # Window, ratio and min_inliers chosen on same-scene and unrelated pairs: without a ratio
        # test unrelated photos verify, and a wrong flow gathers chance inliers (docs/RESULTS.md).
        # W of eq. 1 in coarse cells (1 cell = 16 px at the network input scale, as the paper)
        "window_cells": 1.0,
        "ratio": 0.8,  # Lowe's ratio among the candidates, both directions; None = off
        # two-view verification of guided pairs: at least this many inliers (COLMAP: 15)
        "min_inliers": 25,
        # Lowe's ratio of the raw matches below (mutual NN over all keypoints), whatever ``ratio``
        # is; None = off. Without a window a looser ratio verifies unrelated photos.
        "raw_ratio": 0.8,
        # Raw matches (mutual NN + ratio) beside the guided ones, for pairs where the coarse flow is
        # wrong:
        # 'verified': verify guided and raw (guided: min_inliers; raw: raw_min_inliers) and keep the
        # one that passes; when both do and agree (min_agreement), the one with the most inliers
        # among them and the union of their inliers (verified, min_inliers), else raw
        # (``verify.best_of``, in the pair's worker: the pair is not verified again);
        # 'merge': add raw matches of keypoints that guidance left unmatched, unverified; None:
        # guided only.
        "raw_matches": "verified",
        # raw matches kept by 'verified' pass with COLMAP's 15, as in plain COLMAP
        "raw_min_inliers": 15,
        # 'verified': raw matching is skipped for pairs whose guided matches verify at least this
        # many inliers (they are kept as they are); None: raw matching on every pair
        "raw_below": None,
        # 'verified', both sides pass: share of each side's inliers within the RANSAC threshold of
        # the other's epipolar geometry, both ways, below which the pair keeps its raw matches
        # (chosen on the development split, docs/RESULTS.md).
        "min_agreement": 0.9,
        # drop keypoints whose coarse forward-backward error exceeds this many cells
        "max_fb_cells": None,
        # drop keypoints whose coarse match score (softmax probability) is below this
        "min_score": None,
        "device": "auto",  # torch device: auto = CUDA when available, else CPU; or cpu, cuda, ...
        # pairs matched at once by match_database; 'auto':
        # one per CPU core on CPU with 1 torch thread, else 1
        "workers": "auto",
        "max_pairs": 1 << 20,  # values gathered or computed per block of eq. 1: bounds memory
    }

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        self.device = resolve_device(self.conf["device"])
        coarse_conf = {
            **self.conf["coarse"],
            "device": str(self.device),
            "weights": self.conf["weights"],
        }
        mode = self.conf["mode"]
        if self.conf["raw_matches"] not in (None, "merge", "verified"):
            raise ValueError(
                f"raw_matches must be None, 'merge' or 'verified', got {self.conf['raw_matches']!r}"
            )
        if mode not in ("auto", "filter", "raw"):
            raise ValueError(f"mode must be 'auto', 'filter' or 'raw', got {mode!r}")
        if mode == "auto":
            try:
                self.coarse = CoarseMatcher({**coarse_conf, "mode": "filter"})
            except FileNotFoundError as error:
                if self.conf["weights"] is not None:
                    raise
                logger.warning(
                    "No trained coarse filter (%s): guided matching falls back to "
                    "the raw correlation of backbone features (untrained, weaker "
                    "guidance). Install or train weights, or pass weights=PATH.",
                    error,
                )
                self.coarse = CoarseMatcher({**coarse_conf, "mode": "raw"})
        else:
            self.coarse = CoarseMatcher({**coarse_conf, "mode": mode})
        self.torch_threads = self.coarse.torch_threads
        workers = self.conf["workers"]
        # a pair is hundreds of small ops on one torch thread: pairs in parallel use the cores
        if workers == "auto":
            cores = (
                len(os.sched_getaffinity(0))
                if hasattr(os, "sched_getaffinity")
                else os.cpu_count() or 1
            )
            workers = (
                min(8, cores)
                if self.device.type == "cpu"
                and (self.torch_threads or torch.get_num_threads()) == 1
                else 1
            )
        if not isinstance(workers, int) or isinstance(workers, bool) or workers < 1:
            raise ValueError(f"workers must be 'auto' or a positive integer, got {workers!r}")
        self.pair_workers = workers

    def describe(self) -> dict:
        return {
            **super().describe(),
            "pair_workers": self.pair_workers,
            "coarse": self.coarse.describe(),
        }

    @property
    def verification_conf(self) -> dict:
        """With 'verified' raw matches the matcher applies the guided threshold itself
        (``verify.best_of``) and verifies at the raw threshold."""
        if self.conf["raw_matches"] == "verified":
            return {"min_num_inliers": min(self.conf["raw_min_inliers"], self.conf["min_inliers"])}
        return {"min_num_inliers": self.conf["min_inliers"]}

    def prepare(self, image: ImageData) -> None:
        self.features(image)

    def retrieval_backbone(self) -> CoarseMatcher:
        return self.coarse

    def features(self, image: ImageData):
        """Backbone features of ``image`` (cached by name until ``release``, and in ``image.extra``:
        an image sent to another process carries them, so the worker needs neither the photo nor the
        backbone pass)."""
        # the backbone, its weights (a fine-tuned one too) and input size
        key = f"coarse/{self.coarse.features_key}"
        if key in image.extra:
            return image.extra[key]
        feats = self.coarse.extract_path(image.path, image.name)
        if (feats.geometry.width, feats.geometry.height) != (image.width, image.height):
            raise ValueError(
                f"{image.path} is {feats.geometry.width}x{feats.geometry.height} "
                f"pixels but its keypoints are for {image.width}x{image.height}: "
                "the image file is not the one the features were extracted from."
            )
        image.extra[key] = feats
        return feats

    def coarse_flows(self, a: ImageData, b: ImageData) -> CoarseFlows:
        """Coarse match of the pair, evaluated at both images' keypoints."""
        result = self.coarse.match(self.features(a), self.features(b))
        flow_ab, score_ab, fb_ab = result.flow_ab(a.keypoints[:, :2])
        flow_ba, score_ba, fb_ba = result.flow_ba(b.keypoints[:, :2])
        pair_score = float(min(result.matches.score_ab.mean(), result.matches.score_ba.mean()))
        return CoarseFlows(
            flow_ab,
            score_ab,
            fb_ab,
            flow_ba,
            score_ba,
            fb_ba,
            result.cell_size_a,
            result.cell_size_b,
            pair_score,
        )

    def match_flows(
        self, a: ImageData, b: ImageData, flows: CoarseFlows, **overrides
    ) -> np.ndarray:
        """Eq. 1 given the coarse flows; ``overrides`` replace options of ``flow_options``
        (the benchmark's sweep)."""
        return self.flows_verified(a, b, flows, self.verification_conf, **overrides)[0]

    def flows_verified(
        self, a: ImageData, b: ImageData, flows: CoarseFlows, verification: dict, **overrides
    ) -> tuple[np.ndarray, pycolmap.TwoViewGeometry | None]:
        """``match_flows`` and, with 'verified' raw matches, the geometry of the matches that
        ``verify.best_of`` chose (``Matcher.match_verified``)."""
        conf = self.flow_conf(overrides)
        dev = self.device

        def valid(score: np.ndarray, fb: np.ndarray, cell: float) -> torch.Tensor:
            ok = np.ones(len(score), bool)
            if conf["min_score"] is not None:
                ok &= score >= conf["min_score"]
            if conf["max_fb_cells"] is not None:
                ok &= fb <= conf["max_fb_cells"] * cell
            return torch.from_numpy(ok)

        da, db = (
            normalize_descriptors(a.descriptors, dev),
            normalize_descriptors(b.descriptors, dev),
        )
        m = (
            guided_match(
                torch.tensor(a.keypoints[:, :2], dtype=torch.float32),
                da,
                torch.tensor(b.keypoints[:, :2], dtype=torch.float32),
                db,
                torch.tensor(flows.flow_ab, dtype=torch.float32),
                torch.tensor(flows.flow_ba, dtype=torch.float32),
                conf["window_cells"] * flows.cell_a,
                conf["window_cells"] * flows.cell_b,
                conf["ratio"],
                valid(flows.score_ab, flows.fb_ab, flows.cell_b),
                valid(flows.score_ba, flows.fb_ba, flows.cell_a),
                conf["max_pairs"],
            )
            .cpu()
            .numpy()
        )

        def raw() -> np.ndarray:
            with self.timed("raw"):
                return mutual_nn_match(da, db, conf["raw_ratio"]).cpu().numpy()

        if conf["raw_matches"] == "merge":
            m = verify.union(m, raw())
        elif conf["raw_matches"] == "verified":
            cam_a, cam_b = (
                im.camera or verify.default_camera(im.width, im.height) for im in (a, b)
            )
            with self.timed("choice"):
                return verify.best_of(
                    cam_a,
                    a.keypoints,
                    cam_b,
                    b.keypoints,
                    m,
                    raw,
                    verify.two_view_options(verification),
                    conf["min_inliers"],
                    conf["raw_min_inliers"],
                    conf["min_agreement"],
                    conf["raw_below"],
                )
        return m.astype(np.uint32), None

    def match_verified(self, a: ImageData, b: ImageData, verification: dict) -> tuple:
        return self.match_guided(
            a, b, lambda a, b, flows: self.flows_verified(a, b, flows, verification)
        )

    def match(self, a: ImageData, b: ImageData) -> np.ndarray:
        return self.match_verified(a, b, self.verification_conf)[0]

    def release(self, name: str) -> None:
        self.coarse.release(name)
