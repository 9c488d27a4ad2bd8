"""4D convolutions: the fast dense and the sparse implementations against the naive loop of
conv3d."""

import pytest
import torch
import torch.nn.functional as F

from colmap_guided.coarse import CoarseMatcher
from colmap_guided.coarse.conv4d import SparseNeighbourhood, conv4d, kernel_offsets, sparse_conv4d
from colmap_guided.coarse.model import correlation
from colmap_guided.images import read_image
from colmap_guided.paths import shared_data_dir

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def conv4d_naive(x, weight, bias=None, groups=1):
    """The paper's/NCNet's 4D convolution as a Python loop of 3D convolutions, one per output
    I-slice and kernel I-offset: the reference the fast implementations are checked against."""
    n, _, ni, nj, nk, nl = x.shape
    ki = weight.shape[2]
    out = x.new_zeros(n, weight.shape[0], ni, nj, nk, nl)
    for i in range(ni):
        for a in range(ki):
            src = i + a - ki // 2
            if 0 <= src < ni:
                out[:, :, i] += torch.nn.functional.conv3d(
                    x[:, :, src],
                    weight[:, :, a],
                    padding=tuple(k // 2 for k in weight.shape[3:]),
                    groups=groups,
                )
    return out if bias is None else out + bias.view(1, -1, 1, 1, 1, 1)


@pytest.fixture(scope="module")
def real_corr(shared_data):
    """Correlation of two photos of the Sacre Coeur at 128 px (8x6 and 6x8 grids)."""
    images = shared_data_dir() / "lightglue_assets" / "images"
    cm = CoarseMatcher({"mode": "raw", "resize_max": 128, "device": "cpu"})
    fa, fb = (
        cm.extract(read_image(images / n)).features
        for n in ("sacre_coeur1.jpg", "sacre_coeur2.jpg")
    )
    return correlation(fa[None], fb[None])[0]


def all_coords(shape):
    return torch.stack(
        torch.meshgrid(*[torch.arange(s) for s in shape], indexing="ij"), -1
    ).reshape(-1, 4)


@pytest.mark.parametrize(
    "c_in,c_out,groups,kernel", [(1, 4, 1, 3), (4, 6, 2, 3), (3, 2, 1, 5), (2, 1, 1, (3, 1, 3, 5))]
)
def test_dense_equals_naive(c_in, c_out, groups, kernel):
    torch.manual_seed(0)
    k = (kernel,) * 4 if isinstance(kernel, int) else kernel
    x = torch.randn(2, c_in, 5, 6, 4, 7)
    w, b = torch.randn(c_out, c_in // groups, *k), torch.randn(c_out)
    torch.testing.assert_close(
        conv4d(x, w, b, groups), conv4d_naive(x, w, b, groups), rtol=1e-4, atol=1e-4
    )


@pytest.mark.parametrize(
    "c_in,c_out,groups", [(1, 4, 1), (4, 6, 2), (3, 1, 1), (4, 2, 2), (2, 3, 1)]
)
def test_sparse_all_active_equals_dense(c_in, c_out, groups):
    """Each form of sparse_conv4d: gather (1 input channel), scatter (1 output channel per group),
    rulebook."""
    torch.manual_seed(1)
    shape = (4, 5, 3, 6)
    x = torch.randn(1, c_in, *shape)
    w, b = torch.randn(c_out, c_in // groups, 3, 3, 3, 3), torch.randn(c_out)
    coords = all_coords(shape)
    out = sparse_conv4d(
        x[0].reshape(c_in, -1).t(), SparseNeighbourhood(coords, shape, (3, 3, 3, 3)), w, b, groups
    )
    torch.testing.assert_close(
        out, conv4d_naive(x, w, b, groups)[0].reshape(c_out, -1).t(), rtol=1e-4, atol=1e-4
    )


@pytest.mark.parametrize("c_in,c_out", [(1, 3), (2, 3), (2, 1)])
def test_sparse_subset_reads_inactive_as_zero(c_in, c_out):
    """On a subset of positions, sparse = dense conv of the volume zeroed outside the subset,
    sampled there."""
    torch.manual_seed(2)
    shape = (5, 4, 5, 4)
    x = torch.randn(1, c_in, *shape)
    active = torch.rand(shape) < 0.3
    coords = torch.nonzero(active)
    w, b = torch.randn(c_out, c_in, 3, 3, 3, 3), torch.randn(c_out)
    dense = conv4d_naive(x * active, w, b)[0][:, active].t()
    out = sparse_conv4d(x[0][:, active].t(), SparseNeighbourhood(coords, shape, (3, 3, 3, 3)), w, b)
    torch.testing.assert_close(out, dense, rtol=1e-4, atol=1e-4)


def test_dense_equals_naive_on_real_correlation(real_corr):
    """A real correlation volume (two photos, EfficientNet-Lite0 features) through a 16-channel
    layer."""
    torch.manual_seed(3)
    x = real_corr[None, None]
    w, b = torch.randn(16, 1, 3, 3, 3, 3) * 0.1, torch.randn(16) * 0.1
    y1 = F.relu(conv4d(x, w, b))
    torch.testing.assert_close(y1, F.relu(conv4d_naive(x, w, b)), rtol=1e-4, atol=1e-5)
    w2 = torch.randn(4, 8, 3, 3, 3, 3) * 0.1
    torch.testing.assert_close(
        conv4d(y1, w2, groups=2), conv4d_naive(y1, w2, groups=2), rtol=1e-4, atol=1e-4
    )


def test_dense_gradient_matches_naive():
    torch.manual_seed(4)
    x = torch.randn(1, 2, 4, 3, 4, 3)
    w1 = torch.randn(3, 2, 3, 3, 3, 3, requires_grad=True)
    w2 = w1.detach().clone().requires_grad_(True)
    (conv4d(x, w1) ** 2).sum().backward()
    (conv4d_naive(x, w2) ** 2).sum().backward()
    torch.testing.assert_close(w1.grad, w2.grad, rtol=1e-4, atol=1e-3)


def test_kernel_offsets_order():
    off = kernel_offsets((3, 1, 3, 3))
    assert (
        off.shape == (27, 4)
        and off[0].tolist() == [-1, 0, -1, -1]
        and off[13].tolist() == [0, 0, 0, 0]
    )


def test_conv4d_rejects_bad_weight():
    with pytest.raises(ValueError, match="odd kernels"):
        conv4d(torch.zeros(1, 2, 3, 3, 3, 3), torch.zeros(1, 2, 2, 2, 2, 2))
