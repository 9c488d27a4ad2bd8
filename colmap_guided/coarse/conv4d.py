"""4D convolutions for the neighbourhood-consensus filter (paper §4.1, NCNet), dense and sparse.

Both use PyTorch's convention (cross-correlation, zero 'same' padding, odd kernels) and the weight
layout (C_out, C_in / groups, kI, kJ, kK, kL), so the same weights run in either.

- ``conv4d``: dense. The 4D kernel is split along its first dimension into kI 3D kernels; one
  batched conv3d over all I-slices computes the kI partial outputs, which are summed with a shift
  along I. This is the GPU and training path (the paper's loop of per-slice 3D convolutions,
  batched).
- ``sparse_conv4d``: submanifold sparse convolution on a set of active positions (Sparse-NCNet's
  idea, written in plain torch as gathers, matmuls and index_add over a ``SparseNeighbourhood``):
  outputs only at the active positions, inactive neighbours read as zero. With every position active
  it equals ``conv4d`` (tested). The CPU path.
"""

from __future__ import annotations

import itertools

import torch
import torch.nn.functional as F


def conv4d(
    x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None, groups: int = 1
) -> torch.Tensor:
    """Dense 4D convolution of x (N, C_in, I, J, K, L), zero padding, output the same size."""
    n, c_in, ni, nj, nk, nl = x.shape
    c_out, c_in_g, ki, kj, kk, kl = weight.shape
    if c_in_g * groups != c_in or any(k % 2 == 0 for k in (ki, kj, kk, kl)):
        raise ValueError(
            f"conv4d: weight {tuple(weight.shape)} does not fit input {tuple(x.shape)} "
            f"with groups={groups} (odd kernels only)"
        )
    cg = c_out // groups
    # (G, cg, c_in_g, ki, kj, kk, kl) → (G, ki, cg, ...): output channels stay grouped for conv3d.
    w3 = (
        weight.view(groups, cg, c_in_g, ki, kj, kk, kl)
        .permute(0, 3, 1, 2, 4, 5, 6)
        .reshape(groups * ki * cg, c_in_g, kj, kk, kl)
    )
    slices = x.transpose(1, 2).reshape(n * ni, c_in, nj, nk, nl)
    y = F.conv3d(slices, w3, padding=(kj // 2, kk // 2, kl // 2), groups=groups)
    y = y.view(n, ni, groups, ki, cg, nj, nk, nl)
    pad = ki // 2
    out = y[:, :, :, pad].clone()
    for a in range(ki):
        d = a - pad  # out[i] += y[i + d, a]
        if d == 0 or abs(d) >= ni:
            continue
        if d > 0:
            out[:, : ni - d] += y[:, d:, :, a]
        else:
            out[:, -d:] += y[:, : ni + d, :, a]
    out = out.reshape(n, ni, c_out, nj, nk, nl).transpose(1, 2)
    if bias is not None:
        out = out + bias.view(1, -1, 1, 1, 1, 1)
    return out


def kernel_offsets(
    kernel_size: tuple[int, int, int, int], device: torch.device | None = None
) -> torch.Tensor:
    """(prod(kernel_size), 4) offsets of the kernel taps, row-major like the weight's last four
    dims."""
    ranges = [range(-(k // 2), k // 2 + 1) for k in kernel_size]
    return torch.tensor(list(itertools.product(*ranges)), dtype=torch.long, device=device)


def neighbour_table(
    coords: torch.Tensor, shape: tuple[int, int, int, int], kernel_size: tuple[int, int, int, int]
) -> torch.Tensor:
    """For N active positions coords (N, 4) in a volume of ``shape``, the (N, taps) index of each
    tap's neighbour among the active positions, or N where the neighbour is inactive or outside.
    Uses a lookup volume padded by the kernel radius, so that no bounds checks are needed."""
    n = coords.shape[0]
    pad = torch.tensor([k // 2 for k in kernel_size], device=coords.device)
    padded = [s + 2 * (k // 2) for s, k in zip(shape, kernel_size)]
    strides = torch.tensor(
        [padded[1] * padded[2] * padded[3], padded[2] * padded[3], padded[3], 1],
        device=coords.device,
    )
    lut = torch.full(
        (padded[0] * padded[1] * padded[2] * padded[3],), n, dtype=torch.long, device=coords.device
    )
    lin = ((coords + pad) * strides).sum(dim=1)
    lut[lin] = torch.arange(n, device=coords.device)
    taps = (kernel_offsets(kernel_size, coords.device) * strides).sum(dim=1)
    # lut[...]: 3x faster on CPU
    return lut.index_select(0, (lin[:, None] + taps[None]).view(-1)).view(n, len(taps))


class SparseNeighbourhood:
    """The neighbourhood structure of N active positions, shared by all layers of a sparse filter:
    ``table`` (N, taps) from ``neighbour_table`` and, built on first use, the ``rulebook``: per tap
    t with active pairs, (t, output indices, input indices) of the active positions whose tap-t
    neighbour is active."""

    def __init__(
        self,
        coords: torch.Tensor,
        shape: tuple[int, int, int, int],
        kernel_size: tuple[int, int, int, int],
    ):
        self.table = neighbour_table(coords, shape, kernel_size)
        self.n, self.taps = self.table.shape
        self._rulebook: list[tuple[int, torch.Tensor, torch.Tensor]] | None = None

    @property
    def rulebook(self) -> list[tuple[int, torch.Tensor, torch.Tensor]]:
        if self._rulebook is None:
            # (taps * N): active pairs come out sorted by tap
            by_tap = self.table.t().contiguous().view(-1)
            flat = torch.nonzero(by_tap < self.n).squeeze(1)
            tap = flat // self.n
            out, inp = flat - tap * self.n, by_tap.index_select(0, flat)
            counts = torch.bincount(tap, minlength=self.taps).tolist()
            self._rulebook = [
                (t, o, i)
                for t, (o, i) in enumerate(zip(out.split(counts), inp.split(counts)))
                if len(o)
            ]
        return self._rulebook


def sparse_conv4d(
    x: torch.Tensor,
    nbhd: SparseNeighbourhood,
    weight: torch.Tensor,
    bias: torch.Tensor | None = None,
    groups: int = 1,
) -> torch.Tensor:
    """Submanifold 4D convolution of features x (N, C_in) at N active positions: returns (N, C_out),
    out[p] = b + sum_t W_t x[p + offset_t] over the active neighbours only
    (inactive ones read as 0).

    Three equivalent forms, picked by the channel counts of a group (CPU cost, measured):
    - one input channel (first NC layer): gather form, one (N, taps) gather of scalars and one
      matmul;
    - one output channel (last NC layer): scatter form, z = x W_t for all taps in one matmul, then
      out[p] = sum_t z[p + offset_t, t], a gather of scalars;
    - otherwise: per-tap gather-matmul-scatter over the rulebook, proportional to the number of
      active (position, neighbour) pairs rather than N x taps (most neighbours of a sparse support
      are inactive).
    """
    n, c_in = x.shape
    c_out, c_in_g = weight.shape[:2]
    taps = nbhd.taps
    cg = c_out // groups
    w = weight.reshape(groups, cg, c_in_g, taps)
    table = nbhd.table.reshape(-1)
    if c_in == 1:  # gather form (groups == 1)
        gathered = torch.cat([x[:, 0], x.new_zeros(1)]).index_select(0, table).view(n, taps)
        out = gathered @ w.reshape(c_out, taps).t()
    elif cg == 1:  # scatter form
        index = (nbhd.table * taps + torch.arange(taps, device=x.device)).view(-1)
        outs = []
        for g in range(groups):
            z = x[:, g * c_in_g : (g + 1) * c_in_g] @ w[g, 0]  # (N, taps)
            outs.append(
                torch.cat([z.reshape(-1), z.new_zeros(taps)])
                .index_select(0, index)
                .view(n, taps)
                .sum(dim=1)
            )
        out = torch.stack(outs, dim=1)
    else:  # rulebook
        w_taps = w.permute(3, 0, 2, 1)  # (taps, G, c_in_g, cg)
        out = x.new_zeros(n, c_out)
        for t, o, i in nbhd.rulebook:
            xs = x.index_select(0, i)
            if groups == 1:
                y = xs @ w_taps[t, 0]
            else:
                # one small matmul per group: half the work of a block-diagonal matrix for 2 groups
                y = torch.cat(
                    [xs[:, g * c_in_g : (g + 1) * c_in_g] @ w_taps[t, g] for g in range(groups)],
                    dim=1,
                )
            out.index_add_(0, o, y)
    return out if bias is None else out + bias
