"""Metrics of the evaluation suite on hand-made inputs (no data needed)."""

import numpy as np
import pycolmap
import pytest

from colmap_guided import geometry
from recon_scripts.evaluation import matcher_specs, metrics
from recon_scripts.evaluation.registration import compare_poses


def random_rotation(rng, max_deg=180.0):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(0, max_deg))
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def rot_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def test_pose_auc_matches_hand_computation():
    # errors 1 and 3 deg, threshold 5: recall curve (0,0)-(1,.5)-(3,1)-(5,1)
    # area = 0.5*1*0.5 + (0.5+1)/2*2 + 1*2 = 3.75 -> 3.75 / 5 = 0.75
    assert metrics.pose_auc([3.0, 1.0], [5.0])[0] == pytest.approx(0.75)
    # threshold 2: (0,0)-(1,.5)-(2,.5): 0.25 + 0.5 = 0.75 -> / 2 = 0.375
    assert metrics.pose_auc([1.0, 3.0], [2.0])[0] == pytest.approx(0.375)
    # a failure (inf) halves the recall: (0,0)-(1,.5)-(5,.5) -> 0.25 + 2 = 2.25 / 5
    assert metrics.pose_auc([1.0, np.inf], [5.0])[0] == pytest.approx(0.45)
    assert metrics.pose_auc([np.nan, np.inf], [5.0])[0] == 0.0
    assert metrics.pose_auc([], [5.0]) == [0.0]
    # an error exactly at the threshold contributes nothing below it
    assert metrics.pose_auc([5.0], [5.0])[0] == pytest.approx(0.0)
    assert metrics.pose_accuracy([1.0, 3.0, 30.0], [5.0, 10.0, 20.0]) == pytest.approx(
        [2 / 3, 2 / 3, 2 / 3]
    )


def test_ground_truth_poses_give_auc_100_and_shuffled_poses_about_0():
    rng = np.random.default_rng(0)
    poses = [(random_rotation(rng), rng.normal(size=3)) for _ in range(50)]
    exact = [metrics.relative_pose_error(R, t, R, t)["pose"] for R, t in poses]
    assert metrics.pose_auc(exact) == pytest.approx([1.0, 1.0, 1.0])
    shuffled = [
        metrics.relative_pose_error(*poses[(i + 1) % 50], *poses[i])["pose"] for i in range(50)
    ]
    assert max(metrics.pose_auc(shuffled)) < 0.05
    # the same pose with t scaled (E has no scale) or negated (sign ambiguity) is exact
    R, t = poses[0]
    assert metrics.relative_pose_error(R, -3 * t, R, t)["pose"] == pytest.approx(0.0, abs=1e-5)
    assert metrics.relative_pose_error(R, -3 * t, R, t)["t"] == pytest.approx(0.0, abs=1e-5)
    assert metrics.relative_pose_error(None, None, R, t)["pose"] == np.inf


def test_rotation_and_translation_errors():
    assert metrics.rotation_error(rot_z(10), np.eye(3)) == pytest.approx(10.0)
    assert metrics.translation_error([1, 0, 0], [0, 1, 0]) == pytest.approx(90.0)
    assert metrics.translation_error([1, 0.1, 0], [-1, 0, 0]) == pytest.approx(
        np.degrees(np.arctan(0.1))
    )
    assert metrics.translation_error([1, 0, 0], [-1, 0, 0], sign_ambiguous=False) == pytest.approx(
        180.0
    )
    assert metrics.translation_error([1, 0, 0], [0, 0, 0]) == 0.0
    R, t = geometry.relative_pose(np.eye(3), np.zeros(3), rot_z(20), np.array([1.0, 0, 0]))
    assert metrics.rotation_angle(R) == pytest.approx(20.0)


def _two_views(rng, n=300, noise=0.0):
    cam = pycolmap.Camera(
        model="PINHOLE", width=640, height=480, params=[500.0, 520.0, 320.0, 240.0]
    )
    X = rng.uniform([-2, -2, 4], [2, 2, 8], size=(n, 3))
    R, t = random_rotation(rng, 15.0), np.array([1.0, 0.2, 0.1])
    x1 = X[:, :2] / X[:, 2:]
    Y = X @ R.T + t
    x2 = Y[:, :2] / Y[:, 2:]
    K = np.array([[500.0, 0, 320], [0, 520.0, 240], [0, 0, 1]])
    p1 = x1 @ K[:2, :2].T + K[:2, 2] + rng.normal(scale=noise, size=x1.shape)
    p2 = x2 @ K[:2, :2].T + K[:2, 2] + rng.normal(scale=noise, size=x2.shape)
    return cam, p1, p2, R, t


@pytest.mark.parametrize("estimator", ["cv2", "pycolmap"])
def test_essential_ransac_recovers_pose_and_fails_on_shuffled_matches(estimator):
    rng = np.random.default_rng(1)
    cam, p1, p2, R, t = _two_views(rng, noise=0.3)
    est = metrics.estimate_relative_pose(p1, p2, cam, cam, estimator=estimator)
    err = metrics.relative_pose_error(est["R"], est["t"], R, t)
    assert err["pose"] < 1.0 and est["num_inliers"] > 250
    # LO-RANSAC runs all its trials on pure outliers: slow, and cv2 covers it
    if estimator == "pycolmap":
        return
    shuffled = metrics.estimate_relative_pose(
        p1, rng.permutation(p2), cam, cam, estimator=estimator
    )
    bad = metrics.relative_pose_error(
        shuffled["R"] if shuffled else None, shuffled["t"] if shuffled else None, R, t
    )
    assert bad["pose"] > 5.0
    assert metrics.estimate_relative_pose(p1[:4], p2[:4], cam, cam, estimator=estimator) is None


def test_symmetric_epipolar_distance_and_transfer_error():
    # Pure x-translation between normalised cameras: epipolar lines are horizontal (y2 = y1).
    E = geometry.essential_from_pose(np.eye(3), np.array([1.0, 0, 0]))
    x1 = np.array([[0.1, 0.2], [0.3, -0.1]])
    x2 = np.array([[0.5, 0.2], [0.0, -0.1 + 0.02]])
    d = metrics.symmetric_epipolar_distance(x1, x2, E)
    assert d[0] == pytest.approx(0.0, abs=1e-12) and d[1] == pytest.approx(0.02)
    H = np.array([[1.0, 0, 5], [0, 1, -2], [0, 0, 1]])
    e = metrics.homography_transfer_error(
        np.array([[10.0, 10], [0, 0]]), np.array([[15.0, 8], [5, 1]]), H
    )
    assert e == pytest.approx([0.0, 3.0])
    assert metrics.share_within([0.5, 2.9, 4.0, 11.0, np.inf]) == pytest.approx([0.4, 0.6, 0.6])


def test_wxbs_scoring_with_an_exact_and_a_wrong_fundamental_matrix():
    rng = np.random.default_rng(2)
    cam, p1, p2, R, t = _two_views(rng, n=60)
    K = np.array([[500.0, 0, 320], [0, 520.0, 240], [0, 0, 1]])
    F = np.linalg.inv(K).T @ geometry.essential_from_pose(R, t) @ np.linalg.inv(K)
    corrs = np.concatenate([p1, p2], 1)
    assert metrics.share_within(metrics.geometry_errors(corrs, F, "F")) == pytest.approx(
        [1.0, 1.0, 1.0]
    )
    est = metrics.estimate_geometry(p1, p2, "F")
    assert metrics.share_within(metrics.geometry_errors(corrs, est["M"], "F"))[0] > 0.95
    assert metrics.share_within(metrics.geometry_errors(corrs, None, "F")) == [0.0, 0.0, 0.0]
    F_wrong = (
        np.linalg.inv(K).T @ geometry.essential_from_pose(rot_z(30) @ R, t[::-1]) @ np.linalg.inv(K)
    )
    assert metrics.share_within(metrics.geometry_errors(corrs, F_wrong, "F"))[0] < 0.3


def test_compare_poses_flags_wrong_registrations_after_similarity_alignment():
    rng = np.random.default_rng(3)
    ref = {f"im{i}": (random_rotation(rng, 40), rng.normal(size=3)) for i in range(8)}
    # est = ref seen in another world frame: x_est = s Q^T (x_ref - c)
    Q, s, c = random_rotation(rng), 2.5, rng.normal(size=3)
    est = {}
    for n, (R, t) in ref.items():
        center = -R.T @ t
        R_est = R @ Q
        c_est = s * Q.T @ (center - c)
        est[n] = (R_est, -R_est @ c_est)
    checks = compare_poses(est, ref)
    assert all(v["ok"] for v in checks.values())
    assert max(v["rotation_error"] for v in checks.values()) < 1e-6
    assert max(v["center_error"] for v in checks.values()) < 1e-6
    # one camera rotated by 10 deg, another one moved far away: both wrong, the rest still right
    R, t = est["im3"]
    est["im3"] = (rot_z(10) @ R, rot_z(10) @ t)
    R, t = est["im5"]
    center = -R.T @ t + np.array([30.0, 0, 0])
    est["im5"] = (R, -R @ center)
    checks = compare_poses(est, ref)
    assert [n for n, v in checks.items() if not v["ok"]] == ["im3", "im5"]
    assert compare_poses({"a": est["im0"]}, {"a": ref["im0"]})["a"]["ok"] is None


def test_matcher_specs_parse_and_refuse_unknown():
    """An unknown matcher or option stops the benchmark (no table silently missing a row)."""
    spec = matcher_specs.parse_spec("guided:ratio=none,window_cells=1.5,weights=a/b.safetensors")
    assert spec.name == "guided" and spec.conf == {
        "ratio": None,
        "window_cells": 1.5,
        "weights": "a/b.safetensors",
    }
    assert matcher_specs.parse_spec("raw").conf == {}
    specs = matcher_specs.parse_specs(["raw:ratio=0.9", "guided_epipolar"], {"device": "cpu"})
    assert [s.label for s in specs] == ["raw:ratio=0.9", "guided_epipolar"] and specs[0].conf == {
        "ratio": 0.9,
        "device": "cpu",
    }
    with pytest.raises(ValueError, match="not in the registry"):
        matcher_specs.parse_specs(["raw", "no_such_matcher"])
    with pytest.raises(ValueError, match="no option mutual"):
        matcher_specs.parse_specs(
            list(matcher_specs.DEFAULT_TWO_VIEW_SPECS) + ["raw:ratio=0.8,mutual=false"]
        )
    matcher_specs.parse_specs(matcher_specs.DEFAULT_TWO_VIEW_SPECS)  # every default row can run
    with pytest.raises(ValueError):
        matcher_specs.parse_spec("raw:ratio")


def test_one_preset_name_means_the_same_matcher_on_the_command_line_in_python_and_benchmarks():
    """matchers.PRESETS is the one set of named confs: get_matcher, the CLI's --matcher and the
    benchmark specs resolve a name to the same matcher and options, and every default benchmark row
    is a preset."""
    from colmap_guided.__main__ import build_parser
    from colmap_guided.cli import matcher_conf_from_args
    from colmap_guided.matchers import PRESETS, get_matcher, resolve_auto

    assert set(matcher_specs.DEFAULT_TWO_VIEW_SPECS) <= set(PRESETS)
    (spec,) = matcher_specs.parse_specs(["raw_mutual"], {"device": "cpu"})
    assert (spec.name, spec.conf) == ("raw", {"ratio": None, "device": "cpu"})
    assert (
        matcher_specs.parse_specs(["raw:ratio=none"])[0].conf
        == matcher_specs.parse_specs(["raw_mutual"])[0].conf
    )
    assert matcher_specs.build(spec).conf == get_matcher("raw_mutual", {"device": "cpu"}).conf
    args = build_parser().parse_args(
        [
            "match",
            "--database_path",
            "db.db",
            "--image_path",
            "images",
            "--matcher",
            "guided_ratio0.9",
            "--device",
            "cpu",
        ]
    )
    matcher = get_matcher(args.matcher, matcher_conf_from_args(args, args.matcher))
    assert matcher.name == "guided" and matcher.conf["ratio"] == 0.9
    assert (
        build_parser()
        .parse_args(["match", "--database_path", "db.db", "--image_path", "images"])
        .matcher
        == "auto"
    )
    # the drop-in on COLMAP's SIFT database
    assert resolve_auto("auto", "sift")[:2] == ("guided", "sift")
    with pytest.raises(ValueError, match="choose one of"):
        get_matcher("raw_ratio")


def test_estimate_geometry_returns_none_when_opencv_asserts(monkeypatch):
    """OpenCV 5's MAGSAC++ raises (!model.empty()) on some degenerate WxBS match sets: no model, no
    crash."""
    import cv2

    def failing(*args, **kwargs):
        raise cv2.error("(-215:Assertion failed) !model.empty() in function 'setModelParameters'")

    monkeypatch.setattr(cv2, "findFundamentalMat", failing)
    rng = np.random.default_rng(0)
    assert (
        metrics.estimate_geometry(rng.uniform(0, 100, (20, 2)), rng.uniform(0, 100, (20, 2)), "F")
        is None
    )
