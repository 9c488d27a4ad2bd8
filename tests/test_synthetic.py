"""The rendered scene: files, determinism, pixel-exact ground truth, and COLMAP reconstructing
it."""

import math

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_guided import synthetic
from colmap_guided.synthetic import (
    Polygon,
    load_scene,
    make_texture,
    render_image,
    render_scene,
    transfer_points,
)
from recon_scripts.evaluation.ground_truth import pose_errors


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return render_scene(tmp_path_factory.mktemp("scene"), num_images=8)


@pytest.fixture(scope="module")
def sfm(scene, tmp_path_factory):
    """pycolmap's default pipeline on the scene: database and the reconstructions found."""
    work = tmp_path_factory.mktemp("sfm")
    database = work / "database.db"
    pycolmap.extract_features(database, scene.image_dir, device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
    models = pycolmap.incremental_mapping(database, scene.image_dir, work / "sparse")
    return database, models


def test_files_and_ground_truth_model(scene):
    assert scene.names == [f"view_{i:03d}.jpg" for i in range(8)]
    for name in scene.names:
        image = cv2.imread(str(scene.image_dir / name))
        assert image.shape == (480, 640, 3)
        assert image.std() > 30  # a textured photo, not a flat field
        depth = scene.depth(name)
        assert depth.shape == (480, 640) and 0.3 < (depth > 0).mean() < 0.95  # sky has no depth
    gt = pycolmap.Reconstruction(scene.gt_dir)
    assert gt.num_reg_images() == 8 and gt.num_cameras() == 1
    camera = gt.cameras[1]
    assert camera.model == pycolmap.CameraModelId.PINHOLE
    np.testing.assert_allclose(camera.calibration_matrix(), scene.K)
    loaded = load_scene(scene.image_dir.parent)
    assert loaded.names == scene.names and (loaded.width, loaded.height) == (640, 480)
    np.testing.assert_allclose(loaded.K, scene.K)
    for name, (R, t) in scene.cam_from_world.items():
        np.testing.assert_allclose(loaded.cam_from_world[name][0], R, atol=1e-9)
        np.testing.assert_allclose(loaded.cam_from_world[name][1], t, atol=1e-9)


def test_same_seed_same_images_other_seed_differs(scene, tmp_path):
    again = render_scene(tmp_path / "again", num_images=2)
    for name in again.names:
        assert (again.image_dir / name).read_bytes() == (scene.image_dir / name).read_bytes()
    synthetic.main(
        [
            str(tmp_path / "other"),
            "--num_images",
            "2",
            "--seed",
            "1",
            "--width",
            "320",
            "--height",
            "240",
        ]
    )
    other = cv2.imread(str(tmp_path / "other" / "images" / "view_000.jpg")).astype(float)
    first = cv2.imread(str(scene.image_dir / "view_000.jpg"))
    assert np.abs(other - cv2.resize(first, (320, 240), interpolation=cv2.INTER_AREA)).mean() > 20
    assert pycolmap.Reconstruction(tmp_path / "other" / "ground_truth").num_reg_images() == 2


def test_texture_lands_where_the_camera_projects_it():
    """A white square on a black board is rendered centred on the projection of its 3D centre
    (COLMAP pixel convention, through supersampling and area downscaling), to a few hundredths of a
    pixel."""
    K = np.array([[300.0, 0, 64], [0, 300, 48], [0, 0, 1]])
    conf = {**synthetic.default_conf, "noise_sigma": 0.0}
    rng = np.random.default_rng(0)
    rows, cols = np.mgrid[0:96, 0:128] + 0.5
    for ox, oy in rng.uniform(-0.3, 0.3, (3, 2)):
        texture = np.zeros((600, 600, 3), np.float32)
        texture[290:310, 290:310] = 1  # 20 cm square centred at (3 m, 3 m) of the board
        verts = np.array([(0, 0), (6, 0), (6, 6), (0, 6)], float)
        origin, u, v = (
            np.array([ox - 3, oy - 3, 10.0]),
            np.array([1.0, 0, 0]),
            np.array([0, 1.0, 0]),
        )
        board = Polygon(origin, u, v, verts, make_texture(texture, 100.0))
        image, depth = render_image([board], K, np.eye(3), np.zeros(3), 128, 96, conf, rng)
        weight = image[:, :, 0] / 255.0
        centroid = np.array([(weight * cols).sum(), (weight * rows).sum()]) / weight.sum()
        expected = K[:2, :2] @ [ox / 10, oy / 10] + K[:2, 2]
        assert np.abs(centroid - expected).max() < 0.06
        assert weight.sum() == pytest.approx((0.2 * 30) ** 2, rel=0.01)
        np.testing.assert_allclose(depth, 10.0, rtol=1e-5)


def test_ground_truth_transfer_aligns_image_content(scene):
    """Pixels of view 0 moved into view 1 by depth and poses land on the same texture: the best
    sub-pixel shift of view 1 is zero, and the matched intensities agree closely."""
    gray = [
        cv2.imread(str(scene.image_dir / n), cv2.IMREAD_GRAYSCALE).astype(np.float32)
        for n in scene.names
    ]
    rows, cols = np.mgrid[0:480:3, 0:640:3]
    points = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], 1)
    moved, valid = transfer_points(scene, scene.names[0], scene.names[1], points)
    assert valid.mean() > 0.3
    source = gray[0][rows.ravel()[valid], cols.ravel()[valid]]

    def mean_abs_diff(dx: float, dy: float) -> float:
        xy = (moved[valid] + [dx, dy] - 0.5).astype(np.float32)
        target = cv2.remap(gray[1], xy[:, :1], xy[:, 1:], cv2.INTER_LINEAR)[:, 0]
        return float(np.abs(source - target).mean())

    shifts = [(dx, dy) for dx in (-0.5, 0, 0.5) for dy in (-0.5, 0, 0.5)]
    costs = [mean_abs_diff(*s) for s in shifts]
    assert shifts[int(np.argmin(costs))] == (0, 0)
    assert min(costs) < 5


def test_default_pipeline_registers_all_images_accurately(scene, sfm):
    database, models = sfm
    db = pycolmap.Database.open(database)
    keypoints = [db.num_keypoints_for_image(image.image_id) for image in db.read_all_images()]
    cameras = db.read_all_cameras()
    db.close()
    assert min(keypoints) > 800
    # The EXIF tags make COLMAP group the photos into one camera with a focal length prior.
    assert len(cameras) == 1 and cameras[0].has_prior_focal_length
    assert cameras[0].params[0] == pytest.approx(scene.K[0, 0], rel=0.01)
    best = max(models.values(), key=lambda rec: rec.num_reg_images())
    assert best.num_reg_images() == 8
    errors = pose_errors(best, scene)
    assert set(errors) == set(scene.names)
    assert max(rot for rot, _ in errors.values()) < 1.0
    assert max(center for _, center in errors.values()) < 0.02


def test_verified_sift_matches_follow_ground_truth(scene, sfm):
    database, _ = sfm
    db = pycolmap.Database.open(database)
    ids = {image.name: image.image_id for image in db.read_all_images()}
    a, b = scene.names[3], scene.names[4]
    matches = db.read_two_view_geometry(ids[a], ids[b]).inlier_matches
    kp_a, kp_b = db.read_keypoints(ids[a])[:, :2], db.read_keypoints(ids[b])[:, :2]
    db.close()
    assert len(matches) > 100
    moved, valid = transfer_points(scene, a, b, kp_a[matches[:, 0]])
    assert valid.mean() > 0.9
    error = np.linalg.norm(moved - kp_b[matches[:, 1]], axis=1)[valid]
    assert np.median(error) < 0.6 and np.mean(error < 3) > 0.95


def test_pose_errors_measure_a_perturbed_model(scene):
    gt = pycolmap.Reconstruction(scene.gt_dir)
    estimate = pycolmap.Reconstruction(gt)
    # A similarity of the whole model changes nothing; then turn one camera by 5 degrees.
    similarity = pycolmap.Sim3d(
        2.5, pycolmap.Rotation3d(np.array([0.1, -0.3, 0.2])), np.array([1.0, 2, 3])
    )
    estimate.transform(similarity)
    image = estimate.find_image_with_name(scene.names[2])
    pose = image.cam_from_world()
    turn = cv2.Rodrigues(np.array([0, math.radians(5), 0]))[0]  # about the camera centre
    turned = pycolmap.Rigid3d(
        pycolmap.Rotation3d(turn @ pose.rotation.matrix()), turn @ pose.translation
    )
    estimate.frame(image.frame_id).set_cam_from_world(image.camera_id, turned)
    errors = pose_errors(estimate, scene.gt_dir)
    assert errors[scene.names[2]][0] == pytest.approx(5.0, abs=1e-6)
    others = [err for name, err in errors.items() if name != scene.names[2]]
    assert max(max(err) for err in others) < 1e-6
    estimate.deregister_frame(image.frame_id)
    assert pose_errors(estimate, scene)[scene.names[2]] == (math.inf, math.inf)


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="num_images"):
        render_scene(tmp_path, num_images=1)
    with pytest.raises(FileNotFoundError, match="render_scene"):
        pose_errors(pycolmap.Reconstruction(), tmp_path / "missing")
