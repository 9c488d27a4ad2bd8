"""Network inputs and pairs: ``View`` (a stored image, a degraded or synthetic version of it, an
optional training window of its feature grid) and ``PairSample`` (two views, label, F, GT matches),
and the window crop the dense CPU path trains on (``crop_sample``)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from colmap_guided.coarse.geometry import ImageGeometry


@dataclass
class View:
    """One network input: a (possibly degraded) stored image or a synthetic warp of one."""

    key: str  # "img/<scene>/<name>/v<k>" (k = 0 clean, k > 0 archival) or "syn/<scene>/<name>/h<k>"
    scene: str
    name: str
    geometry: ImageGeometry
    xy_ideal: np.ndarray  # (gh, gw, 2) cell centres in the resized frame, undistorted (frame of F)
    H: np.ndarray | None = (
        None  # synthetic views: source photo's original pixels -> this view's pixels
    )
    window: tuple[int, int, int, int] | None = (
        None  # training crop of the grid: (row0, col0, rows, cols)
    )

    @property
    def grid(self) -> tuple[int, int, int, int]:
        """(row0, col0, rows, cols) of the cells the network sees (the whole grid without a
        window)."""
        g = self.geometry
        return self.window if self.window is not None else (0, 0, g.grid_height, g.grid_width)

    def crop(self, array):
        """Crop a (..., gh, gw) array or tensor of this view's full grid to its window."""
        r0, c0, h, w = self.grid
        return array[..., r0 : r0 + h, c0 : c0 + w]

    def crop_xy(self) -> np.ndarray:
        r0, c0, h, w = self.grid
        return self.xy_ideal[r0 : r0 + h, c0 : c0 + w]


@dataclass
class PairSample:
    """A training or validation pair, everything in numpy; ``collate`` turns a list into tensors."""

    a: View
    b: View
    positive: bool
    source: str  # 'sfm', 'synthetic' or 'negative'
    F: np.ndarray  # (3, 3) resized frames: xy_b^T F xy_a = 0 for the centres in View.xy_ideal
    pts_a: np.ndarray  # (N, 2) ground-truth matches in original pixels of a's geometry (N may be 0)
    pts_b: np.ndarray

    def swapped(self) -> "PairSample":
        return PairSample(
            self.b, self.a, self.positive, self.source, self.F.T.copy(), self.pts_b, self.pts_a
        )


def plain_centres(geometry: ImageGeometry) -> np.ndarray:
    """Cell centres in the resized frame, (gh, gw, 2)."""
    return (geometry.cell_centers() * geometry.scale).reshape(
        geometry.grid_height, geometry.grid_width, 2
    )


def crop_sample(sample: PairSample, max_cells: int, rng: np.random.Generator) -> PairSample:
    """Crop both feature grids to at most ``max_cells`` per side, keeping the feature scale.

    The 4D filter is what costs on a CPU (its work grows with the fourth power of the grid side), so
    training can see windows of the native-resolution grids instead of downscaled images. For a
    positive pair both windows are centred (with a random jitter of a quarter window) on the two
    cells of one random ground-truth match, so they overlap in the scene; negatives get random
    windows. F, the cell centres and the GT matches stay in the full resized frames
    (collate crops them).
    """

    def window(view: View, centre) -> tuple[int, int, int, int]:
        g = view.geometry
        h, w = min(max_cells, g.grid_height), min(max_cells, g.grid_width)
        if centre is None:
            r0 = int(rng.integers(0, g.grid_height - h + 1))
            c0 = int(rng.integers(0, g.grid_width - w + 1))
        else:
            col, row = centre + rng.uniform(-0.25, 0.25, 2) * [w, h]
            r0 = int(np.clip(round(row - (h - 1) / 2), 0, g.grid_height - h))
            c0 = int(np.clip(round(col - (w - 1) / 2), 0, g.grid_width - w))
        return r0, c0, h, w

    ca = cb = None
    if sample.positive and len(sample.pts_a):
        i = int(rng.integers(len(sample.pts_a)))
        ca = sample.a.geometry.pixel_to_cell(sample.pts_a[i : i + 1])[0]
        cb = sample.b.geometry.pixel_to_cell(sample.pts_b[i : i + 1])[0]
    a = replace(sample.a, window=window(sample.a, ca))
    b = replace(sample.b, window=window(sample.b, cb))
    return replace(sample, a=a, b=b)


def inside(xy: np.ndarray, geometry: ImageGeometry) -> np.ndarray:
    return (
        (xy[:, 0] >= 0)
        & (xy[:, 1] >= 0)
        & (xy[:, 0] < geometry.width)
        & (xy[:, 1] < geometry.height)
    )


def cells_in_window(view: View, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) in the view's window of the cell nearest to each point (original pixels), and
    whether that cell lies inside the window."""
    g = view.geometry
    cr = np.rint(g.pixel_to_cell(pts)).astype(np.int64)
    col = cr[:, 0].clip(0, g.grid_width - 1)
    row = cr[:, 1].clip(0, g.grid_height - 1)
    r0, c0, h, w = view.grid
    row, col = row - r0, col - c0
    return row, col, (row >= 0) & (row < h) & (col >= 0) & (col < w)
