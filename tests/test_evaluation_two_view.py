"""Two-view protocol on real pairs with reference cameras, and WxBS scoring (fast: a few pairs)."""

import json
import subprocess
import sys

import numpy as np
import pytest

from colmap_guided.paths import REPO_ROOT
from recon_scripts.__main__ import main
from recon_scripts.evaluation import metrics, two_view
from recon_scripts.evaluation.reference import load_reference


@pytest.mark.parametrize("key", ["train/strecha_entry_P10", "train/instantngp_fox"])
def test_reference_cameras_agree_with_the_pseudo_ground_truth(shared_data, key):
    """The Strecha / instant-ngp conversions (axes, K rescaling) agree with the independent COLMAP
    model."""
    ref, pseudo = load_reference(key, "reference"), load_reference(key, "pseudo_gt")
    assert ref.source == "reference" and pseudo.source == "pseudo_gt"
    pairs = two_view.sample_pairs(ref, 12, seed=0)
    assert len(pairs) == 12
    errs = [
        metrics.relative_pose_error(
            *pseudo.relative_pose(p["a"], p["b"]), *ref.relative_pose(p["a"], p["b"])
        )["R"]
        for p in pairs
    ]
    assert np.median(errs) < 2.0
    # sampling is deterministic and only yields covisible pairs with a reference pose
    assert pairs == two_view.sample_pairs(ref, 12, seed=0)
    assert all(p["covisible"] >= 50 and ref.comparable(p["a"], p["b"]) for p in pairs)


def test_strecha_castle_frames_are_not_mixed(shared_data):
    ref = load_reference("train/strecha_castle")
    # two calibration frames
    assert not ref.comparable("castle-P19_0000.jpg", "castle-P30_0020.jpg")
    assert all(ref.comparable(p["a"], p["b"]) for p in two_view.sample_pairs(ref, None))


@pytest.fixture(scope="module")
def sift_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("sift_cache")


def test_pose_protocol_on_real_pairs(shared_data, sift_cache):
    result = two_view.run_pose_benchmark(
        scenes=("train/strecha_entry_P10",),
        specs=["raw:ratio=0.8"],
        max_pairs=2,
        cache_dir=sift_cache,
    )
    r = result["results"]["raw:ratio=0.8"]
    errors = [p["err_pose"] for p in r["pairs"]]
    assert len(errors) == 2
    # the summary is the trapezoid AUC of the per-pair errors
    assert r["summary"]["auc"] == pytest.approx([100 * v for v in metrics.pose_auc(errors)])
    # raw SIFT on easy Strecha pairs: a right protocol (intrinsics, pixel convention, pose
    # direction) gives errors of a few degrees at most; a wrong one gives tens of degrees
    assert max(errors) < 5.0 and r["summary"]["precision"] > 50
    # the metric itself: reference poses score 100, the poses of the other pair score ~0
    ref = load_reference("train/strecha_entry_P10")
    gts = [ref.relative_pose(p["a"], p["b"]) for p in result["pairs"]]
    assert metrics.pose_auc(
        [metrics.relative_pose_error(*gt, *gt)["pose"] for gt in gts]
    ) == pytest.approx([1, 1, 1])
    swapped = [metrics.relative_pose_error(*gts[1 - i], *gts[i])["pose"] for i in range(2)]
    assert min(swapped) > 5.0 and metrics.pose_auc(swapped)[0] == 0.0


def test_wxbs_ground_truth_correspondences_score_high(shared_data):
    pairs = two_view.list_wxbs_pairs()
    assert len(pairs) >= 30
    pair = next(p for p in pairs if p["pair"] == "WGABS/kremlin")
    corrs = two_view.wxbs_corrs_colmap(pair["corrs"])
    F = metrics.estimate_geometry(corrs[:, :2], corrs[:, 2:], "F")["M"]
    share = metrics.share_within(metrics.geometry_errors(corrs, F, "F"))
    assert share[2] > 0.9  # the labels agree with one epipolar geometry
    rng = np.random.default_rng(0)
    shuffled = np.concatenate([corrs[:, :2], corrs[rng.permutation(len(corrs)), 2:]], 1)
    assert metrics.share_within(metrics.geometry_errors(shuffled, F, "F"))[0] < share[0] / 2


def test_two_view_preset(shared_data, sift_cache, tmp_path, capsys):
    """The preset on one pair of each of two scenes (strecha_entry_P10's features cached by the
    test above) and one WxBS pair: the same records and summary as one run of the protocol on both
    scenes; a matcher it cannot run stops it before any work (a table never loses a row
    silently)."""
    out = tmp_path / "out"
    scenes = ["train/strecha_entry_P10", "train/strecha_castle"]
    argv = [
        "two_view",
        f"sets={' '.join(scenes)} wxbs",
        "max_pairs=1",
        "methods=raw:ratio=0.8",
        "wxbs_max_pairs=1",
        f"cache_dir={sift_cache}",
        f"output={out / 'benchmark.json'}",
    ]
    with pytest.raises(ValueError, match="no_such_matcher"):
        main([*argv, "methods=raw:ratio=0.8 no_such_matcher"])
    assert not out.exists()
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "| raw:ratio=0.8 |" in text and "AUC@5°" in text and "WxBS" in text
    for name in (
        "two_view.json",
        "two_view.md",
        "two_view.png",
        "wxbs.json",
        "wxbs.md",
        "wxbs.png",
        "benchmark.json",
        "benchmark.md",
    ):
        assert (out / name).is_file()
    data = json.loads((out / "two_view.json").read_text())
    assert list(data["results"]) == ["raw:ratio=0.8"] and len(data["pairs"]) == 2
    whole = two_view.run_pose_benchmark(scenes, ["raw:ratio=0.8"], 1, cache_dir=sift_cache)
    assert data["config"] == whole["config"] and data["pairs"] == whole["pairs"]
    mine, theirs = data["results"]["raw:ratio=0.8"], whole["results"]["raw:ratio=0.8"]

    def untimed(rows):
        return [{k: v for k, v in r.items() if k not in ("time", "time_per_pair")} for r in rows]

    assert untimed(mine["pairs"]) == untimed(theirs["pairs"])
    assert untimed([mine["summary"]]) == untimed([theirs["summary"]])
    assert list(mine["per_scene"]) == scenes
    assert (out / "two_view.md").read_text() in text
    wxbs = json.loads((out / "wxbs.json").read_text())
    share = wxbs["results"]["raw:ratio=0.8"]["pairs"][0]["share"]
    assert share == sorted(share) and 0 <= share[0] <= 100


@pytest.mark.slow
def test_two_view_preset_command(shared_data, tmp_path):
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        "-m",
        "recon_scripts",
        "two_view",
        "sets=train/strecha_entry_P10 wxbs",
        "max_pairs=1",
        "methods=raw:ratio=0.8",
        "wxbs_max_pairs=1",
        f"cache_dir={tmp_path / 'cache'}",
        f"output={out / 'benchmark.json'}",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=REPO_ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "| raw:ratio=0.8 |" in proc.stdout and "AUC@5°" in proc.stdout
    for name in (
        "two_view.json",
        "two_view.md",
        "two_view.png",
        "wxbs.json",
        "wxbs.md",
        "wxbs.png",
    ):
        assert (out / name).is_file()
    data = json.loads((out / "two_view.json").read_text())
    assert list(data["results"]) == ["raw:ratio=0.8"] and len(data["pairs"]) == 1
