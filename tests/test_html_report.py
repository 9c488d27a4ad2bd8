"""report.html: self-contained, shows the model it was made from, says why a photo did not register,
draws matches where they are, renders in Chromium."""

from __future__ import annotations

import base64
import html
import io
import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from PIL import Image

from colmap_guided import database as dbio
from colmap_guided import html_report, model_view, report
from colmap_guided.mapping import load_models
from colmap_guided.reconstruct import reconstruct

REPO = Path(__file__).resolve().parent.parent
PAIR_FIGURE = re.compile(
    r"<figure class='pair'><figcaption>[^<]*</figcaption>"
    r"<img src='data:(image/jpeg);base64,([A-Za-z0-9+/=]+)'"
)
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
        "eras": {
            "historical": {"num_images": 2, "num_registered": 0, "registered_ratio": 0.0},
            "modern": {"num_images": 3, "num_registered": 2, "registered_ratio": 2 / 3},
        },
        "skipped_images": {
            "broken.jpg": "damaged or truncated image (image "
            "file is truncated); copy or scan it again"
        },
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
    panels = [
        ("guided: a \u2194 b", black, black, np.array([[0.5, 0.5, 199.5, 99.5]])),
        ("raw: a \u2194 b", folder / "a.jpg", folder / "b.jpg", np.zeros((0, 4))),
    ]
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


@pytest.fixture(scope="module")
def run_with_strangers(synthetic_scene, tmp_path_factory):
    """The synthetic scene plus a photo of something else (smooth noise) and a blank one; a manifest
    with eras."""
    scene = tmp_path_factory.mktemp("strangers") / "scene"
    shutil.copytree(synthetic_scene.image_dir, scene / "images")
    small = np.random.default_rng(1).integers(0, 255, (60, 80, 3), dtype=np.uint8)
    Image.fromarray(cv2.resize(small, (640, 480), interpolation=cv2.INTER_CUBIC)).save(
        scene / "images" / "unrelated.jpg"
    )
    Image.fromarray(
        np.tile(np.linspace(90, 110, 640)[None, :, None], (480, 1, 3)).astype(np.uint8)
    ).save(scene / "images" / "blank.png")
    eras = {
        name: "historical" if i % 3 == 0 else "modern"
        for i, name in enumerate(synthetic_scene.names)
    }
    (scene / "manifest.json").write_text(
        json.dumps({"images": [{"name": n, "era": e} for n, e in eras.items()]})
    )
    out = tmp_path_factory.mktemp("strangers_out")
    result = reconstruct(scene, output=out, matcher="raw")
    return result, out, eras


def _model_data(page: str) -> dict:
    found = re.search(r"<script type='application/json' id='model-data'>(.*?)</script>", page, re.S)
    assert found, "the page has no 3D view"
    return json.loads(found.group(1))  # the page writes "</" as "<\/" (valid JSON)


def test_page_shows_the_model_it_was_made_from(run_with_strangers, synthetic_scene):
    result, out, eras = run_with_strangers
    page = (out / "report.html").read_text(encoding="utf-8")
    assert result["html_report_path"] == str(out / "report.html")
    assert (
        not re.search(r"(src|href)=['\"](?!data:)", page)
        and "http://" not in page
        and "https://" not in page
    )
    assert "verified matches" in page and page.count("<figure class='pair'>") == 3
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    data = _model_data(page)
    # Every point of the model (fewer than MAX_POINTS here), at its place, and every registered
    # camera.
    assert (
        data["num_points_total"]
        == data["num_points_shown"]
        == rec.num_points3D()
        == result["num_points3D"]
        > 500
    )
    assert f"all {rec.num_points3D():,} points" in page
    shown = model_view.decode_points(data)
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    step = np.linalg.norm(np.array(data["quant"]["step"])) * data["frame"]["radius"]
    assert shown.shape == xyz.shape
    assert np.abs(np.sort(shown, axis=0) - np.sort(xyz, axis=0)).max() < step
    names = sorted(im.name for im in rec.images.values() if im.has_pose)
    assert [c["name"] for c in data["cameras"]] == names == sorted(synthetic_scene.names)
    frame = data["frame"]
    for cam in data["cameras"]:
        centre = np.array(cam["c"]) * frame["radius"] @ np.array(frame["axes"]) + np.array(
            frame["origin"]
        )
        assert (
            np.linalg.norm(centre - rec.find_image_with_name(cam["name"]).projection_center())
            < 1e-3 * frame["radius"]
        )
        assert cam["era"] == eras[cam["name"]] and cam["thumb"].startswith(
            "data:image/jpeg;base64,"
        )
    assert set(data["colors_by_era"]) == {"historical", "modern"}
    # The up direction: the photos were taken upright, so the cameras' up vectors agree with it.
    up = np.array(frame["axes"])[2]
    assert all(
        -rec.images[i].cam_from_world().rotation.matrix()[1] @ up > 0.9 for i in rec.reg_image_ids()
    )
    # A large model is shown by a sample, and the page says so.
    sample = model_view.view_data(rec, eras, max_points=100)
    assert (
        sample["num_points_shown"] == 100
        and len(model_view.decode_points(sample)) == 100
        and sample["num_points_total"] == rec.num_points3D()
    )
    assert f"100 of the {rec.num_points3D():,} points" in model_view.view_html(
        rec, eras, max_points=100
    )


def test_each_photo_that_did_not_register_says_where_and_why(run_with_strangers):
    result, out, _ = run_with_strangers
    assert result["model"]["unregistered_images"] == ["blank.png", "unrelated.jpg"]
    saved = json.loads((out / "report.json").read_text(encoding="utf-8"))
    why = saved["unregistered"]
    assert why == result["unregistered"] and set(why) == {"blank.png", "unrelated.jpg"}
    assert (
        why["blank.png"]["stage"] == "features"
        and why["blank.png"]["num_keypoints"] < report.MIN_KEYPOINTS
    )
    stranger = why["unrelated.jpg"]
    assert (
        stranger["stage"] == "matching"
        and stranger["verified_pairs"] == 0
        and stranger["best_pair"] is None
    )
    assert (
        stranger["num_keypoints"] > 500
        and stranger["best_candidate"] in result["model"]["registered_images"]
    )
    page = (out / "report.html").read_text(encoding="utf-8")
    for entry in why.values():
        assert html.escape(entry["reason"]) in page and html.escape(entry["suggestion"]) in page
    assert (
        "In no model (stage where it dropped out): "
        "blank.png (features), unrelated.jpg (matching)" in report.summary_text(result)
    )


def test_later_stages_are_told_apart(run_with_strangers):
    """A photo with verified pairs that the mapper left out (``mapping``); one placed in a smaller
    model is that model's result, not a photo left out."""
    result, out, _ = run_with_strangers
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    names = sorted(rec.images[i].name for i in rec.reg_image_ids())
    left_out = pycolmap.Reconstruction(rec)
    left_out.deregister_frame(rec.find_image_with_name(names[0]).frame_id)
    # a second, smaller model that holds names[0] and names[1] only
    alone = pycolmap.Reconstruction(rec)
    for name in names[2:]:
        alone.deregister_frame(rec.find_image_with_name(name).frame_id)
    database = out / "database.db"
    everyone = names + ["blank.png", "unrelated.jpg"]
    mapping_stage = report.explain_unregistered(database, {0: left_out}, everyone, {})[names[0]]
    separate = report.explain_unregistered(database, {0: left_out, 1: alone}, everyone, {})
    with dbio.open_database(database) as db:
        image_id = db.read_image_with_name(names[0]).image_id
        pair_ids, counts = db.read_two_view_geometry_num_inliers()
        mine = {
            pair_id: n
            for pair_id, n in zip(pair_ids, counts)
            if n > 0 and image_id in pycolmap.pair_id_to_image_pair(pair_id)
        }
    assert mapping_stage["stage"] == "mapping" and mapping_stage["verified_pairs"] == len(mine) > 0
    assert (
        mapping_stage["best_inliers"] == max(mine.values())
        and mapping_stage["best_pair"] in names[1:]
    )
    assert mapping_stage["best_pair"] in mapping_stage["suggestion"]
    assert names[0] not in separate and set(separate) == {"blank.png", "unrelated.jpg"}
    entries = report.model_entries({0: left_out, 1: alone}, {0: [], 1: ["a problem"]}, {})
    assert [(m["path"], m["images"], m["passes_check"]) for m in entries] == [
        ("sparse/0", names[1:], True),
        ("sparse/1", names[:2], False),
    ]


def test_every_model_is_a_result(two_buildings, synthetic_scene):
    result, out, _ = two_buildings
    sparse = load_models(out / "sparse")
    others = sorted(f"other_view_{i:03d}.jpg" for i in range(6))
    assert [sorted(rec.images[i].name for i in rec.reg_image_ids()) for rec in sparse.values()] == [
        sorted(synthetic_scene.names),
        others,
    ]
    # each model listed with its photos and check, exported beside it
    assert [(m["path"], m["images"], m["passes_check"]) for m in result["models"]] == [
        ("sparse/0", sorted(synthetic_scene.names), True),
        ("sparse/1", others, True),
    ]
    for m, rec in zip(result["models"], sparse.values()):
        text = pycolmap.Reconstruction(m["exports"]["text"])
        assert text.num_points3D() == rec.num_points3D() == m["num_points3D"] > 100
        assert Path(m["exports"]["ply"]) == out / m["path"] / "points3D.ply"
    # the other building's photos are its model's, not photos that failed
    assert result["unregistered"] == {}
    text = report.summary_text(result)
    assert "1 other model(s), photos in each: sparse/1 (6)" in text and "In no model" not in text
    assert "Joining models: 1 tried, 0 joined (report.html)" in text
    page = (out / "report.html").read_text(encoding="utf-8")
    assert "<option value='1'>sparse/1: 6 photos</option>" in page
    assert "Photos in no model, and why (0)" in page and "<h2>The models (2)</h2>" in page
    # the two were tried for joining: their pairs, matched in the first pass, verified none
    (tried,) = result["database"]["joins"]
    assert "<h2>Joining models (1 tried, 0 joined)</h2>" in page
    assert "<tr><td>sparse/0 (8) and sparse/1 (6)</td><td class='num'>0 / 0</td>" in page
    assert f"<td>no: {tried['why']}</td></tr>" in page
    assert sorted(c["name"] for c in _strict(page, "model-data-1")["cameras"]) == others


def test_page_opens_the_model_that_holds_a_linked_photo(chromium, two_buildings, tmp_path):
    from recon_scripts.evaluation.screenshot import screenshot, view_pixels

    _, out, _ = two_buildings
    full = screenshot(out / "report.html", tmp_path / "first.png", (1200, 900))
    linked = screenshot(
        out / "report.html", tmp_path / "second.png", (1200, 900), photo="other_view_002.jpg"
    )
    assert view_pixels(full) > 2000 and view_pixels(linked) > 2000
    # another model on screen: the view differs
    a, b = (np.asarray(Image.open(p).convert("RGB")).astype(int) for p in (full, linked))
    assert np.abs(a - b).sum(axis=2).astype(bool).sum() > 5000


def test_model_is_exported_for_other_tools(run_with_strangers):
    result, out, _ = run_with_strangers
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    ply = Path(result["exports"]["ply"])
    assert ply == out / "sparse" / "0" / "points3D.ply"
    header = ply.read_bytes().split(b"end_header")[0].decode("ascii")
    assert header.startswith("ply") and f"element vertex {rec.num_points3D()}" in header
    text = pycolmap.Reconstruction(result["exports"]["text"])
    assert (text.num_points3D(), text.num_reg_images()) == (
        rec.num_points3D(),
        rec.num_reg_images(),
    )
    assert (Path(result["exports"]["text"]) / "points3D.txt").is_file()
    # the exports beside the model leave sparse/N readable as before
    models = load_models(out / "sparse")
    assert list(models) == [0] and models[0].num_points3D() == rec.num_points3D()


def test_model_view_draws_in_headless_chromium(chromium, run_with_strangers, tmp_path):
    from recon_scripts.evaluation.screenshot import screenshot, view_pixels

    _, out, eras = run_with_strangers
    # raises where the page writes to the console (a script error)
    png = screenshot(out / "report.html", tmp_path / "shot.png", (1200, 900))
    # The canvas's dark background, many coloured points on it, and frusta in both era colours.
    assert view_pixels(png) > 2000, "the 3D view shows nothing"
    shot = np.asarray(Image.open(png).convert("RGB")).astype(int)
    for hex_color in {model_view.ERA_COLORS[era] for era in eras.values()}:
        rgb = np.array([int(hex_color[i : i + 2], 16) for i in (1, 3, 5)])
        assert (np.abs(shot - rgb).sum(axis=2) < 40).sum() > 30, hex_color


def _undistortion_fails(rec: pycolmap.Reconstruction) -> str:
    """Gives one registered photo's camera a strong barrel distortion (as bundle adjustment may
    estimate for a print), under which its image corners cannot be undistorted; returns its name."""
    image = rec.images[min(rec.reg_image_ids())]
    camera = rec.cameras[image.camera_id]
    f, cx, cy = camera.mean_focal_length(), camera.principal_point_x, camera.principal_point_y
    rec.cameras[image.camera_id] = pycolmap.Camera(
        camera_id=camera.camera_id,
        model="SIMPLE_RADIAL",
        width=camera.width,
        height=camera.height,
        params=[f, cx, cy, -0.5],
    )
    corner = rec.cameras[image.camera_id].cam_from_img(np.array([[0.0, 0.0]]))
    assert not np.isfinite(corner).all(), "the camera was meant to fail undistortion"
    return image.name


def _strict(page: str, block: str = "model-data") -> dict:
    found = re.search(rf"<script type='application/json' id='{block}'>(.*?)</script>", page, re.S)
    assert found, "the page has no 3D view"

    def refuse(constant):
        raise AssertionError(f"the page's data holds {constant}: not JSON, the browser refuses it")

    return json.loads(found.group(1), parse_constant=refuse)


def test_a_camera_that_cannot_be_undistorted_keeps_the_view_valid(run_with_strangers):
    _, out, eras = run_with_strangers
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    name = _undistortion_fails(rec)
    data = _strict(model_view.view_html(rec, eras))
    assert [c["name"] for c in data["cameras"]] == sorted(
        rec.images[i].name for i in rec.reg_image_ids()
    )
    # the frustum is drawn from the camera's pinhole part: a symmetric pyramid around its axis
    cam = next(c for c in data["cameras"] if c["name"] == name)
    corners = np.array(cam["f"]) - np.array(cam["c"])
    axis = corners.mean(axis=0)
    assert np.isfinite(corners).all() and np.linalg.norm(axis) > 0
    assert np.ptp(np.linalg.norm(corners - axis, axis=1)) < 1e-3


def test_page_with_such_a_camera_draws_in_headless_chromium(chromium, run_with_strangers, tmp_path):
    from recon_scripts.evaluation.screenshot import screenshot, view_pixels

    result, out, _ = run_with_strangers
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    _undistortion_fails(rec)
    page = html_report.write_html_report(tmp_path / "report.html", result, [], rec)
    png = screenshot(page, tmp_path / "shot.png", (1200, 900))
    assert view_pixels(png) > 2000, "the 3D view shows nothing"


@pytest.mark.slow
def test_page_renders_in_headless_chromium(chromium, tmp_path):
    from recon_scripts.evaluation.screenshot import screenshot

    folder = tmp_path / "images"
    (folder / "old").mkdir(parents=True)
    for name in ("a.jpg", "b.jpg", "c.jpg", "old/d.jpg"):
        Image.fromarray(np.full((90, 120, 3), 200, np.uint8)).save(folder / name)
    path = html_report.write_html_report(tmp_path / "report.html", _report(folder), [])
    png = screenshot(path, tmp_path / "shot.png", (1000, 1400))
    shot = np.asarray(Image.open(png).convert("RGB")).astype(int)
    assert shot.shape == (1400, 1000, 3)
    # The plot's bars are drawn: the 'registered' green (#3b7d3c) and 'skipped' red (#a23b2a) are on
    # screen.
    for rgb in ((0x3B, 0x7D, 0x3C), (0xA2, 0x3B, 0x2A)):
        assert (np.abs(shot - np.array(rgb)).sum(axis=2) < 30).sum() > 200, rgb
