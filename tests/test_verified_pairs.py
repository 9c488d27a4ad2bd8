"""The matching preset on a few real pairs: verified inliers, reference check, timings, sweep."""

import json

import pytest

from recon_scripts.__main__ import main


@pytest.mark.slow
def test_matching_preset(shared_data, tmp_path, capsys):
    options = ["pairs_per_set=1", "unrelated=2", "repeat=1", f"cache_dir={tmp_path / 'features'}"]
    output = tmp_path / "matching.json"
    sets = "sets=lund_door_gtsfm wxbs/WGABS unrelated"
    assert main(["matching", sets, "methods=raw guided", f"output={output}", *options]) == 0
    summary = output.with_suffix(".md").read_text()
    assert summary in capsys.readouterr().out
    lines = summary.splitlines()
    assert lines[0] == (
        "| set | pair | raw inliers | guided inliers | raw s | guided s | guided/raw time |"
    )
    lund = lines[2].split(" | ")
    assert lund[:2] == ["| lund_door_gtsfm", "DSC_0001.JPG–DSC_0002.JPG"]
    # lund_door's pair verifies on the reference model's geometry, with thousands of inliers
    assert all(cell.endswith(" ✓") and int(cell[:-2]) > 1000 for cell in lund[2:4])
    assert lines[3].startswith("| wxbs/WGABS | kremlin | ")
    assert lines[5].startswith("Median per pair: raw ")
    assert lines[-4:-2] == ["| matcher | verified / pairs | max inliers |", "|---|---|---|"]
    assert [line.split(" | ")[0] for line in lines[-2:]] == ["| raw", "| guided"]
    assert all(line.split(" | ")[1].endswith("/2") for line in lines[-2:])
    results = json.loads(output.read_text())["results"]
    assert list(results) == ["lund_door_gtsfm", "wxbs/WGABS", "unrelated"]
    guided = results["lund_door_gtsfm"]["guided"]["pairs"][0]
    parts = guided["coarse_extract_s"] + guided["coarse_match_s"] + guided["eq1_s"]
    assert guided["total_s"] == pytest.approx(parts) and guided["reference"]
    unrelated = results["unrelated"]["raw"]["pairs"]
    assert len(unrelated) == 2 and all("|" in p["set"] and not p["reference"] for p in unrelated)


@pytest.mark.slow
def test_matching_sweep(shared_data, tmp_path, capsys):
    """Raw and 16 guided option sets on the same pairs (the coarse flows computed once a pair)."""
    output = tmp_path / "sweep.json"
    options = ["pairs_per_set=1", "unrelated=1", f"cache_dir={tmp_path / 'features'}"]
    sets = "sets=sacre_coeur_hloc unrelated"
    assert main(["matching", sets, "sweep=true", f"output={output}", *options]) == 0
    lines = output.with_suffix(".md").read_text().splitlines()
    assert lines[0].startswith("| matcher | ratio | max_fb_cells | window_cells | related verified")
    assert len(lines) == 2 + 17
    assert lines[2].startswith("| raw | – | – | – | 1/1 | 0 / 0 of 0 | 1.00 | ")
    assert lines[3].startswith("| guided | None | None | 1.0 | 1/1 | 0 / 0 of 0 | ")
    assert lines[-1].startswith("| guided | 0.95 | 2.0 | 2.0 | ")
    assert all(line.startswith("| guided | ") and line.endswith("/1 |") for line in lines[3:])
    results = json.loads(output.read_text())["results"]
    assert [len(runs) for runs in results.values()] == [17, 17]
    assert results["sacre_coeur_hloc"]["raw"]["torch_threads"] == 1


def test_the_sweep_runs_on_sift_only(capsys):
    assert main(["matching", "sweep=true", "features=aliked"]) == 2
    assert "SIFT only" in capsys.readouterr().err
    assert main(["matching", "features=orb"]) == 2
    assert "features: one of" in capsys.readouterr().err
