"""The coarse PCK preset on a few held-out pairs: its table pools the points of every scene."""

import json

import numpy as np
import pytest

from recon_scripts.__main__ import main
from recon_scripts.matching.coarse_pck import select_pairs, totals


def test_coarse_pck_preset(shared_data, tmp_path, capsys):
    sets = ["strecha_entry_P10", "instantngp_fox"]
    output = tmp_path / "pck.json"
    argv = [
        "coarse_pck",
        f"sets={' '.join(sets)}",
        "methods=raw colmap_guided/weights/coarse_filter.safetensors",
        "labels=shipped",
        "archival=damaged_scan",
        "pairs_per_scene=1",
        "max_points=50",
        f"output={output}",
    ]
    assert main(argv) == 0
    text = capsys.readouterr().out
    summary = output.with_suffix(".md").read_text()
    assert summary in text
    rows = [line.split(" | ") for line in summary.splitlines() if line.startswith("| ")]
    assert [r[:2] for r in rows[1:5]] == [
        ["| raw correlation", "clean"],
        ["| raw correlation", "damaged_scan"],
        ["| shipped", "clean"],
        ["| shipped", "damaged_scan"],
    ]
    assert rows[5] == ["| method", "images", *sets[:-1], f"{sets[-1]} |"]
    results = json.loads(output.read_text())["results"]
    assert list(results) == sets and list(results[sets[0]]) == ["raw correlation", "shipped"]
    # the pooled PCK is the share of all errors (50 points, both directions, of each scene)
    parts = [results[s]["shipped"]["pck"]["clean"] for s in sets]
    assert [p["per_scene"][s]["n"] for p, s in zip(parts, sets)] == [100, 100]
    pooled = totals(parts)
    for t in (8, 16, 32):
        for prefix in ("", "resized_"):
            shares = [p["per_scene"][s][f"{prefix}pck{t}"] for p, s in zip(parts, sets)]
            assert pooled[f"{prefix}pck{t}"] == pytest.approx(np.mean(shares), abs=1e-12)
    assert rows[3][2:8] == [
        f"{100 * pooled[f'{prefix}pck{t}']:.1f}" for prefix in ("resized_", "") for t in (8, 16, 32)
    ]
    assert pooled["pck8"] <= pooled["pck16"] <= pooled["pck32"]
    # scenes of unlike sizes: the pooled share weighs each by its errors, the mean does not
    shares = {f"{p}pck{t}": 0.1 for p in ("", "resized_") for t in (8, 16, 32)}
    unlike = totals(
        [
            {"per_scene": {"a": {"n": 10, **shares, "pck16": 0.3}}, "match_s": 1.0, "pairs": 1},
            {"per_scene": {"b": {"n": 30, **shares}}, "match_s": 2.0, "pairs": 2},
        ]
    )
    assert unlike["pck16"] == 6 / 40 and unlike["scene_mean_pck16"] == pytest.approx(0.2)
    assert unlike["ms_per_pair"] == 1000.0 and unlike["n_points"] == 40
    assert [p[0] for p in select_pairs(sets, 1, 50)] == sets
