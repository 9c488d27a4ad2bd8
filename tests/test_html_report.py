"""report.html: self-contained, says what a historian needs, draws matches where they are, renders in Chromium."""

from __future__ import annotations

import base64
import io
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from colmap_guided import html_report
from colmap_guided.reconstruct import reconstruct
from colmap_guided.synthetic import render_scene

REPO = Path(__file__).resolve().parent.parent
PAIR_FIGURE = re.compile(r"<figure class='pair'><figcaption>[^<]*</figcaption><img src='data:(image/jpeg);base64,([A-Za-z0-9+/=]+)'")
DATA_URI = re.compile(r"src='data:(image/(?:png|jpeg));base64,([A-Za-z0-9+/=]+)'")


def _report(image_path: Path) -> dict:
    names = ["a.jpg", "b.jpg", "c.jpg", "old/d.jpg", "broken.jpg"]
    return {
        "scene": "Tour Saint-Jacques",
        "image_path": str(image_path),
        "matcher": {"name": "guided"},
        "model": {
            "num_images": 5,
            "num_registered": 2,
            "registered_ratio": 0.4,
            "num_models": 2,
            "num_points3D": 1234,
            "mean_track_length": 3.5,
            "mean_reprojection_error": 0.61,
            "registered_images": ["a.jpg", "b.jpg"],
            "unregistered_images": ["broken.jpg", "c.jpg", "old/d.jpg"],
        },
        "eras": {"historical": {"num_images": 2, "num_registered": 0, "registered_ratio": 0.0}, "modern": {"num_images": 3, "num_registered": 2, "registered_ratio": 2 / 3}},
        "skipped_images": {"broken.jpg": "damaged or truncated image (image file is truncated); copy or scan it again"},
        "timings": {"extract": 1.0, "match": 2.0},
        "database": {"num_pairs": 10},
        "_names": names,
    }


def _decode(uri_b64: str) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(uri_b64))).convert("RGB"))


def test_page_is_self_contained_and_lists_what_matters(tmp_path):
    folder = tmp_path / "images"
    (folder / "old").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for name in ("a.jpg", "b.jpg", "c.jpg", "old/d.jpg"):
        Image.fromarray(rng.integers(0, 255, (90, 120, 3), dtype=np.uint8)).save(folder / name)
    (folder / "broken.jpg").write_bytes(b"\xff\xd8broken")
    report = _report(folder)

    # One match drawn from the top-left pixel centre of A to the bottom-right pixel centre of B
    # (COLMAP coordinates: pixel (col, row) has its centre at (col + 0.5, row + 0.5)).
    black = np.zeros((100, 200, 3), np.uint8)
    panels = [("guided: a \u2194 b", black, black, np.array([[0.5, 0.5, 199.5, 99.5]])), ("raw: a \u2194 b", folder / "a.jpg", folder / "b.jpg", np.zeros((0, 4)))]
    path = html_report.write_html_report(tmp_path / "report.html", report, panels)
    page = path.read_text(encoding="utf-8")

    assert not re.search(r"(src|href)=['\"](?!data:)", page), "every image must be embedded"
    assert "http://" not in page and "https://" not in page
    assert "40&nbsp;%" in page and "2 of 5 images" in page
    assert "historical" in page and "0/2" in page and "modern" in page and "2/3" in page
    for name in ("c.jpg", "old/d.jpg"):
        assert name in page
    assert "copy or scan it again" in page
    uris = DATA_URI.findall(page)
    assert len(uris) >= 5  # plot, 2 unregistered thumbnails, 2 match drawings
    drawings = [_decode(b64) for _, b64 in PAIR_FIGURE.findall(page)]
    assert len(drawings) == 2 and drawings[1].shape == (90, 250, 3)
    first = drawings[0].astype(int)
    h, w = first.shape[:2]
    assert (w, h) == (410, 100)  # two 200-px images and a 10-px gap
    # The line runs from (0, 0) to the last pixel of B: lit near its middle, dark far from it.
    mid = first[h // 2 - 3 : h // 2 + 4, w // 2 - 3 : w // 2 + 4].max()
    assert mid > 60
    assert first[5:15, 150:190].max() < 40 and first[85:95, 220:260].max() < 40


def test_reconstruct_writes_the_page(tmp_path):
    render_scene(tmp_path / "scene", num_images=4, width=400, height=300)
    result = reconstruct(tmp_path / "scene", output=tmp_path / "out", matcher="raw")
    page = (tmp_path / "out" / "report.html").read_text(encoding="utf-8")
    assert result["html_report_path"] == str(tmp_path / "out" / "report.html")
    assert "verified matches" in page and page.count("<figure class='pair'>") == 3


@pytest.mark.slow
def test_page_renders_in_headless_chromium(tmp_path):
    sys.path.insert(0, str(REPO / "recon_scripts"))
    from render_report_screenshot import find_chromium, screenshot

    if find_chromium() is None:
        pytest.skip("Chromium is not installed (Debian: apt-get install chromium)")
    folder = tmp_path / "images"
    (folder / "old").mkdir(parents=True)
    for name in ("a.jpg", "b.jpg", "c.jpg", "old/d.jpg"):
        Image.fromarray(np.full((90, 120, 3), 200, np.uint8)).save(folder / name)
    path = html_report.write_html_report(tmp_path / "report.html", _report(folder), [])
    png = screenshot(path, tmp_path / "shot.png", (1000, 1400))
    shot = np.asarray(Image.open(png).convert("RGB")).astype(int)
    assert shot.shape == (1400, 1000, 3)
    # The plot's bars are drawn: the 'registered' green (#3b7d3c) and 'skipped' red (#a23b2a) are on screen.
    for rgb in ((0x3B, 0x7D, 0x3C), (0xA2, 0x3B, 0x2A)):
        assert (np.abs(shot - np.array(rgb)).sum(axis=2) < 30).sum() > 200, rgb
