"""Mapping (incremental / global / hierarchical, seeded, thin view graphs) and the model check."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pycolmap
import pytest

from colmap_guided.mapping import MAPPERS, check_conf, run_mapping, write_models
from colmap_guided.model_check import check_models
from recon_scripts.evaluation.ground_truth import pose_errors

NUM_FRAMES = 12


@pytest.fixture(scope="module")
def thin_chain(tmp_path_factory) -> str:
    """A chain of 12 photos in which each point is seen by 3 consecutive photos only: neighbours
    share 50 verified inliers, second neighbours 25 (a thin but correct view graph, like a ring of
    archival views)."""
    path = tmp_path_factory.mktemp("thin") / "database.db"
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs, options.num_cameras_per_rig, options.num_frames_per_rig = 1, 1, NUM_FRAMES
    options.num_points3D = 25 * NUM_FRAMES
    options.match_config = pycolmap.SyntheticDatasetMatchConfig.CHAINED
    pycolmap.set_random_seed(0)
    with pycolmap.Database.open(str(path)) as db:
        gt = pycolmap.synthesize_dataset(options, db)
        ids = sorted(gt.reg_image_ids(), key=lambda i: gt.images[i].name)
        # first photo that sees it
        window = {pid: k % NUM_FRAMES for k, pid in enumerate(sorted(gt.points3D))}
        for i in range(NUM_FRAMES - 1):
            a, b = ids[i], ids[i + 1]
            in_b = {p.point3D_id: k for k, p in enumerate(gt.images[b].points2D) if p.has_point3D()}
            keep = [
                (k, in_b[p.point3D_id])
                for k, p in enumerate(gt.images[a].points2D)
                if p.has_point3D()
                and p.point3D_id in in_b
                and window[p.point3D_id] <= i <= window[p.point3D_id] + 1
            ]
            geometry = db.read_two_view_geometry(a, b)
            geometry.inlier_matches = np.array(keep, np.uint32)
            db.delete_matches(a, b)
            db.delete_two_view_geometry(a, b)
            db.write_matches(a, b, geometry.inlier_matches)
            db.write_two_view_geometry(a, b, geometry)
        inliers = [
            len(db.read_two_view_geometry(ids[i], ids[i + 1]).inlier_matches)
            for i in range(1, NUM_FRAMES - 1)
        ]
    assert set(inliers) == {50}
    return str(path)


def test_colmap_thresholds_break_the_thin_chain(thin_chain, tmp_path):
    """The test can fail: COLMAP's registration threshold (30 2D-3D inliers) stops at the initial
    pair."""
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size, options.num_threads, options.random_seed = 2, 1, 0
    models = pycolmap.incremental_mapping(thin_chain, str(tmp_path), str(tmp_path), options)
    assert max((m.num_reg_images() for m in models.values()), default=0) < NUM_FRAMES


@pytest.mark.parametrize("mapper", MAPPERS)
def test_every_mapper_registers_the_thin_chain(thin_chain, tmp_path, mapper):
    models = run_mapping(
        thin_chain, tmp_path, tmp_path / "sparse", {"mapper": mapper, "num_threads": 1}
    )
    assert models[0].num_reg_images() == NUM_FRAMES
    assert sorted(p.name for p in (tmp_path).iterdir()) == ["sparse"]  # no .partial left
    assert pycolmap.Reconstruction(str(tmp_path / "sparse" / "0")).num_reg_images() == NUM_FRAMES


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_seeded_single_thread_mapping_repeats_exactly(thin_chain, tmp_path, mapper):
    poses = []
    for run in range(2):
        models = run_mapping(
            thin_chain,
            tmp_path,
            tmp_path / f"sparse{run}",
            {"mapper": mapper, "num_threads": 1, "random_seed": 7},
        )
        rec = models[0]
        poses.append(
            {
                rec.images[i].name: rec.images[i].cam_from_world().matrix()
                for i in rec.reg_image_ids()
            }
        )
    assert poses[0].keys() == poses[1].keys()
    for name in poses[0]:
        np.testing.assert_array_equal(poses[0][name], poses[1][name])


def test_extending_the_largest_model_keeps_a_model_that_mapping_again_would_shrink(
    thin_chain, tmp_path
):
    """Escalation continues model 0 and maps the other photos again: where that places fewer of
    another model's photos than the mapper that made it, the model stays (each photo in one
    model); where the continued model takes a model's photos, that model goes."""
    conf = {"mapper": "incremental", "num_threads": 1}
    whole = run_mapping(thin_chain, tmp_path, tmp_path / "all", conf)[0]
    names = sorted(whole.images[i].name for i in whole.reg_image_ids())
    halves = [
        run_mapping(thin_chain, tmp_path, tmp_path / f"half{k}", {**conf, "image_names": part})[0]
        for k, part in enumerate((names[:6], names[6:]))
    ]
    assert [rec.num_reg_images() for rec in halves] == [6, 6]
    sparse = tmp_path / "sparse"
    write_models(sparse, halves)
    # the continued model reaches 2 photos of the other half; mapping again places none of the rest
    models = run_mapping(thin_chain, tmp_path, sparse, {**conf, "image_names": names[:8]}, True)
    placed = [sorted(rec.images[i].name for i in rec.reg_image_ids()) for rec in models.values()]
    assert placed == [names[:8], names[8:]]
    assert [sorted(p.name for p in sparse.iterdir())] == [["0", "1"]]
    # mapping every photo: the continued model takes them all
    models = run_mapping(thin_chain, tmp_path, sparse, conf, True)
    assert [rec.num_reg_images() for rec in models.values()] == [NUM_FRAMES]


def test_mapping_conf_is_strict():
    with pytest.raises(
        ValueError, match="Unknown mapping option 'min_modelsize'; did you mean 'min_model_size'?"
    ) as err:
        check_conf({"min_modelsize": 3})
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="Unknown mapper 'glomap'"):
        check_conf({"mapper": "glomap"})


def test_cli_global_mapping(synthetic_scene, tmp_path):
    """`reconstruct --mapper global --seed 3 --threads 1`: true poses, the options in report.json.
    Global mapping leaves out view_007, whose only strong pair is planar (149 inliers to view_006;
    17 to view_005), where incremental mapping registers all 8."""
    out = tmp_path / "out"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "colmap_guided",
            "reconstruct",
            str(synthetic_scene.image_dir.parent),
            "--output",
            str(out),
            "--matcher",
            "raw",
            "--mapper",
            "global",
            "--seed",
            "3",
            "--threads",
            "1",
            "--quiet",
        ],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    result = json.loads((out / "report.json").read_text())
    assert result["num_registered"] >= len(synthetic_scene.names) - 1
    errors = pose_errors(pycolmap.Reconstruction(str(out / "sparse" / "0")), synthetic_scene)
    registered = [e for e in errors.values() if np.isfinite(e[0])]
    assert len(registered) == result["num_registered"] and max(e[0] for e in registered) < 1.0, (
        errors
    )
    assert {
        k: result["options"]["mapping"][k] for k in ("mapper", "random_seed", "num_threads")
    } == {"mapper": "global", "random_seed": 3, "num_threads": 1}
    assert result["model_check"]["ok"], result["model_check"]
    bad = subprocess.run(
        [sys.executable, "-m", "colmap_guided", "reconstruct", str(tmp_path), "--mapper", "glomap"],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "invalid choice: 'glomap'" in bad.stderr


@pytest.fixture()
def lund_door(shared_data) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(str(shared_data / "lund_door_gtsfm" / "colmap_ground_truth"))


def test_model_check_passes_a_real_model_and_flags_a_corrupted_focal(lund_door):
    assert check_models({0: lund_door}) == {
        "ok": True,
        "problems": [],
        "conf": check_models({})["conf"],
    }
    # the model's own camera object: edited in place
    camera = next(iter(lund_door.cameras.values()))
    # 2.4 million px: an orthographic camera
    camera.params = [camera.params[0] * 1000, *camera.params[1:]]
    checked = check_models({0: lund_door})
    assert not checked["ok"]
    focal = [p for p in checked["problems"] if "focal length" in p]
    assert (
        len(focal) == 1
        and focal[0].startswith("sparse/0: focal length 2435380 px")
        and "DSC_0001.JPG" in focal[0]
    )


def test_model_check_flags_a_pose_jump(lund_door):
    image = next(im for im in lund_door.images.values() if im.name == "DSC_0005.JPG")
    frame = lund_door.frames[image.frame_id]
    # 90° about x
    turn = pycolmap.Rigid3d(
        pycolmap.Rotation3d(np.array([np.sin(np.pi / 4), 0, 0, np.cos(np.pi / 4)])), np.zeros(3)
    )
    frame.rig_from_world = turn * frame.rig_from_world
    problems = check_models({0: lund_door})["problems"]
    assert any("pose jump" in p and "DSC_0005.JPG" in p for p in problems), problems


def _keep_observations(rec: pycolmap.Reconstruction, image: pycolmap.Image, keep: set[int]) -> None:
    for idx, point in enumerate(image.points2D):
        if point.has_point3D() and point.point3D_id not in keep:
            rec.delete_observation(image.image_id, idx)


def test_photos_on_too_few_3d_points_are_taken_out_until_none_is_left(lund_door):
    """A photo observing 10 3D points goes; one observing 16, 3 of them seen only with the first, is
    left with 13 and goes too; every other photo stays, each on >= 15 points."""
    from colmap_guided.mapping import prune_weak_images

    a, b = (
        next(im for im in lund_door.images.values() if im.name == n)
        for n in ("DSC_0005.JPG", "DSC_0006.JPG")
    )
    shared = sorted(
        {p.point3D_id for p in a.points2D if p.has_point3D()}
        & {p.point3D_id for p in b.points2D if p.has_point3D()}
    )
    only_b = sorted({p.point3D_id for p in b.points2D if p.has_point3D()} - set(shared))
    for pid in shared[:3]:  # three points seen by a and b only
        # copied: the track changes
        for image_id, idx in [
            (el.image_id, el.point2D_idx) for el in lund_door.points3D[pid].track.elements
        ]:
            if image_id not in (a.image_id, b.image_id):
                lund_door.delete_observation(image_id, idx)
    _keep_observations(lund_door, a, set(shared[:10]))
    _keep_observations(lund_door, b, set(shared[:3]) | set(only_b[:13]))
    before = lund_door.num_reg_images()
    assert (
        lund_door.images[a.image_id].num_points3D,
        lund_door.images[b.image_id].num_points3D,
    ) == (10, 16)
    assert prune_weak_images(lund_door, 15) == {"DSC_0005.JPG": 10, "DSC_0006.JPG": 13}
    assert lund_door.num_reg_images() == before - 2 and not lund_door.images[a.image_id].has_pose
    assert min(lund_door.images[i].num_points3D for i in lund_door.reg_image_ids()) >= 15
    assert prune_weak_images(lund_door, 15) == {}


def test_pose_support_counts_the_inliers_a_model_explains_and_drops_for_a_wrong_pose(
    thin_chain, tmp_path
):
    """``auto``'s tie-break: a right model explains every verified inlier between its photos;
    turning one photo by 20° leaves its pairs' inliers unexplained (the other pairs keep theirs)."""
    from colmap_guided import database as dbio
    from colmap_guided.mapping import auto_key, pose_support

    rec = run_mapping(
        thin_chain, tmp_path, tmp_path / "sparse", {"mapper": "incremental", "num_threads": 1}
    )[0]
    with dbio.open_database(thin_chain) as db:
        inliers = dbio.read_verified_inliers(db, set(rec.reg_image_ids()))
    total = sum(len(m) for m in inliers.values())
    assert pose_support(rec, thin_chain) >= 0.99 * total > 0
    assert auto_key(rec, thin_chain)[1:] == (
        NUM_FRAMES,
        pose_support(rec, thin_chain),
    ) and auto_key(None, thin_chain) == (False, 0, 0)
    # pose support left out
    assert auto_key(rec, None)[1:] == (NUM_FRAMES,) and auto_key(None, None) == (False, 0)
    image = next(
        im
        for im in rec.images.values()
        if im.name == sorted(im.name for im in rec.images.values())[5]
    )
    own = sum(len(m) for pair, m in inliers.items() if image.image_id in pair)
    frame = rec.frames[image.frame_id]
    # 20° about y
    turn = pycolmap.Rigid3d(
        pycolmap.Rotation3d(np.array([0, np.sin(np.pi / 18), 0, np.cos(np.pi / 18)])), np.zeros(3)
    )
    frame.rig_from_world = turn * frame.rig_from_world
    assert own >= 100 and pose_support(rec, thin_chain) <= total - 0.95 * own


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_a_refined_principal_point_moves_back_towards_the_truth(thin_chain, tmp_path, mapper):
    """The camera's principal point is put 30 px off the one the photos were made with: mapping
    keeps it there unless ``refine_principal_point`` lets bundle adjustment move it back."""
    db_path = tmp_path / "database.db"
    shutil.copy(thin_chain, db_path)
    with pycolmap.Database.open(str(db_path)) as db:
        camera = db.read_all_cameras()[0]
        truth = camera.principal_point_x
        camera.principal_point_x = truth + 30
        db.update_camera(camera)
    errors = {}
    for refine in (False, True):
        conf = {"mapper": mapper, "num_threads": 1, "refine_principal_point": refine}
        models = run_mapping(db_path, tmp_path, tmp_path / f"sparse{refine}", conf)
        assert models[0].num_reg_images() == NUM_FRAMES
        errors[refine] = abs(models[0].cameras[camera.camera_id].principal_point_x - truth)
    assert errors[False] == pytest.approx(30) and errors[True] < 15, errors
