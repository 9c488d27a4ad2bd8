"""Losses of §4.2 on hand-built volumes whose values are computed by hand, and against loop
references."""

import math

import numpy as np
import pytest
import torch

from colmap_guided.train.losses import (
    coarse_loss,
    directional_softmax,
    epipolar_distance,
    epipolar_loss,
    image_loss,
    point_loss,
)

# A: one row of two cells, centres x = 8 and 24 (y = 8); B: the same grid.
# s_ab[a, b] (softmax over b):  a0 -> [0.7, 0.3],  a1 -> [0.4, 0.6]
# s_ba[a, b] (softmax over a):  b0 -> [0.8, 0.2],  b1 -> [0.55, 0.45]
S_AB = torch.tensor([[0.7, 0.3], [0.4, 0.6]], dtype=torch.float64).reshape(1, 1, 2, 1, 2)
S_BA = torch.tensor([[0.8, 0.55], [0.2, 0.45]], dtype=torch.float64).reshape(1, 1, 2, 1, 2)
XY = torch.tensor([[8.0, 8.0], [24.0, 8.0]], dtype=torch.float64).reshape(1, 1, 2, 2)
# Epipolar line of (u, v) in A is the vertical line x = u in B: l = F (u, v, 1) = (1, 0, -u).
F_VERTICAL = torch.tensor([[0, 0, 1], [0, 0, 0], [-1, 0, 0]], dtype=torch.float64).reshape(1, 3, 3)


def _two(t):
    return torch.cat([t, t], 0)


def test_image_loss_hand_values():
    pos = torch.tensor([True])
    loss, _ = image_loss(S_AB, S_BA, pos)
    # mean max A->B = (0.7 + 0.6) / 2, B->A = (0.8 + 0.55) / 2
    assert loss.item() == pytest.approx(-(0.65 + 0.675))
    loss, _ = image_loss(S_AB, S_BA, ~pos)
    assert loss.item() == pytest.approx(0.65 + 0.675)
    loss, _ = image_loss(_two(S_AB), _two(S_BA), torch.tensor([True, False]))
    assert loss.item() == pytest.approx(0.0)
    # masking A's second cell removes it from the A->B mean only
    mask_a = torch.tensor([[[True, False]]])
    loss, _ = image_loss(S_AB, S_BA, pos, mask_a=mask_a)
    assert loss.item() == pytest.approx(-(0.7 + 0.675))


def test_epipolar_loss_hand_values():
    pos = torch.tensor([True])
    # A->B: a0 argmax b0 (x=8, on line x=8), a1 argmax b1 (x=24, on x=24): P = {a0, a1}, N = {}
    #   l_ab = -(0.7 + 0.6) / 2 = -0.65
    # B->A: b0 argmax a0 (x=8, line x=8): P; b1 argmax a0 (x=8, line x=24, distance 16): N with λ=10
    #   l_ba = 0.5 * 0.55 - 0.8 = -0.525
    loss, stats = epipolar_loss(S_AB, S_BA, pos, F_VERTICAL, XY, XY, lam=10.0)
    assert loss.item() == pytest.approx(-0.65 - 0.525)
    assert stats["epi_inlier_frac"] == pytest.approx(3 / 4)
    # λ = 17 > 16: b1 becomes a positive too: l_ba = -(0.8 + 0.55) / 2
    loss, _ = epipolar_loss(S_AB, S_BA, pos, F_VERTICAL, XY, XY, lam=17.0)
    assert loss.item() == pytest.approx(-0.65 - 0.675)
    # negative pair: every cell in N, positive term zero: 0.5 * 0.65 + 0.5 * 0.675
    loss, _ = epipolar_loss(S_AB, S_BA, ~pos, F_VERTICAL, XY, XY, lam=10.0)
    assert loss.item() == pytest.approx(0.5 * 0.65 + 0.5 * 0.675)
    # F^T = -F here: same lines, same loss (the sign of F does not matter)
    loss_t, _ = epipolar_loss(S_AB, S_BA, pos, F_VERTICAL.transpose(1, 2), XY, XY, lam=10.0)
    assert loss_t.item() == pytest.approx(-0.65 - 0.525)
    # shifting B's cells right by 16 px: a0's match (b0, now at x=24) is off its line x=8 -> N
    xy_b = XY + torch.tensor([16.0, 0.0], dtype=torch.float64)
    loss, _ = epipolar_loss(S_AB, S_BA, pos, F_VERTICAL, XY, xy_b, lam=10.0)
    # A->B: a0 -> b0 at x=24, line x=8: N; a1 -> b1 at x=40, line x=24: N  => l_ab = 0.5 * 0.65
    # B->A: b0 (x=24) line x=24, argmax a0 at x=8: N; b1 (x=40) argmax a0: N => l_ba = 0.5 * 0.675
    assert loss.item() == pytest.approx(0.5 * 0.65 + 0.5 * 0.675)


def test_point_loss_hand_values():
    pos = torch.tensor([True])
    # GT matches (a0, b1), (a0, b0), (a1, b1) and one padding row
    matches = torch.tensor([[[0, 1], [0, 0], [1, 1], [-1, -1]]])
    loss, _ = point_loss(S_AB, S_BA, pos, matches)
    # A->B: a0: max(0.3, 0.7) = 0.7; a1: 0.6 -> mean 0.65
    # B->A: b1: max(s_ba[a0,b1] = 0.55, s_ba[a1,b1] = 0.45) = 0.55; b0: 0.8 -> mean 0.675
    assert loss.item() == pytest.approx(-(0.65 + 0.675))
    # only (a1, b0): A->B 0.4, B->A 0.2
    loss, _ = point_loss(S_AB, S_BA, pos, torch.tensor([[[1, 0]]]))
    assert loss.item() == pytest.approx(-(0.4 + 0.2))
    # a negative pair in the batch is ignored (no point supervision on negatives)
    loss, _ = point_loss(_two(S_AB), _two(S_BA), torch.tensor([True, False]), _two(matches))
    assert loss.item() == pytest.approx(-(0.65 + 0.675))


def test_point_loss_gradient_reaches_only_the_best_gt_entry():
    s_ab = S_AB.clone().requires_grad_(True)
    s_ba = S_BA.clone().requires_grad_(True)
    matches = torch.tensor([[[0, 1], [0, 0]]])
    loss, _ = point_loss(s_ab, s_ba, torch.tensor([True]), matches)
    loss.backward()
    g_ab = s_ab.grad.reshape(2, 2)
    g_ba = s_ba.grad.reshape(2, 2)
    # A->B: a0 is the only source cell, its best GT entry is b0 (0.7): gradient -1 there only
    assert torch.equal(g_ab, torch.tensor([[-1.0, 0.0], [0.0, 0.0]], dtype=torch.float64))
    # B->A: b0 (0.8) and b1 (0.55) each have one GT entry, both from a0; mean over 2 sources
    assert torch.equal(g_ba, torch.tensor([[-0.5, -0.5], [0.0, 0.0]], dtype=torch.float64))


def test_directional_softmax_masks_padding():
    torch.manual_seed(0)
    scores = torch.randn(2, 3, 4, 2, 5)
    mask_a = torch.ones(2, 3, 4, dtype=torch.bool)
    mask_b = torch.ones(2, 2, 5, dtype=torch.bool)
    mask_a[1, 2:, :] = False
    mask_b[1, :, 3:] = False
    s_ab, s_ba = directional_softmax(scores, mask_a, mask_b)
    assert torch.allclose(s_ab.sum((3, 4)), torch.ones(2, 3, 4))
    assert torch.allclose(s_ba.sum((1, 2)), torch.ones(2, 2, 5))
    assert s_ab[1, :, :, :, 3:].abs().max() == 0 and s_ba[1, 2:].abs().max() == 0
    # the valid part of pair 1 equals the softmax of the cropped volume
    crop = scores[1, :2, :, :, :3].reshape(8, 6)
    assert torch.allclose(s_ab[1, :2, :, :, :3].reshape(8, 6), torch.softmax(crop, 1))
    assert torch.allclose(s_ba[1, :2, :, :, :3].reshape(8, 6), torch.softmax(crop, 0))


def _epipolar_reference(s_ab, s_ba, positive, F, xy_a, xy_b, mask_a, mask_b, lam):
    """Loop implementation of eq. (4)-(5), straight from the paper's formulas."""
    total = 0.0
    B, ha, wa, hb, wb = s_ab.shape
    for n in range(B):
        for direction in ("ab", "ba"):
            if direction == "ab":
                src_cells = [(i, j) for i in range(ha) for j in range(wa) if mask_a[n, i, j]]

                def vol(c):
                    return s_ab[n, c[0], c[1]]

                Fn, xs, xt = F[n], xy_a[n], xy_b[n]
            else:
                src_cells = [(k, l_) for k in range(hb) for l_ in range(wb) if mask_b[n, k, l_]]

                def vol(c):
                    return s_ba[n, :, :, c[0], c[1]]

                Fn, xs, xt = F[n].T, xy_b[n], xy_a[n]
            P, N = [], []
            for c in src_cells:
                v = vol(c)
                best = float(v.max())
                t = np.unravel_index(int(v.argmax()), v.shape)
                x = np.array([*xs[c[0], c[1]], 1.0])
                line = Fn @ x
                y = np.array([*xt[t[0], t[1]], 1.0])
                d = abs(line @ y) / math.hypot(line[0], line[1])
                (P if positive[n] and d < lam else N).append(best)
            total += (0.5 * np.mean(N) if N else 0.0) - (np.mean(P) if P else 0.0)
    return total / B


def _random_case(seed, B=3, ha=3, wa=4, hb=5, wb=2):
    g = torch.Generator().manual_seed(seed)
    scores = torch.randn(B, ha, wa, hb, wb, generator=g, dtype=torch.float64) * 3
    mask_a = torch.ones(B, ha, wa, dtype=torch.bool)
    mask_b = torch.ones(B, hb, wb, dtype=torch.bool)
    mask_a[0, -1] = False
    mask_b[1, :, -1] = False
    s_ab, s_ba = directional_softmax(scores, mask_a, mask_b)
    ya, xa = torch.meshgrid(torch.arange(ha) * 16.0 + 8, torch.arange(wa) * 16.0 + 8, indexing="ij")
    yb, xb = torch.meshgrid(torch.arange(hb) * 16.0 + 8, torch.arange(wb) * 16.0 + 8, indexing="ij")
    xy_a = torch.stack([xa, ya], -1).expand(B, -1, -1, -1).double()
    xy_b = torch.stack([xb, yb], -1).expand(B, -1, -1, -1).double()
    F = torch.randn(B, 3, 3, generator=g, dtype=torch.float64)
    F[:, 2, 2] *= 40  # keep lines in the image region
    positive = torch.tensor([True, False, True][:B])
    return s_ab, s_ba, positive, F, xy_a, xy_b, mask_a, mask_b


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_epipolar_loss_matches_loop_reference(seed):
    s_ab, s_ba, positive, F, xy_a, xy_b, mask_a, mask_b = _random_case(seed)
    for lam in (4.0, 16.0, 40.0):
        loss, _ = epipolar_loss(s_ab, s_ba, positive, F, xy_a, xy_b, mask_a, mask_b, lam=lam)
        ref = _epipolar_reference(
            s_ab.numpy(),
            s_ba.numpy(),
            positive.numpy(),
            F.numpy(),
            xy_a.numpy(),
            xy_b.numpy(),
            mask_a.numpy(),
            mask_b.numpy(),
            lam,
        )
        assert loss.item() == pytest.approx(ref, abs=1e-12)


def test_epipolar_distance_on_real_geometry():
    """Two pinhole cameras, a projected 3D point: distance 0 on the line, known offset off it."""
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    R = np.array([[np.cos(0.2), 0, np.sin(0.2)], [0, 1, 0], [-np.sin(0.2), 0, np.cos(0.2)]])
    t = np.array([-1.0, 0.1, 0.2])
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(K).T @ tx @ R @ np.linalg.inv(K)
    X = np.array([[0.3, -0.2, 5.0], [-1.0, 0.5, 8.0]])
    xa = (K @ X.T).T
    xa = xa[:, :2] / xa[:, 2:]
    Xb = (R @ X.T).T + t
    xb = (K @ Xb.T).T
    xb = xb[:, :2] / xb[:, 2:]
    d = epipolar_distance(torch.tensor(F)[None], torch.tensor(xa)[None], torch.tensor(xb)[None])
    assert d.abs().max().item() < 1e-9
    line = F @ np.array([*xa[0], 1.0])
    normal = line[:2] / np.linalg.norm(line[:2])
    moved = torch.tensor(xb[0] + 7.0 * normal)[None, None]
    d = epipolar_distance(torch.tensor(F)[None], torch.tensor(xa[:1])[None], moved)
    assert d.item() == pytest.approx(7.0, abs=1e-9)


def test_losses_train_a_filter_in_the_right_direction():
    """Gradient steps on the raw scores with the epipolar loss move argmaxes onto the epipolar
    lines."""
    s_ab, s_ba, positive, F, xy_a, xy_b, mask_a, mask_b = _random_case(5, B=2)
    positive = torch.tensor([True, True])
    g = torch.Generator().manual_seed(5)
    scores = (torch.randn(s_ab.shape, generator=g, dtype=torch.float64)).requires_grad_(True)
    opt = torch.optim.Adam([scores], lr=0.1)
    batch = dict(positive=positive, F=F, xy_a=xy_a, xy_b=xy_b, mask_a=mask_a, mask_b=mask_b)
    first = None
    for _ in range(60):
        sa, sb = directional_softmax(scores, mask_a, mask_b)
        loss, stats = coarse_loss("epipolar", sa, sb, batch, lam=16.0)
        first = stats["epi_inlier_frac"] if first is None else first
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert stats["epi_inlier_frac"] >= first + 0.3  # 0.45 -> 1.0 measured
    assert stats["max_pos"] > 0.9  # P's maxima are sharpened towards 1
    with pytest.raises(ValueError):
        coarse_loss("pixels", sa, sb, batch)


def test_sparse_training_path_equals_dense_with_full_support():
    """The sparse filter the CPU path runs (CoarseNet.sparse_volume + sparse_best) gives the dense
    epipolar loss and the same filter gradients when its support holds every entry
    (k >= grid sizes), so training it trains what inference runs; with the product's k = 3 the loss
    still flows."""
    from colmap_guided.coarse.model import CoarseNet, correlation, sparse_best
    from colmap_guided.train.losses import epipolar_loss_from_best

    torch.manual_seed(0)
    net = CoarseNet({"pretrained": False}).double()
    fa = torch.nn.functional.normalize(torch.randn(1, 8, 3, 4, dtype=torch.float64), dim=1)
    fb = torch.nn.functional.normalize(torch.randn(1, 8, 4, 3, dtype=torch.float64), dim=1)
    # (3, 4, 2)
    xa = (
        torch.stack(
            torch.meshgrid(torch.arange(4.0), torch.arange(3.0), indexing="xy"), -1
        ).double()
        * 16
        + 8
    )
    # (4, 3, 2)
    xb = (
        torch.stack(
            torch.meshgrid(torch.arange(3.0), torch.arange(4.0), indexing="xy"), -1
        ).double()
        * 16
        + 8
    )
    # line of (u, v): x = u
    F = torch.tensor([[[0, 0, 1], [0, 0, 0], [-1, 0, 0]]], dtype=torch.float64)
    pos = torch.tensor([True])

    out = net(fa, fb)
    dense, _ = epipolar_loss(out["s_ab"], out["s_ba"], pos, F, xa[None], xb[None], lam=16.0)
    g_dense = torch.autograd.grad(dense, list(net.filter.parameters()))

    def sparse(k):
        a, b, v = net.sparse_volume(correlation(fa, fb)[0], k, radius=0)
        idx_ab, best_ab = sparse_best(a, b, v, 12, 12)
        idx_ba, best_ba = sparse_best(b, a, v, 12, 12)
        ones = torch.ones(1, 12, dtype=torch.bool)
        return epipolar_loss_from_best(
            best_ab[None],
            idx_ab[None],
            best_ba[None],
            idx_ba[None],
            pos,
            F,
            xa.reshape(1, -1, 2),
            xb.reshape(1, -1, 2),
            ones,
            ones,
            lam=16.0,
        )[0]

    full = sparse(12)
    assert full.item() == pytest.approx(dense.item(), abs=1e-10)
    for g, h in zip(g_dense, torch.autograd.grad(full, list(net.filter.parameters()))):
        assert torch.allclose(g, h, atol=1e-10)
    grads = torch.autograd.grad(sparse(3), list(net.filter.parameters()))
    assert all(torch.isfinite(g).all() for g in grads) and sum(g.abs().sum() for g in grads) > 0
