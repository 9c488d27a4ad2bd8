"""Input geometry of the coarse network: resizing, padding, feature cell ↔ original pixel.

Coordinates follow COLMAP: (0, 0) is the top-left corner of the top-left pixel. An image of
``width x height`` pixels is resized (corner-aligned, as cv2.resize does) to ``resized_width x
resized_height``, both multiples of the stride, keeping the aspect ratio up to that rounding, with
the long side equal to ``resize_max`` (paper §4.3: 401 px for training, 497 px at test time for
ResNet's padding; multiples of 16 here, see ``backbone.py``). A point ``x`` maps to ``x *
resized_width / width``. Feature cell ``(col, row)`` has its centre at ``stride * col +
cell_offset`` in the resized image, ``cell_offset`` being the backbone's (15.5 for EfficientNet's TF
'same' padding, 0.5 for ResNet). "Cell coordinates" are continuous: integer values are cell centres.

Batches of different sizes are zero-padded at the bottom/right, which keeps the origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F


@dataclass(frozen=True)
class ImageGeometry:
    """How one image's original pixels relate to its resized network input and its feature grid."""

    width: int  # original image size
    height: int
    resized_width: int  # network input size, multiples of stride
    resized_height: int
    stride: int
    cell_offset: float

    @property
    def grid_width(self) -> int:
        return self.resized_width // self.stride

    @property
    def grid_height(self) -> int:
        return self.resized_height // self.stride

    @property
    def scale(self) -> np.ndarray:
        """(sx, sy): resized pixels per original pixel."""
        return np.array([self.resized_width / self.width, self.resized_height / self.height])

    @property
    def cell_size(self) -> float:
        """Side of one feature cell in original pixels (the larger of x and y)."""
        return float(self.stride / self.scale.min())

    def pixel_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) original pixel coordinates → continuous cell coordinates (col, row)."""
        return (np.asarray(xy, dtype=np.float64) * self.scale - self.cell_offset) / self.stride

    def cell_to_pixel(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) continuous cell coordinates (col, row) → original pixel coordinates."""
        return (np.asarray(uv, dtype=np.float64) * self.stride + self.cell_offset) / self.scale

    def cell_centers(self) -> np.ndarray:
        """(grid_height * grid_width, 2) original-pixel centres of the cells in row-major order."""
        rows, cols = np.mgrid[: self.grid_height, : self.grid_width]
        return self.cell_to_pixel(np.stack([cols.ravel(), rows.ravel()], axis=1))

    def to_dict(self) -> dict:
        return {
            k: getattr(self, k)
            for k in ("width", "height", "resized_width", "resized_height", "stride", "cell_offset")
        }


def resize_geometry(
    width: int, height: int, resize_max: int, stride: int, cell_offset: float
) -> ImageGeometry:
    """Geometry of an image resized so its long side is ``resize_max`` (rounded down to a multiple
    of ``stride``) and its short side the nearest multiple of ``stride`` to the aspect-preserving
    size."""
    if width < 1 or height < 1:
        raise ValueError(f"Image size must be positive, got {width}x{height}")
    if resize_max < stride:
        raise ValueError(
            f"resize_max ({resize_max}) must be at least the feature stride ({stride})"
        )
    cells_max = resize_max // stride
    scale = resize_max / max(width, height)
    gw = min(cells_max, max(1, round(width * scale / stride)))
    gh = min(cells_max, max(1, round(height * scale / stride)))
    return ImageGeometry(width, height, gw * stride, gh * stride, stride, cell_offset)


def as_rgb(image: np.ndarray) -> np.ndarray:
    """uint8 HxW (grayscale), HxWx1 or HxWx3 (RGB) → HxWx3 uint8 RGB."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise TypeError(
            f"Expected a uint8 image, got {image.dtype}: "
            "convert with np.clip(img, 0, 255).astype(np.uint8)"
        )
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim == 3 and image.shape[2] == 3:
        return image
    raise ValueError(f"Expected an HxW grayscale or HxWx3 RGB image, got shape {image.shape}")


def resize_image(image: np.ndarray, geometry: ImageGeometry) -> np.ndarray:
    """Resize an RGB uint8 image to the geometry's network input size (area filter when
    shrinking)."""
    size = (geometry.resized_width, geometry.resized_height)
    shrink = geometry.resized_width < geometry.width or geometry.resized_height < geometry.height
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def pad_to_shape(x: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Zero-pad (..., H, W) at the bottom/right to (..., height, width)."""
    h, w = x.shape[-2:]
    if h > height or w > width:
        raise ValueError(f"Cannot pad {h}x{w} to the smaller {height}x{width}")
    return F.pad(x, (0, width - w, 0, height - h))


def stack_padded(tensors: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Stack (C, H_i, W_i) tensors into (B, C, H, W) zero-padded at the bottom/right, with
    a (B, H, W) bool mask of the valid positions."""
    height = max(t.shape[-2] for t in tensors)
    width = max(t.shape[-1] for t in tensors)
    batch = torch.stack([pad_to_shape(t, height, width) for t in tensors])
    mask = torch.zeros(len(tensors), height, width, dtype=torch.bool, device=batch.device)
    for i, t in enumerate(tensors):
        mask[i, : t.shape[-2], : t.shape[-1]] = True
    return batch, mask
