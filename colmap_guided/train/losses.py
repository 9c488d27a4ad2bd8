"""The three supervisions of the paper (§4.2), on batched, zero-padded 4D volumes.

Shapes (batch of B pairs, feature grids hA×wA and hB×wB padded to a common batch shape):
    s_ab    (B, hA, wA, hB, wB)  softmax of the filtered volume over B's dimensions  (s^{A→B})
    s_ba    (B, hA, wA, hB, wB)  softmax over A's dimensions                         (s^{B→A})
    mask_a  (B, hA, wA) bool     True on real (not zero-padded) feature cells of A; mask_b likewise.
    positive (B,) bool           y_AB = +1 (same scene) or -1 (different scenes).

The total loss is the paper's eq. (2), L = Σ_pairs l^{A→B}(s^{A→B}) + l^{B→A}(s^{B→A}); every
function here returns the mean over the batch of l^{A→B} + l^{B→A} (a constant factor that Adam
ignores) and a dict of detached statistics for logging.

Normalisation choices (documented departures from the letter of the paper):
* image level (eq. 3) sums max s over all features of A; we average over the valid cells instead, so
  pairs with different grid sizes weigh the same (NCNet's released code also averages).
* point supervision (eq. 6) sums over features of A that have a ground-truth match; we average over
  them, for the same reason. Negative pairs carry no point loss (the paper uses no negative term).
* the epipolar loss (eq. 5) is already normalised by |N| and |P|; an empty set contributes 0.
"""

from __future__ import annotations

import torch

NEG_INF = float("-inf")


def directional_softmax(
    scores: torch.Tensor, mask_a: torch.Tensor | None = None, mask_b: torch.Tensor | None = None
):
    """s^{A→B} (softmax over B's cells) and s^{B→A} (over A's cells), ignoring zero-padded cells.

    scores: (B, hA, wA, hB, wB) filtered correlation. Padded cells get probability 0 in the
    direction where they are candidates; rows of padded source cells are left finite and must be
    masked by the losses (they are).
    """
    b, ha, wa, hb, wb = scores.shape
    flat = scores.reshape(b, ha * wa, hb * wb)
    if mask_b is not None:
        flat_ab = flat.masked_fill(~mask_b.reshape(b, 1, hb * wb), NEG_INF)
    else:
        flat_ab = flat
    if mask_a is not None:
        flat_ba = flat.masked_fill(~mask_a.reshape(b, ha * wa, 1), NEG_INF)
    else:
        flat_ba = flat
    s_ab = torch.softmax(flat_ab, dim=2)
    s_ba = torch.softmax(flat_ba, dim=1)
    return s_ab.reshape(scores.shape), s_ba.reshape(scores.shape)


def _flat(s_ab, s_ba, mask_a, mask_b):
    """Per-direction flattened views: (B, n_src, n_tgt) with the source first, and source masks."""
    b, ha, wa, hb, wb = s_ab.shape
    ab = s_ab.reshape(b, ha * wa, hb * wb)
    ba = s_ba.reshape(b, ha * wa, hb * wb).transpose(1, 2)  # source B, target A
    ma = (
        torch.ones(b, ha * wa, dtype=torch.bool, device=s_ab.device)
        if mask_a is None
        else mask_a.reshape(b, -1)
    )
    mb = (
        torch.ones(b, hb * wb, dtype=torch.bool, device=s_ab.device)
        if mask_b is None
        else mask_b.reshape(b, -1)
    )
    return ab, ba, ma, mb


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over the last dim of the entries where mask is True; 0 where there are none."""
    m = mask.to(values.dtype)
    return (values * m).sum(-1) / m.sum(-1).clamp(min=1.0)


def image_loss(s_ab, s_ba, positive, mask_a=None, mask_b=None):
    """Weak image-level supervision, NCNet's loss (eq. 3): l^{A→B} = −y_AB · mean_{ij} max_{kl}
    s^{A→B}_{ijkl}."""
    ab, ba, ma, mb = _flat(s_ab, s_ba, mask_a, mask_b)
    return image_loss_from_best(ab.amax(dim=2), ba.amax(dim=2), positive, ma, mb)


def image_loss_from_best(best_ab, best_ba, positive, ma, mb):
    """Eq. 3 from max_{kl} s^{A→B} (B, nA) and max s^{B→A} (B, nB) of every source cell, masks
    (B, n)."""
    y = positive.to(best_ab.dtype) * 2 - 1
    mean_ab = _masked_mean(best_ab, ma)
    mean_ba = _masked_mean(best_ba, mb)
    per_pair = -y * (mean_ab + mean_ba)
    stats = {
        "max_pos": ((mean_ab + mean_ba) / 2)[positive].mean().item()
        if positive.any()
        else float("nan"),
        "max_neg": ((mean_ab + mean_ba) / 2)[~positive].mean().item()
        if (~positive).any()
        else float("nan"),
    }
    return per_pair.mean(), stats


def epipolar_distance(F: torch.Tensor, x_src: torch.Tensor, x_tgt: torch.Tensor) -> torch.Tensor:
    """Paper eq. (4): distance of x_tgt to the epipolar line F·x_src, in the target image's pixels.

    F: (B, 3, 3) with x_tgt^T F x_src = 0; x_src, x_tgt: (B, N, 2) pixel coordinates.
    """
    ones = torch.ones_like(x_src[..., :1])
    lines = torch.cat([x_src, ones], -1) @ F.transpose(1, 2)  # (B, N, 3): (F x_src)^T
    num = (lines[..., :2] * x_tgt).sum(-1) + lines[..., 2]
    return num.abs() / lines[..., :2].norm(dim=-1).clamp(min=1e-12)


def _epipolar_direction(best, idx, F, x_src, x_tgt, m_src, positive, lam):
    """One direction of eq. (5) from max_{kl} s (B, n_src) and its argmax (B, n_src) into the target
    cells; F maps source points to target lines."""
    with torch.no_grad():
        x_hit = torch.gather(x_tgt, 1, idx.unsqueeze(-1).expand(-1, -1, 2))
        d = epipolar_distance(F, x_src, x_hit)
        P = m_src & (d < lam) & positive[:, None]
        N = m_src & ~P
    loss = 0.5 * _masked_mean(best, N) - _masked_mean(best, P)
    return loss, P, N


def epipolar_loss(s_ab, s_ba, positive, F, xy_a, xy_b, mask_a=None, mask_b=None, lam: float = 16.0):
    """Weak epipolar supervision (eq. 4–5), both directions.

    F: (B, 3, 3) fundamental matrices with x_B^T F x_A = 0 in the frame of xy_a / xy_b (any value
    for negative pairs); xy_a: (B, hA, wA, 2) and xy_b: (B, hB, wB, 2) pixel centres (x, y) of the
    feature cells in that frame; lam: threshold λ on the epipolar distance, one feature-cell spacing
    in that frame. P = valid source cells whose argmax lies within λ of the epipolar line; N its
    complement (all valid cells of negative pairs).
    """
    ab, ba, ma, mb = _flat(s_ab, s_ba, mask_a, mask_b)
    b = ab.shape[0]
    best_ab, idx_ab = ab.max(dim=2)
    best_ba, idx_ba = ba.max(dim=2)
    return epipolar_loss_from_best(
        best_ab,
        idx_ab,
        best_ba,
        idx_ba,
        positive,
        F,
        xy_a.reshape(b, -1, 2),
        xy_b.reshape(b, -1, 2),
        ma,
        mb,
        lam,
    )


def epipolar_loss_from_best(
    best_ab, idx_ab, best_ba, idx_ba, positive, F, xa, xb, ma, mb, lam: float = 16.0
):
    """Eq. 4–5 from max s^{A→B} (B, nA) with its argmax among B's cells (B, nA) and the same for B →
    A; xa (B, nA, 2), xb (B, nB, 2) cell centres in F's frames; ma (B, nA), mb (B, nB) valid cells.
    Shared by the dense path (``epipolar_loss``) and the sparse one (``trainer``: one pair at a
    time)."""
    xa, xb, F = xa.to(best_ab.dtype), xb.to(best_ab.dtype), F.to(best_ab.dtype)
    l_ab, P_ab, _ = _epipolar_direction(best_ab, idx_ab, F, xa, xb, ma, positive, lam)
    l_ba, P_ba, _ = _epipolar_direction(
        best_ba, idx_ba, F.transpose(1, 2), xb, xa, mb, positive, lam
    )
    with torch.no_grad():
        pos = positive
        n_valid = ma.sum(1) + mb.sum(1)
        frac = (P_ab.sum(1) + P_ba.sum(1)).float() / n_valid.clamp(min=1).float()
        best = (_masked_mean(best_ab, ma) + _masked_mean(best_ba, mb)) / 2
    stats = {
        "epi_inlier_frac": frac[pos].mean().item() if pos.any() else float("nan"),
        "max_pos": best[pos].mean().item() if pos.any() else float("nan"),
        "max_neg": best[~pos].mean().item() if (~pos).any() else float("nan"),
    }
    return (l_ab + l_ba).mean(), stats


def point_loss(s_ab, s_ba, positive, matches, mask_a=None, mask_b=None):
    """Point supervision (eq. 6): l^{A→B} = −mean_{ij ∈ M} max_{kl ∈ M^{A→B}(ij)} s^{A→B}_{ijkl}.

    matches: (B, K, 2) long, flat cell indices (i·wA + j, k·wB + l) of ground-truth matches, each
    point assigned to the cell whose centre is nearest; rows with −1 are padding. Negative pairs and
    pairs without matches contribute 0.
    """
    ab, ba, ma, mb = _flat(s_ab, s_ba, mask_a, mask_b)
    b, na, nb = ab.shape
    valid = (matches[..., 0] >= 0) & (matches[..., 1] >= 0) & positive[:, None]
    ia = matches[..., 0].clamp(min=0)
    ib = matches[..., 1].clamp(min=0)
    batch = torch.arange(b, device=ab.device)[:, None].expand_as(ia)

    def direction(s, src, tgt, n_src):
        vals = s[batch, src, tgt]  # (B, K)
        vals = torch.where(valid, vals, torch.full_like(vals, NEG_INF))
        best = torch.full((b, n_src), NEG_INF, dtype=s.dtype, device=s.device)
        best = best.scatter_reduce(1, src, vals, reduce="amax", include_self=True)
        has = torch.isfinite(best)
        return _masked_mean(torch.where(has, best, torch.zeros_like(best)), has), has

    m_ab, has_a = direction(ab, ia, ib, na)
    m_ba, has_b = direction(ba, ib, ia, nb)
    per_pair = -(m_ab + m_ba)
    n = has_a.any(1) | has_b.any(1)  # pairs that carry point supervision
    loss = _masked_mean(per_pair, n)
    with torch.no_grad():
        stats = {"gt_prob": ((m_ab + m_ba) / 2)[n].mean().item() if n.any() else float("nan")}
    return loss, stats


def coarse_loss(supervision: str, s_ab, s_ba, batch: dict, lam: float = 16.0):
    """Dispatch on the supervision name ('image', 'epipolar', 'points') with a batch dict from
    train.data."""
    common = dict(mask_a=batch.get("mask_a"), mask_b=batch.get("mask_b"))
    if supervision == "image":
        return image_loss(s_ab, s_ba, batch["positive"], **common)
    if supervision == "epipolar":
        return epipolar_loss(
            s_ab,
            s_ba,
            batch["positive"],
            batch["F"],
            batch["xy_a"],
            batch["xy_b"],
            lam=lam,
            **common,
        )
    if supervision == "points":
        return point_loss(s_ab, s_ba, batch["positive"], batch["matches"], **common)
    raise ValueError(f"unknown supervision {supervision!r}; choose image, epipolar or points")
