"""Options merged over a stage's defaults: an unknown key is a one-line ValueError that names the
nearest known key and the known ones."""

import pytest

from colmap_guided import features, images
from colmap_guided.conf import merge_conf
from colmap_guided.matchers import get_matcher
from colmap_guided.synthetic import render_scene


def test_unknown_key_names_the_nearest_known_key():
    with pytest.raises(ValueError) as err:
        get_matcher("raw", {"ratoi": 0.9})
    assert str(err.value).startswith(
        "Unknown raw matcher option 'ratoi'; did you mean 'ratio'? known: ['chunk_size', "
    )
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match=r"option 'zzz'; known: \['a', 'b'\]$"):
        merge_conf({"a": 1, "b": 2}, {"zzz": 0}, "test")
    with pytest.raises(ValueError, match="options 'devcie', 'ratoi'; did you mean 'device' for "):
        merge_conf(get_matcher("raw").conf, {"ratoi": 1, "devcie": "cpu"}, "raw matcher")
    assert merge_conf({"a": 1, "b": 2}, {"b": 3}, "test") == {"a": 1, "b": 3}


def test_image_check_and_synthetic_scene_options_are_checked(tmp_path):
    """images.check_image(s), features' image_checks and render_scene: a typo is an error before
    any photo is read or written."""
    line = "Unknown image check option 'min_sise'; did you mean 'min_size'?"
    with pytest.raises(ValueError, match=line):
        images.check_image(tmp_path / "missing.jpg", {"min_sise": 10})
    with pytest.raises(ValueError, match=line):
        images.check_images(tmp_path, ["missing.jpg"], {"min_sise": 10})
    with pytest.raises(ValueError, match=line):
        features.check_conf({"image_checks": {"min_sise": 10}})
    assert images.check_conf({"min_size": 10})["min_size"] == 10
    with pytest.raises(ValueError, match="option 'focal_factr'; did you mean 'focal_factor'?"):
        render_scene(tmp_path / "scene", num_images=2, conf={"focal_factr": 1.0})
    assert not (tmp_path / "scene").exists()


def test_off_is_none_on_the_command_line_and_the_old_spellings_still_work():
    from colmap_guided.__main__ import build_parser
    from colmap_guided.conf import none_or
    from colmap_guided.mapping import check_conf as mapping_conf
    from colmap_guided.match import matcher_conf_from_args

    def parsed(*flags):
        return build_parser().parse_args(["reconstruct", "scene", *flags])

    for off in ("none", "None", "0", "-1"):
        assert matcher_conf_from_args(parsed("--ratio", off), "raw") == {"ratio": None}
    assert matcher_conf_from_args(parsed("--ratio", "0.7"), "raw") == {"ratio": 0.7}
    assert matcher_conf_from_args(parsed(), "raw") == {}  # not given: the matcher's own
    for off in ("none", "off"):
        args = parsed("--stretch_contrast_below", off, "--smooth_noise_above", off)
        assert (args.stretch_contrast_below, args.smooth_noise_above) == (None, None)
    assert parsed("--seed", "none").seed is None and parsed("--seed", "-1").seed is None
    assert parsed("--seed", "3").seed == 3 and parsed().seed == 0
    assert mapping_conf({"random_seed": -1})["random_seed"] is None
    assert mapping_conf({"random_seed": None})["random_seed"] is None
    with pytest.raises(ValueError):
        none_or(float)("off")  # "off" only where a flag reads it so
    with pytest.raises(SystemExit):
        parsed("--ratio", "low")
