"""What report.html embeds: pictures as data URIs, and the page's script and style sheet
(``assets/``)."""

from __future__ import annotations

import base64
import io
from importlib import resources

import numpy as np


def asset(name: str) -> str:
    """A file of colmap_guided/assets (package data: a wheel ships it)."""
    return resources.files(__package__).joinpath("assets", name).read_text(encoding="utf-8")


def data_uri(png_or_jpeg: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(png_or_jpeg).decode('ascii')}"


def encode_jpeg(rgb: np.ndarray, quality: int = 85) -> str:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb)).save(buf, format="JPEG", quality=quality)
    return data_uri(buf.getvalue(), "image/jpeg")


def figure_uri(fig, photo: bool = False) -> str:
    """The figure as a data URI: PNG for plots, JPEG for photo drawings (ten times smaller)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches=None if photo else "tight")
    plt.close(fig)
    if not photo:
        return data_uri(buf.getvalue(), "image/png")
    from PIL import Image

    return encode_jpeg(np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB")), 88)
