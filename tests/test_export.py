"""hloc h5 export and import: hloc's layout and conventions, and an exact round trip of the
database."""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pycolmap
import pytest

from colmap_guided.__main__ import main
from colmap_guided.export import export_h5, import_h5, names_to_pair
from colmap_guided.features import extract_features
from colmap_guided.log import set_verbosity
from colmap_guided.mapping import run_mapping
from colmap_guided.match import match_database
from colmap_guided.synthetic import render_scene


@pytest.fixture(scope="module")
def matched(tmp_path_factory):
    """A database with SIFT, raw matches and two-view geometries; names with sub-folders and
    spaces."""
    root = tmp_path_factory.mktemp("export")
    scene = render_scene(root / "render", num_images=5, width=400, height=300)
    image_path = root / "images"
    names = [
        "north side/view 0.jpg",
        "north side/view 1.jpg",
        "south/view 2.jpg",
        "view 3.jpg",
        "view 4.jpg",
    ]
    for src, name in zip(scene.names, names):
        (image_path / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(scene.image_dir / src, image_path / name)
    database = root / "database.db"
    extract_features(database, image_path)
    match_database(database, image_path, matcher="raw")
    return {"database": database, "image_path": image_path, "names": sorted(names), "root": root}


def _by_name(db):
    return {im.name: im for im in db.read_all_images()}


def assert_same_database(path_a, path_b, geometry=True):
    with pycolmap.Database.open(str(path_a)) as a, pycolmap.Database.open(str(path_b)) as b:
        ia, ib = _by_name(a), _by_name(b)
        assert sorted(ia) == sorted(ib)
        groups_a, groups_b = {}, {}
        for name in ia:
            assert np.array_equal(
                a.read_keypoints(ia[name].image_id), b.read_keypoints(ib[name].image_id)
            ), name
            da, db_ = a.read_descriptors(ia[name].image_id), b.read_descriptors(ib[name].image_id)
            assert da.type == db_.type and np.array_equal(da.data, db_.data), name
            ca, cb = a.read_camera(ia[name].camera_id), b.read_camera(ib[name].camera_id)
            assert (ca.model, ca.width, ca.height, ca.has_prior_focal_length) == (
                cb.model,
                cb.width,
                cb.height,
                cb.has_prior_focal_length,
            )
            assert np.array_equal(ca.params, cb.params), name
            groups_a.setdefault(ia[name].camera_id, set()).add(name)
            groups_b.setdefault(ib[name].camera_id, set()).add(name)
        # same camera sharing
        assert sorted(map(sorted, groups_a.values())) == sorted(map(sorted, groups_b.values()))
        assert (a.num_rigs(), a.num_frames()) == (b.num_rigs(), b.num_frames())
        names = sorted(ia)
        for i, x in enumerate(names):
            for y in names[i + 1 :]:
                pa, pb = (ia[x].image_id, ia[y].image_id), (ib[x].image_id, ib[y].image_id)
                assert a.exists_matches(*pa) == b.exists_matches(*pb)
                if a.exists_matches(*pa):
                    assert np.array_equal(a.read_matches(*pa), b.read_matches(*pb)), (x, y)
                if geometry and a.exists_two_view_geometry(*pa):
                    ga, gb = a.read_two_view_geometry(*pa), b.read_two_view_geometry(*pb)
                    assert ga.config == gb.config, (x, y)
                    assert np.array_equal(
                        np.asarray(ga.inlier_matches), np.asarray(gb.inlier_matches)
                    ), (x, y)
                    for key in "FEH":
                        va, vb = getattr(ga, key), getattr(gb, key)
                        assert (va is None) == (vb is None) and (
                            va is None or np.allclose(va, vb, rtol=1e-9, atol=1e-12)
                        ), (x, y, key)
        assert (a.num_matches(), a.num_inlier_matches()) == (
            b.num_matches(),
            b.num_inlier_matches(),
        )


def test_export_has_hlocs_layout(matched, tmp_path):
    out = export_h5(matched["database"], tmp_path / "h5")
    assert out["num_images"] == 5 and out["num_pairs"] == 10
    with (
        pycolmap.Database.open(str(matched["database"])) as db,
        h5py.File(tmp_path / "h5" / "features.h5") as fd,
        h5py.File(tmp_path / "h5" / "matches.h5") as fm,
    ):
        images = _by_name(db)
        # '/' in a name: nested groups, as hloc's
        assert "north side" in fd and "view 0.jpg" in fd["north side"]
        for name, im in images.items():
            grp = fd[name]
            kp = np.asarray(db.read_keypoints(im.image_id))
            assert grp["keypoints"].shape == (len(kp), 2)
            # hloc: pixel centre at integers
            assert np.array_equal(grp["keypoints"][()], kp[:, :2] - 0.5)
            assert (
                grp["descriptors"].shape == (128, len(kp)) and grp["descriptors"].dtype == np.uint8
            )
            assert np.array_equal(grp["descriptors"][()].T, db.read_descriptors(im.image_id).data)
            assert grp["scores"].shape == (len(kp),)
            camera = db.read_camera(im.camera_id)
            assert list(grp["image_size"][()]) == [camera.width, camera.height]
        a, b = "north side/view 0.jpg", "south/view 2.jpg"
        assert names_to_pair(a, b) == "north side-view 0.jpg/south-view 2.jpg"
        grp = fm[names_to_pair(a, b)]
        matches0 = grp["matches0"][()]
        assert matches0.dtype == np.int32 and matches0.shape == (
            len(db.read_keypoints(images[a].image_id)),
        )
        idx = np.flatnonzero(matches0 >= 0)
        assert np.array_equal(
            np.stack([idx, matches0[idx]], 1),
            np.asarray(db.read_matches(images[a].image_id, images[b].image_id)),
        )
        assert np.array_equal(grp["matching_scores0"][()] > 0, matches0 >= 0)
    lines = (tmp_path / "h5" / "pairs.txt").read_text(encoding="utf-8").splitlines()
    assert len(lines) == 10 and "north side/view 0.jpg\tsouth/view 2.jpg" in lines


def test_round_trip_gives_the_same_database_and_it_maps(matched, tmp_path):
    export_h5(matched["database"], tmp_path / "h5")
    stats = import_h5(
        tmp_path / "new.db", tmp_path / "h5" / "features.h5", tmp_path / "h5" / "matches.h5"
    )
    assert (
        stats["num_images_added"] == 5
        and stats["num_pairs_added"] == 10
        and stats["num_pairs_verified"] == 0
    )
    assert_same_database(matched["database"], tmp_path / "new.db")
    models = run_mapping(
        tmp_path / "new.db", matched["image_path"], tmp_path / "sparse", {"mapper": "incremental"}
    )
    assert max(m.num_reg_images() for m in models.values()) == 5
    # Importing again adds nothing and changes nothing.
    again = import_h5(
        tmp_path / "new.db", tmp_path / "h5" / "features.h5", tmp_path / "h5" / "matches.h5"
    )
    assert again["num_images_added"] == 0 and again["num_pairs_added"] == 0
    assert_same_database(matched["database"], tmp_path / "new.db")


def test_import_of_plain_hloc_files_default_cameras_then_verification(matched, tmp_path):
    """Files with only hloc's datasets (no colmap_ extras): COLMAP default cameras, then
    verification."""
    export_h5(matched["database"], tmp_path / "ours")
    plain = tmp_path / "plain"
    plain.mkdir()
    with (
        h5py.File(tmp_path / "ours" / "features.h5") as src,
        h5py.File(plain / "features.h5", "w") as dst,
    ):
        for name in matched["names"]:
            for key in ("keypoints", "descriptors", "scores", "image_size"):
                dst.create_dataset(f"{name}/{key}", data=src[name][key][()])
    with (
        h5py.File(tmp_path / "ours" / "matches.h5") as src,
        h5py.File(plain / "matches.h5", "w") as dst,
    ):

        def copy(name, obj):
            if isinstance(obj, h5py.Dataset) and obj.name.split("/")[-1] in (
                "matches0",
                "matching_scores0",
            ):
                dst.create_dataset(obj.name, data=obj[()])

        src.visititems(copy)
    stats = import_h5(tmp_path / "plain.db", plain / "features.h5", plain / "matches.h5")
    assert stats["num_pairs_verified"] == 10
    with (
        pycolmap.Database.open(str(matched["database"])) as a,
        pycolmap.Database.open(str(tmp_path / "plain.db")) as b,
    ):
        ia, ib = _by_name(a), _by_name(b)
        assert sorted(ia) == sorted(ib) and b.num_frames() == b.num_images() == 5
        for (
            name
        ) in ia:  # hloc keeps x, y only (no affine shape): +0.5 gives COLMAP's x, y back exactly
            assert np.array_equal(
                a.read_keypoints(ia[name].image_id)[:, :2], b.read_keypoints(ib[name].image_id)
            ), name
            assert np.array_equal(
                a.read_descriptors(ia[name].image_id).data,
                b.read_descriptors(ib[name].image_id).data,
            )
            # COLMAP's default camera: no EXIF in hloc's files
            camera = b.read_camera(ib[name].camera_id)
            assert camera.model.name == "SIMPLE_RADIAL" and camera.params[0] == pytest.approx(
                1.2 * 400
            )
        names = sorted(ia)
        for i, x in enumerate(names):
            for y in names[i + 1 :]:
                pa, pb = (ia[x].image_id, ia[y].image_id), (ib[x].image_id, ib[y].image_id)
                assert np.array_equal(a.read_matches(*pa), b.read_matches(*pb)), (x, y)
        assert stats["num_verified_pairs"] == a.num_verified_image_pairs() - sum(
            n == 0 for n in a.read_two_view_geometry_num_inliers()[1]
        )


def test_cli_export_import(matched, tmp_path, capfd):
    try:
        assert (
            main(
                [
                    "export",
                    "--database_path",
                    str(matched["database"]),
                    "--output",
                    str(tmp_path / "h5"),
                ]
            )
            == 0
        )
        assert (
            main(
                [
                    "export",
                    "--database_path",
                    str(matched["database"]),
                    "--output",
                    str(tmp_path / "h5"),
                ]
            )
            == 2
        )
        assert "pass --overwrite" in capfd.readouterr().err
        assert (
            main(
                [
                    "import",
                    "--database_path",
                    str(tmp_path / "cli.db"),
                    "--features",
                    str(tmp_path / "h5" / "features.h5"),
                    "--matches",
                    str(tmp_path / "h5" / "matches.h5"),
                ]
            )
            == 0
        )
        assert (
            main(
                [
                    "import",
                    "--database_path",
                    str(tmp_path / "x.db"),
                    "--features",
                    str(tmp_path / "missing.h5"),
                ]
            )
            == 2
        )
        assert "No features file" in capfd.readouterr().err
    finally:
        set_verbosity(False, False)
    assert_same_database(matched["database"], tmp_path / "cli.db")
