"""`localize` on a real COLMAP workspace: a model of six synthetic views, two held-out views placed
on their true poses (one without EXIF: focal length estimated), a photo of another scene not placed,
the model only read, a rerun that redoes nothing, and --add writing a new model version beside the
old one."""

from __future__ import annotations

import hashlib
import json
import logging
import re
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from colmap_guided import database as dbio
from colmap_guided import localize as loc
from colmap_guided.__main__ import main
from colmap_guided.log import set_verbosity
from colmap_guided.reconstruct import reconstruct
from colmap_guided.synthetic import render_scene
from colmap_guided.workspace import read_marker
from recon_scripts.evaluation.registration import compare_poses, model_poses

HELD_OUT = ("view_002.jpg", "view_005.jpg")
OUR_ERROR = re.compile(r"^\[[\d:]+ colmap_guided ERROR\] (.+)$", re.MULTILINE)


def digests(folder: Path) -> dict[str, str]:
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(Path(folder).rglob("*"))
        if p.is_file()
    }


def database_content(path: Path) -> dict:
    with dbio.open_database(path) as db:
        summary = dbio.database_summary(db)
        images = dbio.images_by_name(db)
        keypoints = {
            name: dbio.read_keypoints(db, image.image_id).tobytes()
            for name, image in images.items()
        }
    return {"summary": summary, "keypoints": keypoints}


def pose_of(entry: dict) -> tuple[np.ndarray, np.ndarray]:
    w, x, y, z = entry["qvec_wxyz"]
    return pycolmap.Rotation3d(np.array([x, y, z, w])).matrix(), np.array(entry["tvec"])


@pytest.fixture(scope="module")
def workspace(synthetic_scene, tmp_path_factory):
    """A reconstruct workspace of the synthetic views but the held-out ones; the photos to localize:
    a held-out view, the other re-saved without EXIF (a scan: no focal length), a view of another
    scene, a missing file."""
    root = tmp_path_factory.mktemp("localize")
    model_images = root / "model" / "images"
    model_images.mkdir(parents=True)
    for name in synthetic_scene.names:
        if name not in HELD_OUT:
            shutil.copy(synthetic_scene.image_dir / name, model_images / name)
    ws = root / "ws"
    mapping = {"mapper": "incremental", "num_threads": 1}
    result = reconstruct(model_images.parent, output=ws, matcher="raw", mapping_conf=mapping)
    assert result["num_registered"] >= 5
    scans = root / "scans"
    scans.mkdir()
    # no EXIF
    Image.open(synthetic_scene.image_dir / HELD_OUT[1]).save(scans / HELD_OUT[1], quality=95)
    other = render_scene(root / "other", num_images=2, seed=5)
    (ws / "notes.txt").write_text("the user's own notes\n")
    photos = [
        synthetic_scene.image_dir / HELD_OUT[0],
        scans / HELD_OUT[1],
        other.image_dir / other.names[0],
    ]
    before = {"sparse": digests(ws / "sparse"), "database": database_content(ws / "database.db")}
    before["photos"] = {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in photos}
    broken = root / "broken.jpg"
    broken.write_bytes(b"not a photo")
    bad = {"missing": root / "lost.jpg", "broken": broken}
    return {
        "ws": ws,
        "photos": photos,
        "before": before,
        "images": model_images,
        "root": root,
        **bad,
    }


@pytest.fixture(scope="module")
def first(workspace):
    out = loc.localize(
        workspace["ws"], [*workspace["photos"], workspace["missing"], workspace["broken"]]
    )
    return out, {
        Path(e["photo"]).name + ("@scan" if "scans" in e["photo"] else ""): e for e in out["photos"]
    }


def test_held_out_views_are_placed_on_their_true_pose(first, workspace, synthetic_scene):
    _out, by_name = first
    placed = {name: e for name, e in by_name.items() if name.startswith(HELD_OUT)}
    assert len(placed) == 2 and all(
        e["status"] == "placed" and e["confidence"] == "placed" for e in placed.values()
    )
    model = pycolmap.Reconstruction(str(workspace["ws"] / "sparse" / "0"))
    est = model_poses(model)
    est.update({name: pose_of(e) for name, e in placed.items()})
    ref = {name: synthetic_scene.cam_from_world[name.split("@")[0]] for name in est}
    errors = compare_poses(est, ref)
    for name in placed:  # the model aligned to the ground truth by a similarity
        assert errors[name]["rotation_error"] < 1.0 and errors[name]["center_error"] < 0.02, errors
    true_focal = synthetic_scene.K[0, 0]
    for entry in placed.values():
        assert entry["num_inliers"] >= 30 and entry["reprojection_error"] < 2.0
        assert abs(entry["focal_length"] / true_focal - 1) < 0.03, entry  # estimated for the scan
        assert entry["matched_images"][0]["matches"] > 50
        assert {m["image"] for m in entry["matched_images"]} <= {
            p.name for p in workspace["images"].iterdir()
        }


def test_a_photo_of_another_place_and_a_missing_file_are_not_placed(first, workspace):
    out, by_name = first
    other = by_name["view_000.jpg"]
    assert other["status"] == "not placed" and other["confidence"].startswith("not placed")
    assert "qvec_wxyz" not in other
    assert out["skipped"] == {str(workspace["missing"]): "no such file"}
    broken = by_name["broken.jpg"]
    assert broken["status"] == "skipped" and broken["confidence"].startswith("not placed: ")
    text = loc.summary_text(out)
    assert (
        f"{workspace['missing']}: not placed: no such file" in text
        and "Placed 2 of 5 photo(s)" in text
    )


def test_the_model_photos_and_user_files_are_only_read(first, workspace):
    ws, before = workspace["ws"], workspace["before"]
    assert digests(ws / "sparse") == before["sparse"]
    # COLMAP's open rewrites its header only
    assert database_content(ws / "database.db") == before["database"]
    assert {
        str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in workspace["photos"]
    } == before["photos"]
    assert (ws / "notes.txt").read_text() == "the user's own notes\n"
    entries = set(read_marker(ws)["entries"])
    assert {"localized.json", "localize.db", "sparse_localized", "report.json", "sparse"} <= entries
    saved = json.loads((ws / "localized.json").read_text())
    assert (
        saved["model_sha256"] == loc.model_digest(ws / "sparse" / "0") and len(saved["photos"]) == 4
    )


def test_the_report_shows_the_localized_photos(first, workspace):
    page = (workspace["ws"] / "report.html").read_text(encoding="utf-8")
    assert "Photos localized in the model (2 of 4 placed)" in page
    section = page[page.index("Photos localized in the model") :]
    assert "view_002.jpg" in section and "not placed: no image of the model matched" in section
    assert section.count("<img") >= 4  # each placed photo beside its best-matched model photo
    data = json.loads(
        re.search(r"<script[^>]*id='model-data'[^>]*>(.*?)</script>", page, re.DOTALL).group(1)
    )
    # highlighted in the 3D view
    shown = {c["name"] for c in data["cameras"] if c["era"] == "localized"}
    assert {Path(name).name for name in shown} == set(HELD_OUT)


def logged(*args, **kwargs) -> tuple[dict, list[str]]:
    """``localize(*args, **kwargs)`` and the messages it logged (at the default verbosity, whatever
    an earlier test's command set)."""
    set_verbosity()
    records = []
    handler = logging.Handler()
    handler.emit = records.append
    logger = logging.getLogger("colmap_guided")
    logger.addHandler(handler)
    try:
        out = loc.localize(*args, **kwargs)
    finally:
        logger.removeHandler(handler)
    return out, [r.getMessage() for r in records]


@pytest.fixture(scope="module")
def second(first, workspace):
    """The same command again, with --add: nothing is localized again, a new model version is
    written."""
    return logged(workspace["ws"], workspace["photos"], add=True)


def test_a_rerun_redoes_nothing(first, second):
    out, messages = second
    assert any("3 of 3 photo(s) already localized" in m for m in messages), messages
    assert not any(m.startswith(("Extracting", "Matching")) for m in messages), messages
    # the same entries, times included: not computed again
    assert out["photos"] == first[0]["photos"][:3]


def test_add_writes_a_new_model_version_and_keeps_the_old_one(second, workspace, synthetic_scene):
    out, _ = second
    ws = workspace["ws"]
    assert Path(out["added_model"]) == ws / "sparse_localized" / "0"
    assert digests(ws / "sparse") == workspace["before"]["sparse"]
    old = pycolmap.Reconstruction(str(ws / "sparse" / "0"))
    new = pycolmap.Reconstruction(out["added_model"])
    names = {new.images[i].name for i in new.reg_image_ids()}
    added = {loc.db_name(p) for p in workspace["photos"][:2]}
    assert names == {old.images[i].name for i in old.reg_image_ids()} | added
    assert new.num_points3D() > old.num_points3D()  # points of the new photos triangulated
    for image in new.images.values():
        if image.name in added:
            assert image.num_points3D >= 30
    est = {
        Path(n).name + ("@scan" if "scans" in n else ""): pose
        for n, pose in model_poses(new).items()
    }
    ref = {name: synthetic_scene.cam_from_world[name.split("@")[0]] for name in est}
    errors = compare_poses(est, ref)
    assert all(e["rotation_error"] < 1.0 and e["center_error"] < 0.02 for e in errors.values()), (
        errors
    )


def _run(argv, capfd) -> tuple[int, list[str]]:
    set_verbosity()
    code = main([str(a) for a in argv])
    return code, OUR_ERROR.findall(capfd.readouterr().err)


def test_a_missing_or_foreign_workspace_is_one_line(workspace, tmp_path, capfd):
    photo = workspace["photos"][0]
    letters = tmp_path / "letters"
    letters.mkdir()
    (letters / "letter.txt").write_text("Dear archivist,\n")
    for folder, words in (
        (tmp_path / "nowhere", "No workspace at"),
        (letters, "not a workspace written by"),
    ):
        code, errors = _run(["localize", folder, photo], capfd)
        assert code == 2 and len(errors) == 1 and words in errors[0], errors
    assert sorted(p.name for p in letters.iterdir()) == ["letter.txt"]
    code, errors = _run(["localize", workspace["ws"], tmp_path / "lost.jpg"], capfd)
    assert code == 2 and len(errors) == 1 and "None of the 1 photo path(s)" in errors[0], errors


def test_reconstruct_overwrite_removes_what_localize_wrote_and_nothing_else(
    second, workspace, tmp_path
):
    from colmap_guided.workspace import Workspace

    copy = tmp_path / "ws"
    shutil.copytree(workspace["ws"], copy)
    # what `reconstruct --overwrite` does first
    Workspace.claim(copy, "reconstruct", overwrite=True)
    assert sorted(p.name for p in copy.iterdir()) == [".colmap_guided.json", "notes.txt"]


def test_the_command_retrieves_the_top_k_model_images(second, workspace, tmp_path, capfd):
    copy = tmp_path / "ws"
    shutil.copytree(workspace["ws"], copy)
    photo = tmp_path / "again" / HELD_OUT[0]
    photo.parent.mkdir()
    shutil.copy(workspace["photos"][0], photo)  # another path: not localized yet
    code, errors = _run(["localize", copy, photo.parent, "--num_images", "2"], capfd)
    assert code == 0 and not errors
    (entry,) = [
        e
        for e in json.loads((copy / "localized.json").read_text())["photos"]
        if e["photo"] == str(photo)
    ]
    assert entry["status"] == "placed" and 1 <= len(entry["matched_images"]) <= 2  # the top 2 only
    with np.load(
        copy / "localize_retrieval.npz"
    ) as saved:  # the model's descriptors, kept for the next run
        model = pycolmap.Reconstruction(str(copy / "sparse" / "0"))
        assert sorted(saved["names"].tolist()) == sorted(
            model.images[i].name for i in model.reg_image_ids()
        )


def test_a_run_killed_before_the_poses_continues_from_the_database(second, workspace, tmp_path):
    """localize.db holds the photos' keypoints and matches: without localized.json (a run killed
    after matching), the rerun extracts and matches nothing again and finds the same poses."""
    copy = tmp_path / "ws"
    shutil.copytree(workspace["ws"], copy)
    (copy / "localized.json").unlink()
    out, messages = logged(copy, workspace["photos"])
    assert not any(m.startswith("Extracting") for m in messages), messages
    assert any(m.startswith("Matching 0 file pairs") for m in messages), messages
    before = {e["photo"]: e for e in second[0]["photos"]}
    for entry in out["photos"]:
        assert entry["status"] == before[entry["photo"]]["status"]
        if "tvec" in entry:
            assert np.allclose(entry["tvec"], before[entry["photo"]]["tvec"])


def test_photos_are_placed_in_the_model_named_by_model(two_buildings, tmp_path, capfd):
    result, _, other = two_buildings
    ws = tmp_path / "ws"  # a workspace of its own: the shared one stays as reconstruct left it
    reconstruct(Path(result["image_path"]).parent, output=ws, matcher="raw")
    held_out = other.image_dir / other.names[6]  # the other building's view not in the folder
    into_largest = loc.localize(ws, [held_out])["photos"][0]
    assert into_largest["status"] == "not placed", into_largest
    entry = loc.localize(ws, [held_out], model=1)["photos"][0]
    assert entry["status"] == "placed" and entry["matched_images"][0]["image"].startswith("other_")
    saved = json.loads((ws / "localized.json").read_text(encoding="utf-8"))
    assert saved["model"] == str(ws / "sparse" / "1")
    # the page draws the camera in that model's view
    page = (ws / "report.html").read_text(encoding="utf-8")
    data = json.loads(re.search(r"id='model-data-1'>(.*?)</script>", page, re.S).group(1))
    assert held_out.name in {c["name"].rsplit("/", 1)[-1] for c in data["cameras"]}
    code, errors = _run(["localize", ws, held_out, "--model", "4"], capfd)
    assert (
        code == 2
        and len(errors) == 1
        and "holds models 0, 1 (0 the largest); pass one of them." in errors[0]
    ), errors
