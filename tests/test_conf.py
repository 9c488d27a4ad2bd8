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
