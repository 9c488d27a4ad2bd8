"""Pixel flow from grid matches: bilinear interpolation, clamping, forward-backward error."""

import numpy as np
import pytest

from colmap_guided.coarse.flow import CoarseResult, interpolate_grid
from colmap_guided.coarse.geometry import resize_geometry
from colmap_guided.coarse.model import GridMatches


def test_interpolation_exact_on_affine_flow():
    """Per-cell values of an affine map of the cell centres interpolate to that map everywhere
    inside the hull of the centres (bilinear reproduces affine functions)."""
    g = resize_geometry(1063, 780, 512, 16, 15.5)
    A = np.array([[0.9, -0.2], [0.15, 1.1]])
    t = np.array([40.0, -25.0])
    table = g.cell_centers() @ A.T + t
    rng = np.random.default_rng(0)
    lo, hi = (
        g.cell_to_pixel([[0, 0]])[0],
        g.cell_to_pixel([[g.grid_width - 1, g.grid_height - 1]])[0],
    )
    xy = rng.uniform(lo, hi, size=(5000, 2))
    out, clamped = interpolate_grid(g, table, xy)
    np.testing.assert_allclose(out, xy @ A.T + t, atol=1e-9)
    np.testing.assert_allclose(clamped, xy, rtol=0, atol=1e-9)


def test_interpolation_clamps_outside_the_centres():
    g = resize_geometry(640, 480, 512, 16, 15.5)
    table = g.cell_centers()  # identity flow
    corner = np.array([[0.0, 0.0], [639.9, 479.9]])
    out, clamped = interpolate_grid(g, table, corner)
    np.testing.assert_allclose(
        out, g.cell_to_pixel([[0, 0], [g.grid_width - 1, g.grid_height - 1]]), atol=1e-9
    )
    np.testing.assert_allclose(out, clamped, atol=1e-9)


def test_interpolation_rejects_bad_points():
    g = resize_geometry(640, 480, 512, 16, 15.5)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        interpolate_grid(g, g.cell_centers(), np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="finite"):
        interpolate_grid(g, g.cell_centers(), np.array([[np.nan, 2.0]]))


def shift_result(shift_cells: int):
    """A and B of the same size, B = A shifted left by ``shift_cells`` cells: exact grid matches."""
    ga = gb = resize_geometry(1024, 768, 512, 16, 15.5)
    w, h = ga.grid_width, ga.grid_height
    rows, cols = np.divmod(np.arange(w * h), w)
    ab = rows * w + np.clip(cols - shift_cells, 0, w - 1)
    ba = rows * w + np.clip(cols + shift_cells, 0, w - 1)
    ones = np.ones(w * h, np.float32)
    return CoarseResult(ga, gb, GridMatches(ab, 0.5 * ones, ba, 0.25 * ones)), ga


def test_flow_both_directions_and_fb_error():
    res, _ = shift_result(3)
    cell = res.cell_size_a
    assert cell == pytest.approx(32.0) and res.cell_size_b == pytest.approx(32.0)
    xy = np.array([[500.0, 300.0], [700.3, 401.7]])
    xy_b, score, fb = res.flow_ab(xy)
    np.testing.assert_allclose(xy_b, xy - [3 * cell, 0], atol=1e-3)
    np.testing.assert_allclose(score, 0.5)
    np.testing.assert_allclose(fb, 0, atol=1e-3)
    xy_a, score2, _ = res.flow_ba(xy_b)
    np.testing.assert_allclose(xy_a, xy, atol=1e-3)
    np.testing.assert_allclose(score2, 0.25)
    # A's columns 0-3 all map to B's column 0 (x = 31), which maps back to A's column 3 (x = 127):
    # a point at x = 40 gets a forward-backward error of 87 px
    xy_b, _, fb_left = res.flow_ab(np.array([[40.0, 300.0]]))
    assert xy_b[0, 0] == pytest.approx(31.0) and fb_left[0] == pytest.approx(87.0, abs=1e-3)


def test_flow_vectorised_many_points():
    res, _ = shift_result(1)
    xy = np.random.default_rng(1).uniform(0, [1024, 768], size=(20000, 2))
    xy_b, score, fb = res.flow_ab(xy)
    assert (
        xy_b.shape == (20000, 2)
        and score.shape == fb.shape == (20000,)
        and xy_b.dtype == np.float32
    )


def test_grid_matches_and_mutual():
    res, g = shift_result(2)
    src, dst, _, mutual = res.grid_matches_ab()
    assert src.shape == dst.shape == (g.grid_width * g.grid_height, 2)
    # the two leftmost columns of A map to B's first column, whose match goes back to column 2
    cols = np.arange(len(mutual)) % g.grid_width
    assert not mutual[cols < 2].any() and mutual[(cols >= 2)].all()
