"""Resume after SIGKILL at any stage, database safety, quiet COLMAP log, progress bars in a
terminal.

A real `python -m colmap_guided reconstruct` subprocess is killed with SIGKILL in the middle of a
stage (watched through a read-only SQLite connection), started again, and must end with the same
database contents (compared by image name: image ids depend on COLMAP's thread timing) and
registrations as an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import pty
import re
import shutil
import signal
import sqlite3
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from colmap_guided import images
from colmap_guided.database import DatabaseError
from colmap_guided.reconstruct import reconstruct
from colmap_guided.synthetic import render_scene

REPO = Path(__file__).resolve().parent.parent
GLOG_LINE = re.compile(r"^[IWE]\d{8} ", re.M)
NUM_IMAGES = 6
NUM_PAIRS = NUM_IMAGES * (NUM_IMAGES - 1) // 2


def _digest(array) -> str:
    return hashlib.sha1(np.ascontiguousarray(array).tobytes()).hexdigest()


def snapshot(database_path: Path) -> dict:
    """Everything in the database, keyed by image names: image and camera ids are labels that COLMAP
    hands out in the order its threads finish (two uninterrupted runs differ in them), so cameras
    are compared by which images share them, their model, size and parameters, and their number."""
    out = {}
    with pycolmap.Database.open(str(database_path)) as db:
        by_name = {im.name: im for im in db.read_all_images()}
        sharing = {}
        for name, im in sorted(by_name.items()):
            camera = db.read_camera(im.camera_id)
            sharing.setdefault(im.camera_id, []).append(name)
            out[f"image {name}"] = (
                camera.has_prior_focal_length,
                camera.model.name,
                camera.width,
                camera.height,
                tuple(camera.params),
                _digest(db.read_keypoints(im.image_id)),
                _digest(db.read_descriptors(im.image_id).data),
            )
        out["cameras shared by"] = sorted(sharing.values())
        names = sorted(by_name)
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                ia, ib = by_name[a].image_id, by_name[b].image_id
                if db.exists_matches(ia, ib):
                    out[f"matches {a} {b}"] = _digest(db.read_matches(ia, ib))
                if db.exists_two_view_geometry(ia, ib):
                    g = db.read_two_view_geometry(ia, ib)
                    out[f"geometry {a} {b}"] = (
                        g.config,
                        _digest(np.asarray(g.inlier_matches, np.uint32)),
                    )
        out["counts"] = (
            db.num_cameras(),
            db.num_rigs(),
            db.num_frames(),
            db.num_images(),
            db.num_matched_image_pairs(),
            db.num_verified_image_pairs(),
        )
    return out


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """A small rendered landmark and its uninterrupted reconstruction."""
    root = tmp_path_factory.mktemp("reliability")
    scene = render_scene(root / "scene", num_images=NUM_IMAGES, width=400, height=300)
    # Every other photo without EXIF (like a scan): COLMAP gives those a camera each, the others
    # share one.
    for name in scene.names[1::2]:
        Image.open(scene.image_dir / name).save(scene.image_dir / name, quality=95)
    result = reconstruct(root / "scene", output=root / "uninterrupted", matcher="raw")
    assert result["num_registered"] == NUM_IMAGES
    with pycolmap.Database.open(str(root / "uninterrupted" / "database.db")) as db:
        assert db.num_cameras() == 1 + NUM_IMAGES // 2
    return {
        "scene": root / "scene",
        "snapshot": snapshot(root / "uninterrupted" / "database.db"),
        "registered": result["model"]["registered_images"],
    }


def _count(conn: sqlite3.Connection | None, table: str) -> int:
    if conn is None:
        return -1
    try:
        return conn.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]
    except sqlite3.Error:
        return -1


def run_and_kill(scene: Path, output: Path, stage: str, window: tuple[int, int]) -> dict:
    """Start the CLI and SIGKILL it once the stage's row count is inside ``window`` (mapping:
    sparse.partial exists).

    The watcher keeps ONE read-only connection, opened once the database is in WAL mode:
    reconnecting in a loop would race COLMAP's own opens (COLMAP sets no SQLite busy timeout).
    """
    table = {
        "extraction": "descriptors",
        "matching": "matches",
        "verification": "two_view_geometries",
    }.get(stage)
    db_path = output / "database.db"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "colmap_guided",
            "reconstruct",
            str(scene),
            "--output",
            str(output),
            "--matcher",
            "raw",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    conn, seen, deadline = None, None, time.time() + 300
    try:
        while proc.poll() is None and time.time() < deadline:
            if table is None:
                n = 1 if (output / "sparse.partial").is_dir() else 0
            else:
                if conn is None and Path(str(db_path) + "-wal").exists():
                    conn = sqlite3.connect(f"{db_path.as_uri()}?mode=ro", uri=True, timeout=5)
                n = _count(conn, table)
            if window[0] <= n <= window[1]:
                os.kill(proc.pid, signal.SIGKILL)
                seen = n
                break
            time.sleep(0.003)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        if conn is not None:
            conn.close()
    assert seen is not None, (
        f"the run was not caught inside the {stage} stage "
        f"(exit {proc.returncode}): {err.decode()[-2000:]}"
    )
    assert proc.returncode == -signal.SIGKILL
    return {
        "seen": seen,
        "stderr": err.decode("utf-8", "replace"),
        "files": sorted(p.name for p in output.iterdir()),
    }


@pytest.mark.parametrize(
    "stage, window",
    [
        ("matching", (1, NUM_PAIRS - 2)),
        pytest.param("extraction", (1, NUM_IMAGES - 2), marks=pytest.mark.slow),
        pytest.param("verification", (1, NUM_PAIRS - 2), marks=pytest.mark.slow),
        pytest.param("mapping", (1, 1), marks=pytest.mark.slow),
    ],
)
def test_resume_after_sigkill_gives_the_uninterrupted_result(reference, tmp_path, stage, window):
    scene, output = reference["scene"], tmp_path / "killed"
    photos = images.folder_digests(scene / "images")
    killed = run_and_kill(scene, output, stage, window)

    # What SQLite leaves after SIGKILL while a stage writes it: the write-ahead log and its index,
    # next to an intact database (mapping reads the database once, then holds no connection: a kill
    # then leaves the database alone).
    assert {"database.db", "database.db-wal", "database.db-shm"} <= set(killed["files"]) or (
        stage == "mapping" and "database.db" in killed["files"]
    )
    with contextlib.closing(
        sqlite3.connect(f"{(output / 'database.db').as_uri()}?mode=ro", uri=True)
    ) as conn:
        assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    with pycolmap.Database.open(
        str(output / "database.db")
    ) as db:  # pycolmap reopens it; committed rows are there
        if stage == "matching":
            assert killed["seen"] <= db.num_matched_image_pairs() < NUM_PAIRS
        if stage == "extraction":
            assert killed["seen"] <= db.num_images() < NUM_IMAGES
    assert not GLOG_LINE.search(killed["stderr"]), "COLMAP's own log must be quiet by default"

    result = reconstruct(scene, output=output, matcher="raw")  # the same command again

    assert snapshot(output / "database.db") == reference["snapshot"]
    assert result["model"]["registered_images"] == reference["registered"]
    assert not (output / "sparse.partial").exists()
    assert images.folder_digests(scene / "images") == photos


def test_rerun_of_a_finished_run_changes_nothing(reference, tmp_path):
    output = tmp_path / "done"
    shutil.copytree(reference["scene"].parent / "uninterrupted", output)
    result = reconstruct(reference["scene"], output=output, matcher="raw")
    assert result["database"]["num_pairs_matched_now"] == 0
    # no duplicate pairs, nothing rewritten
    assert snapshot(output / "database.db") == reference["snapshot"]


def test_database_of_other_photos_refused_and_overwrite_starts_fresh(reference, tmp_path):
    other = tmp_path / "other" / "images"
    other.mkdir(parents=True)
    for i, p in enumerate(sorted((reference["scene"] / "images").iterdir())):
        shutil.copy(p, other / f"scan_{i:02d}.jpg")
    output = tmp_path / "out"
    shutil.copytree(reference["scene"].parent / "uninterrupted", output)
    (output / "notes.txt").write_text("the user's, not the run's")
    with pytest.raises(
        DatabaseError, match="not in .*--image_path the database was made from, or --overwrite"
    ):
        reconstruct(tmp_path / "other", output=output, matcher="raw")
    assert snapshot(output / "database.db") == reference["snapshot"]  # refused: nothing written

    result = reconstruct(tmp_path / "other", output=output, matcher="raw", overwrite=True)
    assert (
        output / "notes.txt"
    ).read_text() == "the user's, not the run's"  # --overwrite removes only its own
    assert result["num_registered"] == NUM_IMAGES
    with pycolmap.Database.open(str(output / "database.db")) as db:
        assert sorted(im.name for im in db.read_all_images()) == [
            f"scan_{i:02d}.jpg" for i in range(NUM_IMAGES)
        ]


def test_progress_bars_in_a_terminal(reference, tmp_path):
    """Under a terminal, each stage shows a tqdm bar with counts (extract, retrieval descriptors
    for the pairs' order, match; pairs are verified as they are matched)."""
    master, slave = pty.openpty()
    # a 120-column terminal
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "colmap_guided",
            "reconstruct",
            str(reference["scene"]),
            "--output",
            str(tmp_path / "out"),
            "--matcher",
            "raw",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=slave,
    )
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 65536)
        except OSError:  # the pty closes when the process ends
            break
        if not data:
            break
        chunks.append(data)
    proc.wait(timeout=300)
    os.close(master)
    text = b"".join(chunks).decode("utf-8", "replace")
    assert proc.returncode == 0, text[-2000:]
    # tqdm lines: "desc:  40%|####      | 2/5 [00:01<00:02, 1.5img/s]": counts and elapsed<remaining
    # (ETA).
    for desc, total in (
        ("check images", NUM_IMAGES),
        ("extract", NUM_IMAGES),
        ("retrieval", NUM_IMAGES),
        ("match", NUM_PAIRS),
    ):
        assert re.search(rf"{desc}:\s+\d+%\|[^|]*\| \d+/{total} \[\d\d:\d\d<", text), (
            f"no {desc} bar in {text[-3000:]!r}"
        )
    assert not GLOG_LINE.search(text)


@pytest.mark.parametrize("camera_mode", ["auto", "single", "per_folder"])
def test_extraction_in_chunks_groups_cameras_as_one_colmap_call(reference, tmp_path, camera_mode):
    """The extraction runs a few images per pycolmap call (progress, resume); cameras must still be
    shared exactly as one `colmap feature_extractor` call shares them (EXIF camera, folder, or
    all)."""
    from colmap_guided.features import CAMERA_MODES, extract_features

    image_path = tmp_path / "images"
    for i, src in enumerate(sorted((reference["scene"] / "images").iterdir())):
        (image_path / f"roll {i % 2}").mkdir(parents=True, exist_ok=True)
        shutil.copy(src, image_path / f"roll {i % 2}" / src.name)
    ours, theirs = tmp_path / "ours.db", tmp_path / "theirs.db"
    # two images per call
    extract_features(ours, image_path, conf={"camera_mode": camera_mode, "num_threads": 1})
    pycolmap.extract_features(theirs, image_path, camera_mode=CAMERA_MODES[camera_mode])

    def sharing(path):
        with pycolmap.Database.open(str(path)) as db:
            groups = {}
            for im in db.read_all_images():
                groups.setdefault(im.camera_id, []).append(im.name)
            return sorted(sorted(g) for g in groups.values()), db.num_cameras(), db.num_rigs()

    assert sharing(ours) == sharing(theirs)
    expected = {"auto": 1 + NUM_IMAGES // 2, "single": 1, "per_folder": 2}[camera_mode]
    assert sharing(ours)[1] == expected


def test_extraction_numbers_images_in_name_order(reference, tmp_path):
    """Image ids follow the photos' names, whatever order COLMAP's extraction threads finish in: a
    rerun must give the same database, the same pairs and the same model. The first photo is made
    16× larger so that, left to COLMAP, it would be written after the others."""
    from PIL import Image

    from colmap_guided.features import extract_features

    image_path = tmp_path / "images"
    image_path.mkdir()
    names = sorted(p.name for p in (reference["scene"] / "images").iterdir())
    for i, name in enumerate(names):
        with Image.open(reference["scene"] / "images" / name) as im:
            (im.resize((im.width * 4, im.height * 4), Image.BICUBIC) if i == 0 else im).save(
                image_path / name
            )
    database = tmp_path / "colmap.db"
    extract_features(database, image_path, conf={"num_threads": 2})
    with pycolmap.Database.open(str(database)) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        assert all(db.num_keypoints_for_image(ids[name]) > 0 for name in names)
    assert [ids[name] for name in names] == list(range(1, len(names) + 1))
