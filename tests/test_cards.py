"""Scanned cards (colmap_guided/cards.py): the picture inside the card, collage cards split into
their panels, repeated prints mapped once; on real postcards (where ../shared is present) and on
cards made of rendered views with exact poses."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_guided import archival, cards
from colmap_guided import database as dbio
from colmap_guided.reconstruct import reconstruct
from recon_scripts.evaluation.ground_truth import pose_errors

PAPER = (236, 240, 244)  # a white card, in RGB
# views of the synthetic scene used as prints: two on a collage card, one on a captioned card,
# one printed twice (the second a crop, rescaled)
COLLAGE, CAPTIONED, REPRINTED = ("view_000.jpg", "view_001.jpg"), "view_002.jpg", "view_003.jpg"
GUTTER, BORDER = 24, 40
CAPTION_LINES = ("Gruss aus der Altstadt - Rathaus und Markt", "Verlag 1931")


def read_rgb(path: Path) -> np.ndarray:
    return cv2.imread(str(path))[:, :, ::-1].copy()


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    cv2.imwrite(str(path), rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])


@pytest.fixture(scope="module")
def card_scene(synthetic_scene, tmp_path_factory):
    """A folder of photos as an archive holds them: the scene's views, two of them only on one
    collage card, one only on a captioned card, one also as a cropped, rescaled second print."""
    root = tmp_path_factory.mktemp("cards")
    folder = root / "images"
    folder.mkdir()
    source = synthetic_scene.image_dir
    for name in synthetic_scene.names:
        if name not in (*COLLAGE, CAPTIONED):
            shutil.copy(source / name, folder / name)
    views = [read_rgb(source / n) for n in COLLAGE]
    collage, collage_boxes = archival.collage(views, PAPER, BORDER, GUTTER)
    write_rgb(folder / "collage.jpg", collage)
    captioned, picture = archival.mount(read_rgb(source / CAPTIONED), PAPER, BORDER, CAPTION_LINES)
    write_rgb(folder / "captioned.jpg", captioned)
    view = read_rgb(source / REPRINTED)
    h, w = view.shape[:2]
    crop = view[h // 10 : h - h // 20, w // 8 : w - w // 10]
    write_rgb(folder / "reprint.jpg", cv2.resize(crop, None, fx=0.9, fy=0.9))
    return root, collage_boxes, picture


def test_layouts_of_rendered_cards(card_scene):
    root, collage_boxes, picture = card_scene
    collage = cards.find_layout(root / "images" / "collage.jpg")
    assert len(collage.panels) == 2
    for found, true in zip(collage.panels, collage_boxes):
        assert np.abs(np.subtract(found, true)).max() <= 3, (found, true)
    captioned = cards.find_layout(root / "images" / "captioned.jpg")
    assert not captioned.panels and captioned.border
    assert np.abs(np.subtract(captioned.picture, picture)).max() <= 3
    # an ordinary photo keeps every pixel
    assert cards.find_layout(root / "images" / "view_004.jpg").whole


@pytest.fixture(scope="module")
def card_run(card_scene):
    root, _, _ = card_scene
    before = {p.name: p.read_bytes() for p in (root / "images").iterdir()}
    result = reconstruct(root, output=root / "out", matcher="raw")
    return result, before


def panel_names(result: dict) -> list[str]:
    return [panel["name"] for panel in result["cards"]["collage.jpg"]["panels"]]


def test_collage_panels_register_on_their_true_poses(card_scene, card_run, synthetic_scene):
    root, _, _ = card_scene
    result, before = card_run
    # named in the report by their path inside the workspace, as they are cropped into it only
    names = panel_names(result)
    assert names == ["panels/collage_p1.jpg", "panels/collage_p2.jpg"]
    assert all((root / "out" / n).is_file() for n in names)
    # the database and the model name them as COLMAP reads them: from the photo folder
    names = [os.path.relpath(root / "out" / n, root / "images") for n in names]
    # the photos are untouched
    assert {p.name: p.read_bytes() for p in (root / "images").iterdir()} == before
    assert all(panel["registered"] for panel in result["cards"]["collage.jpg"]["panels"])
    # a card's panels are a publisher's different views: their pair waits for escalation
    with dbio.open_database(root / "out" / "database.db") as db:
        assert not dbio.pair_has_matches(db, *(dbio.read_image(db, n).image_id for n in names))
    # the model aligned to the truth (the panels and the captioned card under their views' names)
    model = pycolmap.Reconstruction(str(root / "out" / "sparse" / "0"))
    true_name = {**dict(zip(names, COLLAGE)), "captioned.jpg": CAPTIONED}
    for image in model.images.values():
        image.name = true_name.get(image.name, image.name)
    errors = pose_errors(model, synthetic_scene)
    assert max(errors[name][0] for name in COLLAGE) < 1.0, errors
    assert max(errors[name][1] for name in COLLAGE) < 0.02, errors
    saved = (root / "out" / "report.json").read_text()
    page = (root / "out" / "report.html").read_text()
    assert json.loads(saved)["cards"]["collage.jpg"]["panels"][0]["name"] == panel_names(result)[0]
    assert "panels/collage_p2.jpg" in page
    assert not [text for text in (saved, page) if "../out/panels" in text]


def test_captioned_card_registers_with_no_inlier_off_its_picture(card_scene, card_run):
    root, _, picture = card_scene
    result, _ = card_run
    assert "captioned.jpg" in result["model"]["registered_images"]
    assert result["cards"]["captioned.jpg"]["keypoints_masked"] > 0
    with dbio.open_database(root / "out" / "database.db") as db:
        image_id = dbio.read_image(db, "captioned.jpg").image_id
        xy = dbio.read_keypoints(db, image_id)[:, :2]
        used = [
            xy[inliers[:, 0 if a == image_id else 1]]
            for (a, b), inliers in dbio.read_verified_inliers(db).items()
            if image_id in (a, b)
        ]
    used = np.concatenate(used)
    assert len(used) > 50
    assert cards.in_box(used, picture).all()


def test_card_workspace_page_draws_its_model_in_headless_chromium(chromium, card_run, tmp_path):
    from recon_scripts.evaluation.screenshot import screenshot, view_pixels

    result, _ = card_run
    # raises where the page writes to the console (a script error)
    png = screenshot(Path(result["html_report_path"]), tmp_path / "shot.png", (1200, 900))
    assert view_pixels(png) > 2000, "the 3D view shows nothing"


def test_a_reprint_is_grouped_and_mapped_once(card_run):
    result, _ = card_run
    prints = result["repeated_prints"]
    assert set(prints) | {e["same_picture_as"] for e in prints.values()} == {
        REPRINTED,
        "reprint.jpg",
    }
    ((copy, evidence),) = prints.items()
    assert evidence["inlier_ratio"] >= 0.9
    assert result["unregistered"][copy]["stage"] == "repeated print"
    # every other photo is mapped
    others = set(result["model"]["registered_images"]) | {copy}
    assert len(others) == result["num_images"]


# pictures on each card of postcards_cmahnke, counted by eye; every other card holds one
COLLAGES = {
    "boerse-essen/images/boerse-essen-2.jpg": 4,
    "boerse-essen/images/boerse-essen-3.jpg": 4,
    "boettcherstrasse/images/boettcherstrasse-2.jpg": 3,  # (and a coat of arms)
    "wilhelmshaven/images/wilhelmshaven-1.jpg": 9,
    "wilhelmshaven/images/wilhelmshaven-2.jpg": 9,
}


def test_panel_counts_on_real_postcards(shared_data):
    root = shared_data / "postcards_cmahnke"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    found = {
        path.relative_to(root).as_posix(): cards.find_layout(path)
        for path in sorted(root.glob("*/images/*.jpg"))
    }
    assert len(found) == 19
    assert {name: len(layout.panels) for name, layout in found.items() if layout.panels} == (
        COLLAGES
    )
    for name, layout in found.items():
        x0, y0, x1, y1 = layout.picture
        # the picture is most of the card (never a caption band or a corner)
        assert (x1 - x0) * (y1 - y0) > 0.75 * layout.size[0] * layout.size[1], name


def test_ordinary_photos_keep_every_pixel(shared_data):
    names = {
        folder: sorted(p.name for p in (shared_data / folder / "images").iterdir())
        for folder in ("sacre_coeur_hloc", "lund_door_gtsfm")
        if (shared_data / folder / "images").is_dir()
    }
    if not names:
        pytest.skip("no ordinary photo sets in the shared data")
    for folder, photos in names.items():
        layouts = cards.find_layouts(
            shared_data / folder / "images", photos, cards.check_conf(None)
        )
        assert layouts == {}, folder


@pytest.mark.slow
def test_real_repeated_prints_are_grouped_and_ordinary_pairs_are_not(shared_data, tmp_path):
    essen = shared_data / "postcards_cmahnke" / "boerse-essen"
    if not essen.is_dir():
        pytest.skip(f"{essen} not found")
    result = reconstruct(essen, output=tmp_path / "essen", matcher="raw")
    pairs = {
        (Path(name).name, Path(e["same_picture_as"]).name)
        for name, e in result["repeated_prints"].items()
    }
    # each panel of one print with the same panel of the other
    assert {tuple(sorted(pair)) for pair in pairs} == {
        (f"boerse-essen-2_p{k}.jpg", f"boerse-essen-3_p{k}.jpg") for k in range(1, 5)
    }
    for scene in ("sacre_coeur_hloc", "lund_door_gtsfm"):
        result = reconstruct(shared_data / scene, output=tmp_path / scene, matcher="raw")
        assert result["database"]["num_verified_pairs"] > 10
        assert result["repeated_prints"] == {}, scene
