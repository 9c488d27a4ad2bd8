"""A user's files are never lost: every writing command, pointed at the wrong place, refuses in one
line and leaves every file byte-identical; --overwrite removes only what the project wrote."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from colmap_guided import archival
from colmap_guided.__main__ import main
from colmap_guided.log import set_verbosity
from colmap_guided.synthetic import render_scene
from colmap_guided.train.trainer import Trainer
from colmap_guided.workspace import MARKER, OutputRefused, read_marker
from recon_scripts.evaluation import proxy

OUR_ERROR = re.compile(r"^\[[\d:]+ colmap_guided ERROR\] (.+)$", re.M)
PLACES = ("scene folder", "its parent", "image folder", "folder of the user's files", "a file")


def _snapshot(root: Path) -> dict[str, str]:
    """Every file and folder under ``root``: its bytes' digest (folders: 'dir')."""
    out = {}
    for path in sorted(root.rglob("*")):
        key = path.relative_to(root).as_posix()
        out[key] = "dir" if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest()
    return out


@pytest.fixture
def user_tree(tmp_path):
    """tmp/data/scene/images (3 photos), the user's notes beside them and in the parent, a folder of
    letters (with a report.json of the user's own) and a lone file; returns
    (root, scene, places)."""
    scene = tmp_path / "data" / "scene"
    (scene / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(3):
        small = rng.integers(0, 256, (15, 20, 3), dtype=np.uint8)
        cv2.imwrite(
            str(scene / "images" / f"p{i}.jpg"),
            cv2.resize(small, (160, 120), interpolation=cv2.INTER_CUBIC),
        )
    (scene / "notes.txt").write_text("where each photo was bought\n")
    (tmp_path / "data" / "inventory.csv").write_text("p0,1912\n")
    letters = tmp_path / "letters"
    letters.mkdir()
    (letters / "letter.txt").write_text("Dear archivist,\n")
    (letters / "report.json").write_text('{"mine": true}\n')
    (letters / "database.db").write_bytes(b"my own notes, not a database")
    lone = tmp_path / "file.txt"
    lone.write_text("a file\n")
    places = dict(zip(PLACES, (scene, scene.parent, scene / "images", letters, lone)))
    return tmp_path, scene, places


def _cli(argv, capfd) -> tuple[int, str]:
    try:
        code = main([str(a) for a in argv])
    finally:
        set_verbosity(False, False)
    return code, capfd.readouterr()[1]


def _one_line(err: str) -> str:
    assert "Traceback" not in err, err
    lines = OUR_ERROR.findall(err)
    assert len(lines) == 1, err
    return lines[0]


@pytest.mark.parametrize("overwrite", [False, True])
@pytest.mark.parametrize("place", PLACES)
def test_reconstruct_refuses_every_place_of_the_users_files(user_tree, capfd, place, overwrite):
    root, scene, places = user_tree
    before = _snapshot(root)
    argv = [
        "reconstruct",
        scene,
        "--output",
        places[place],
        "--features",
        "sift",
        "--matcher",
        "raw",
    ]
    code, err = _cli(argv + (["--overwrite"] if overwrite else []), capfd)
    line = _one_line(err)
    assert code == 2 and "--output" in line and "pass" in line, line
    assert _snapshot(root) == before


@pytest.mark.parametrize("overwrite", [False, True])
@pytest.mark.parametrize("place", PLACES)
def test_archival_copies_never_land_on_the_users_files(user_tree, capfd, place, overwrite):
    root, scene, places = user_tree
    before = _snapshot(root)
    photos = sorted((scene / "images").glob("*.jpg"))
    try:
        code = archival.main(
            [
                *map(str, photos),
                "--out",
                str(places[place]),
                *(["--overwrite"] if overwrite else []),
            ]
        )
    finally:
        set_verbosity(False, False)
    assert code == 2 and "--out" in _one_line(capfd.readouterr()[1])
    assert _snapshot(root) == before


@pytest.mark.parametrize("place", PLACES)
def test_proxy_train_and_synthetic_outputs_refuse_the_users_files(user_tree, place):
    root, scene, places = user_tree
    before = _snapshot(root)
    with pytest.raises(OutputRefused):
        proxy.build_proxy(places[place], sources=["scene"], data_dir=scene.parent, n_distractors=0)
    with pytest.raises(OutputRefused, match="--out"):
        Trainer(places[place], {})
    with pytest.raises(OutputRefused):
        render_scene(places[place], num_images=2)
    assert _snapshot(root) == before


def test_export_and_report_refuse_the_users_files_and_overwrite_only_their_own(
    user_tree, synthetic_scene, capfd
):
    root, scene, places = user_tree
    work = root / "work"
    argv = ["reconstruct", synthetic_scene.image_dir, "--output", work, "--features", "sift"]
    argv += ["--matcher", "raw", "--threads", "1"]
    code, err = _cli(argv, capfd)
    assert code == 0, err
    database = work / "database.db"
    before = _snapshot(root)
    for place, target in places.items():
        for extra in ([], ["--overwrite"]):
            code, err = _cli(
                ["export", "--database_path", database, "--output", target, *extra], capfd
            )
            assert code == 2 and "--output" in _one_line(err), (place, err)
            code, err = _cli(["report", target], capfd)
            assert code == 2, (place, err)
            _one_line(err)
    assert _snapshot(root) == before

    # --overwrite in the project's own folders: the user's file put there stays, the run's files are
    # new.
    exported = root / "exported"
    assert _cli(["export", "--database_path", database, "--output", exported], capfd)[0] == 0
    (exported / "my_pairs.txt").write_text("mine\n")
    (work / "notes.txt").write_text("kept\n")
    code, err = _cli(["export", "--database_path", database, "--output", exported], capfd)
    assert code == 2 and "--overwrite" in _one_line(err)
    assert (
        _cli(["export", "--database_path", database, "--output", exported, "--overwrite"], capfd)[0]
        == 0
    )
    assert (exported / "my_pairs.txt").read_text() == "mine\n" and (
        exported / "matches.h5"
    ).is_file()
    old_db = database.stat().st_mtime_ns
    code, err = _cli([*argv, "--overwrite"], capfd)
    assert code == 0, err
    assert (work / "notes.txt").read_text() == "kept\n"
    assert (
        database.stat().st_mtime_ns != old_db
        and json.loads((work / "report.json").read_text())["num_registered"] >= 6
    )
    assert set(read_marker(work)["entries"]) >= {
        "database.db",
        "sparse",
        "report.json",
        "report.html",
    }
    assert _cli(["report", work], capfd)[0] == 0
    for image in synthetic_scene.names:
        assert (synthetic_scene.image_dir / image).is_file()


def test_an_unwritable_output_is_one_line(user_tree, capfd):
    root, scene, places = user_tree
    before = _snapshot(root)
    for target in (places["a file"] / "workspace", Path("/proc/colmap_guided_workspace")):
        code, err = _cli(
            ["reconstruct", scene, "--output", target, "--features", "sift", "--matcher", "raw"],
            capfd,
        )
        assert code == 2 and "writable" in _one_line(err), err
    assert _snapshot(root) == before


def test_coarse_drawing_never_replaces_a_file(user_tree, capfd):
    root, scene, places = user_tree
    before = _snapshot(root)
    photos = sorted((scene / "images").glob("*.jpg"))
    code, err = _cli(["coarse", photos[0], photos[1], "--out", places["a file"]], capfd)
    assert code == 2 and "exists" in _one_line(err)
    assert _snapshot(root) == before


def test_a_marker_of_another_command_is_not_taken(tmp_path):
    render_scene(tmp_path / "synthetic", num_images=2, width=64, height=48)
    assert (
        read_marker(tmp_path / "synthetic")["kind"] == "synthetic"
        and (tmp_path / "synthetic" / MARKER).is_file()
    )
    with pytest.raises(OutputRefused, match="synthetic"):
        Trainer(tmp_path / "synthetic", {})
