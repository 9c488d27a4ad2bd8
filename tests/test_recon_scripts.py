"""The benchmark runner: `python -m recon_scripts PRESET key=value ...`."""

import subprocess
import sys

from colmap_guided.paths import REPO_ROOT
from recon_scripts.__main__ import PRESETS, main, parse_value, preset_class


def test_help_lists_every_preset():
    out = subprocess.run(
        [sys.executable, "-m", "recon_scripts", "--help"],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    for name in PRESETS:
        assert f"\n  {name} " in out and preset_class(name).name == name


def test_options_are_read_against_the_presets_defaults(capsys):
    assert parse_value("sacre_coeur_hloc opensfm_lund", ["a"]) == [
        "sacre_coeur_hloc",
        "opensfm_lund",
    ]
    assert parse_value("3 5", [1]) == [3, 5] and parse_value("5", [1]) == [5]
    assert parse_value("[]", [1]) == [] and parse_value("false", True) is False
    assert parse_value("guided:raw_below=100", "x") == "guided:raw_below=100"
    conf = preset_class("pairs")({"k": [5], "sets": ["opensfm_lund"]}).conf
    assert conf["k"] == [5] and conf["matcher"] == "guided" and conf["sets"] == ["opensfm_lund"]


def test_an_unknown_option_or_preset_is_one_line_and_runs_nothing(capsys):
    assert main(["pairs", "kk=3"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "'kk'" in err and "did you mean 'k'" in err
    assert main(["pairs", "k"]) == 2 and "key=value" in capsys.readouterr().err
    assert main(["no_such_preset"]) == 2 and "unknown preset" in capsys.readouterr().err
