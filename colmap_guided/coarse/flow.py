"""Pixel-level coarse flow m^{A→B}, m^{B→A} from grid matches (paper §4.1: "bilinear interpolation
of the feature matches of its four nearest features"), in original image pixels."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from colmap_guided.coarse.geometry import ImageGeometry
from colmap_guided.coarse.model import GridMatches


def interpolate_grid(
    geometry: ImageGeometry, values: np.ndarray, xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear interpolation of per-cell ``values`` (h * w, D), row-major, at original pixels
    ``xy`` (N, 2) from the four nearest cell centres. Points outside the hull of the cell centres
    are clamped onto it (no extrapolation). Returns the (N, D) values and the clamped points
    (N, 2)."""
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] < 2 or not np.isfinite(xy[:, :2]).all():
        raise ValueError(
            f"Expected (N, 2) finite pixel coordinates, got an array of shape {xy.shape}"
        )
    h, w = geometry.grid_height, geometry.grid_width
    uv = geometry.pixel_to_cell(xy[:, :2])
    u = np.clip(uv[:, 0], 0, w - 1)
    v = np.clip(uv[:, 1], 0, h - 1)
    u0 = np.minimum(np.floor(u), max(w - 2, 0)).astype(np.int64)
    v0 = np.minimum(np.floor(v), max(h - 2, 0)).astype(np.int64)
    u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
    fu, fv = (u - u0)[:, None], (v - v0)[:, None]
    values = np.asarray(values).reshape(h * w, -1)
    out = (
        (1 - fu) * (1 - fv) * values[v0 * w + u0]
        + fu * (1 - fv) * values[v0 * w + u1]
        + (1 - fu) * fv * values[v1 * w + u0]
        + fu * fv * values[v1 * w + u1]
    )
    return out, geometry.cell_to_pixel(np.stack([u, v], axis=1))


@dataclass
class CoarseResult:
    """Coarse matches of one image pair and the flow they define in both directions."""

    geometry_a: ImageGeometry
    geometry_b: ImageGeometry
    matches: GridMatches
    _table_ab: np.ndarray = field(init=False, repr=False)
    _table_ba: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        # Per cell of the source grid: matched target cell centre (x, y) in target pixels, score.
        m = self.matches
        self._table_ab = np.column_stack([self.geometry_b.cell_centers()[m.ab], m.score_ab])
        self._table_ba = np.column_stack([self.geometry_a.cell_centers()[m.ba], m.score_ba])

    @property
    def cell_size_a(self) -> float:
        """One feature cell in A's original pixels (the guided matcher's window W)."""
        return self.geometry_a.cell_size

    @property
    def cell_size_b(self) -> float:
        return self.geometry_b.cell_size

    def flow_ab(self, xy_a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """m^{A→B} at points (N, 2) of A (original pixels). Returns
        - ``xy_b`` (N, 2) float32: the coarse match in B's original pixels;
        - ``score`` (N,) float32: s^{A→B} at the matches of the four cells, interpolated the same
          way;
        - ``fb_err`` (N,) float32: forward-backward error in B's pixels, |m^{B→A}(m^{A→B}(x)) - x|
          measured in A and scaled by cell_size_b / cell_size_a (0 at mutual matches' cell
          centres)."""
        return self._flow(xy_a, self.geometry_a, self.geometry_b, self._table_ab, self._table_ba)

    def flow_ba(self, xy_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """m^{B→A} at points of B: like ``flow_ab`` with A and B swapped (fb_err in A's pixels)."""
        return self._flow(xy_b, self.geometry_b, self.geometry_a, self._table_ba, self._table_ab)

    @staticmethod
    def _flow(xy, geo_src, geo_dst, table_fwd, table_bwd):
        fwd, xy_clamped = interpolate_grid(geo_src, table_fwd, xy)
        back, _ = interpolate_grid(geo_dst, table_bwd, fwd[:, :2])
        fb_err = np.linalg.norm(back[:, :2] - xy_clamped, axis=1) * (
            geo_dst.cell_size / geo_src.cell_size
        )
        return (
            fwd[:, :2].astype(np.float32),
            fwd[:, 2].astype(np.float32),
            fb_err.astype(np.float32),
        )

    def grid_matches_ab(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Cell-level matches A→B: A cell centres (NA, 2), matched B cell centres (NA, 2), score
        (NA,), mutual (NA,) bool; original pixels."""
        return (
            self.geometry_a.cell_centers(),
            self._table_ab[:, :2],
            self.matches.score_ab,
            self.matches.mutual_ab,
        )
