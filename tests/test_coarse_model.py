"""The coarse network: symmetry, batching with padding, softmaxes, raw mode, sparse vs dense."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from colmap_guided.coarse.conv4d import conv4d
from colmap_guided.coarse.model import (
    CoarseNet,
    NeighConsensus,
    correlation,
    soft_mutual_nn,
    sparse_support,
    transpose_volume,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(0)
    return CoarseNet({"pretrained": False}).eval()


def random_features(c, h, w, seed):
    g = torch.Generator().manual_seed(seed)
    return F.normalize(torch.randn(1, c, h, w, generator=g), dim=1)


def test_swapping_images_transposes_the_volume(net):
    fa, fb = random_features(112, 4, 5, 1), random_features(112, 5, 3, 2)
    with torch.no_grad():
        ab, ba = net(fa, fb), net(fb, fa)
    torch.testing.assert_close(ba["volume"], transpose_volume(ab["volume"]), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(ba["s_ab"], transpose_volume(ab["s_ba"]), rtol=1e-5, atol=1e-7)


def test_filter_is_both_orders_averaged():
    """The fused 2-group pass equals NCNet's explicit form: mean of f(c) and f(c^T)^T."""
    torch.manual_seed(1)
    nc = NeighConsensus((4, 3, 1), (3, 3, 3))
    c = torch.rand(1, 4, 3, 5, 4)

    def single_order(v):
        x = v.unsqueeze(1)
        for w, b in zip(nc.weights, nc.biases):
            x = F.relu(conv4d(x, w, b))
        return x[:, 0]

    expected = 0.5 * (single_order(c) + transpose_volume(single_order(transpose_volume(c))))
    torch.testing.assert_close(nc(c), expected, rtol=1e-5, atol=1e-6)


def test_softmaxes_and_padded_batch(net):
    """s_ab sums to 1 over B, s_ba over A; a zero-padded batch with masks gives the single-pair
    values."""
    fa1, fb1 = random_features(112, 3, 4, 3), random_features(112, 4, 4, 4)
    fa2, fb2 = random_features(112, 4, 2, 5), random_features(112, 2, 3, 6)
    with torch.no_grad():
        single = [net(fa1, fb1), net(fa2, fb2)]
        fa = torch.cat([F.pad(fa1, (0, 0, 0, 1)), F.pad(fa2, (0, 2))])
        fb = torch.cat([fb1, F.pad(fb2, (0, 1, 0, 2))])
        ma = torch.zeros(2, 4, 4, dtype=torch.bool)
        ma[0, :3] = True
        ma[1, :, :2] = True
        mb = torch.zeros(2, 4, 4, dtype=torch.bool)
        mb[0] = True
        mb[1, :2, :3] = True
        batch = net(fa, fb, ma, mb)
    for i, (h_a, w_a, h_b, w_b) in enumerate([(3, 4, 4, 4), (4, 2, 2, 3)]):
        for key in ("volume", "s_ab", "s_ba"):
            torch.testing.assert_close(
                batch[key][i, :h_a, :w_a, :h_b, :w_b], single[i][key][0], rtol=1e-5, atol=1e-6
            )
    assert batch["s_ab"][~(ma[:, :, :, None, None] & mb[:, None, None])].abs().max() == 0
    torch.testing.assert_close(single[0]["s_ab"].sum(dim=(3, 4)), torch.ones(1, 3, 4))
    torch.testing.assert_close(single[0]["s_ba"].sum(dim=(1, 2)), torch.ones(1, 4, 4))


def test_forward_is_differentiable_wrt_filter(net):
    fa, fb = random_features(112, 3, 3, 7), random_features(112, 3, 3, 8)
    net.zero_grad()
    out = net(fa, fb)
    (-(out["s_ab"].amax(dim=(3, 4)).sum() + out["s_ba"].amax(dim=(1, 2)).sum())).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.filter.parameters())
    net.zero_grad()


def test_soft_mutual_nn():
    c = torch.tensor([[0.9, 0.3], [0.6, 0.5]]).view(1, 2, 1, 2, 1)
    m = soft_mutual_nn(c)[0, :, 0, :, 0]
    # the mutual best (0.9) is kept; others scaled by (c / max over A) * (c / max over B)
    assert m[0, 0] == pytest.approx(0.9, rel=1e-4)
    assert m[1, 0] == pytest.approx(0.6 * (0.6 / 0.9) * (0.6 / 0.6), rel=1e-4)
    assert m[0, 1] == pytest.approx(0.3 * (0.3 / 0.5) * (0.3 / 0.9), rel=1e-4)


def test_raw_mode_is_mutual_nn_of_the_correlation():
    net = CoarseNet({"pretrained": False, "filter": False})
    assert net.filter is None
    fa, fb = random_features(16, 5, 6, 9), random_features(16, 6, 5, 10)
    g = net.match(fa[0], fb[0])
    c = correlation(fa, fb)[0].reshape(30, 30)
    np.testing.assert_array_equal(g.ab, c.argmax(1).numpy())
    np.testing.assert_array_equal(g.ba, c.argmax(0).numpy())
    np.testing.assert_allclose(
        g.score_ab, torch.softmax(c / net.conf["raw_temperature"], 1).amax(1).numpy(), rtol=1e-5
    )
    assert g.mutual_ab.sum() == g.mutual_ba.sum() > 0


def test_sparse_with_full_support_equals_dense(net):
    fa, fb = random_features(112, 4, 5, 11), random_features(112, 5, 4, 12)
    dense = net.match(fa[0], fb[0], "dense")
    sparse = net.match(fa[0], fb[0], "sparse", k=20)
    np.testing.assert_array_equal(sparse.ab, dense.ab)
    np.testing.assert_array_equal(sparse.ba, dense.ba)
    np.testing.assert_allclose(sparse.score_ab, dense.score_ab, rtol=1e-4)
    np.testing.assert_allclose(sparse.score_ba, dense.score_ba, rtol=1e-4)


def test_sparse_support():
    """Top-k in both directions plus the 3x3 cells around each best match; swapping A and B
    transposes it."""
    torch.manual_seed(5)
    shape = (4, 5, 6, 3)
    c2 = torch.rand(20, 18)
    lin = sparse_support(c2, shape, 2, 1)
    mask = torch.zeros(20, 18, dtype=torch.bool)
    mask.view(-1)[lin] = True
    assert mask.sum(1).min() >= 2 and mask.sum(0).min() >= 2
    assert (
        mask.gather(1, c2.topk(2, dim=1).indices).all()
        and mask.gather(0, c2.topk(2, dim=0).indices).all()
    )
    b = c2[7].argmax().item()  # A cell 7's best B cell and its 3x3 neighbourhood in B's 6x3 grid
    rows, cols = b // 3, b % 3
    for r in range(max(rows - 1, 0), min(rows + 2, 6)):
        for c in range(max(cols - 1, 0), min(cols + 2, 3)):
            assert mask[7, r * 3 + c]
    swapped = torch.zeros(18, 20, dtype=torch.bool)
    swapped.view(-1)[sparse_support(c2.t().contiguous(), (6, 3, 4, 5), 2, 1)] = True
    assert torch.equal(swapped, mask.t())
    assert len(sparse_support(c2, shape, 1, 0)) < len(lin) <= 20 * 18


def test_sparse_is_symmetric(net):
    fa, fb = random_features(112, 6, 5, 13), random_features(112, 5, 7, 14)
    ab, ba = net.match(fa[0], fb[0], "sparse", k=3), net.match(fb[0], fa[0], "sparse", k=3)
    np.testing.assert_array_equal(ab.ab, ba.ba)
    np.testing.assert_allclose(ab.score_ab, ba.score_ba, rtol=1e-5)


def test_unknown_option():
    with pytest.raises(ValueError, match="Unknown CoarseNet option"):
        CoarseNet({"pretrained": False, "resize": 3})
