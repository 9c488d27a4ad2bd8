"""Input geometry: resize to multiples of 16, pixel ↔ cell mapping, padding."""

import numpy as np
import pytest
import torch

from colmap_guided.coarse.geometry import as_rgb, resize_geometry, resize_image, stack_padded


@pytest.mark.parametrize(
    "w,h", [(1024, 731), (780, 1063), (1296, 1936), (300, 451), (4000, 100), (512, 512)]
)
def test_resize_geometry(w, h):
    g = resize_geometry(w, h, 512, 16, 15.5)
    assert g.resized_width % 16 == 0 and g.resized_height % 16 == 0
    assert max(g.resized_width, g.resized_height) == 512
    assert g.grid_width <= 32 and g.grid_height <= 32
    # aspect kept up to the rounding to a multiple of 16 (half a cell per side)
    assert (
        abs(g.resized_width - w * 512 / max(w, h)) <= 8
        and abs(g.resized_height - h * 512 / max(w, h)) <= 8
    )


def test_resize_max_not_multiple_of_stride():
    g = resize_geometry(1000, 500, 500, 16, 15.5)
    assert (g.resized_width, g.resized_height) == (496, 256)


def test_round_trip_pixel_cell():
    g = resize_geometry(1063, 780, 512, 16, 15.5)
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, [1063, 780], size=(1000, 2))
    np.testing.assert_allclose(g.cell_to_pixel(g.pixel_to_cell(xy)), xy, rtol=0, atol=1e-9)
    # cell (0, 0) centre: 15.5 resized pixels from the corner; cells are 16 resized px apart
    sx, sy = g.scale
    np.testing.assert_allclose(
        g.cell_to_pixel([[0, 0], [1, 2]]), [[15.5 / sx, 15.5 / sy], [31.5 / sx, 47.5 / sy]]
    )
    assert g.cell_size == pytest.approx(16 / min(sx, sy))
    assert len(g.cell_centers()) == g.grid_width * g.grid_height


def test_resize_is_corner_aligned():
    """A block of pixels lands where x * scale puts it (undoing resize = dividing by the scale)."""
    img = np.zeros((600, 800), np.uint8)
    img[300:340, 400:440] = 255  # corners (400, 300) and (440, 340)
    g = resize_geometry(800, 600, 512, 16, 15.5)
    small = resize_image(as_rgb(img), g)[:, :, 0].astype(float)
    ys, xs = np.mgrid[: small.shape[0], : small.shape[1]]
    cx, cy = (small * (xs + 0.5)).sum() / small.sum(), (small * (ys + 0.5)).sum() / small.sum()
    np.testing.assert_allclose([cx, cy], np.array([420, 320]) * g.scale, atol=0.05)


def test_gray_and_rgb_inputs():
    gray = np.arange(12, dtype=np.uint8).reshape(3, 4)
    assert as_rgb(gray).shape == (3, 4, 3) and (as_rgb(gray)[:, :, 2] == gray).all()
    assert as_rgb(gray[:, :, None]).shape == (3, 4, 3)
    with pytest.raises(TypeError, match="uint8"):
        as_rgb(gray.astype(np.float32))
    with pytest.raises(ValueError, match="HxW"):
        as_rgb(np.zeros((3, 4, 4), np.uint8))


def test_stack_padded():
    a, b = torch.ones(2, 3, 4), torch.ones(2, 5, 2)
    batch, mask = stack_padded([a, b])
    assert batch.shape == (2, 2, 5, 4)
    assert mask[0].sum() == 12 and mask[1].sum() == 10
    assert (batch[0, :, 3:] == 0).all() and (batch[1, :, :, 2:] == 0).all()
    assert torch.equal(batch[0, :, :3, :4], a)
