"""The retrieval preset: recall of the co-visible pairs of training scenes, alone and pooled."""

import json

import pytest

from recon_scripts.__main__ import main


@pytest.mark.slow  # GeM descriptors of two training scenes: about a minute
def test_retrieval_preset(shared_data, tmp_path, capsys):
    sets = ["train/dfsfm_sacre_coeur", "train/bundler_et"]
    output, work = tmp_path / "retrieval.json", tmp_path / "work"
    argv = ["retrieval", f"sets={' '.join(sets)} pooled", "k=2 100", f"work={work}"]
    assert main([*argv, f"output={output}"]) == 0
    summary = output.with_suffix(".md").read_text()
    assert summary in capsys.readouterr().out
    results = json.loads(output.read_text())["results"]
    assert list(results) == [*sets, "pooled"] and list(results["pooled"]) == ["k=2", "k=100"]
    scenes, pooled = [results[s] for s in sets], results["pooled"]
    for label in ("k=2", "k=100"):
        for key in ("images", "covisible", "connected_exhaustive"):
            assert pooled[label][key] == sum(s[label][key] for s in scenes) > 0
        assert all(s[label]["cross_scene"] == 0 for s in scenes)
    # k above the images: every pair, so every co-visible pair and exhaustive's components
    for r in [s["k=100"] for s in scenes] + [pooled["k=100"]]:
        assert (r["fraction"], r["recall"], r["connected"]) == (1, 1, r["connected_exhaustive"])
    sizes = [s["k=2"]["images"] for s in scenes]
    assert pooled["k=100"]["cross_scene"] == sizes[0] * sizes[1]
    assert pooled["k=2"]["pairs"] < pooled["k=100"]["pairs"]
    lines = summary.splitlines()
    assert [line.split(" | ")[:2] for line in lines[2:4]] == [
        ["| pooled (all scenes)", "2"],
        ["| pooled (all scenes)", "100"],
    ]
    assert lines[5].startswith("Per scene (alone): recall")
    assert lines[6] == "| scene | images | co-visible | k=2 | k=100 |"
    first = scenes[0]["k=2"]
    assert lines[8].startswith(f"| dfsfm_sacre_coeur | {first['images']} | {first['covisible']} |")
    connected = first["connected_exhaustive"]
    assert lines[8].endswith(f" | 1.00 (1.00) [{connected}/{connected}] |")
    # descriptors kept in the work folder; fewer shared points count more pairs co-visible
    assert (work / "train_dfsfm_sacre_coeur" / "descriptors.npy").is_file()
    assert main([*argv, "min_shared=1", f"output={tmp_path / 'loose.json'}"]) == 0
    loose = json.loads((tmp_path / "loose.json").read_text())["results"]["pooled"]["k=2"]
    assert loose["covisible"] > pooled["k=2"]["covisible"]
