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
    from colmap_guided.cli import matcher_conf_from_args
    from colmap_guided.conf import none_or
    from colmap_guided.mapping import check_conf as mapping_conf

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


class _Stage:
    """A stage whose options the flag generator reads: its dict literal and comments."""

    default_conf = {
        "ratio": 0.8,  # nearest-neighbour ratio test
        # matches kept per pair,
        # at most
        "max_matches": 256,
        "name": "raw",
        "threshold": None,  # pixels; None: no threshold
        "sizes": (512, 1024),
        "steps": (),
        "refine": True,  # sub-pixel refinement
        "nested": {"a": 1},  # options of a part
        "verbose": False,
        "keep": 50,  # matches kept, in % of all
    }


def _stage_parser(keys=None, **kwargs):
    import argparse

    from colmap_guided.conf import add_conf_flags

    parser = argparse.ArgumentParser()
    kwargs.setdefault("types", {"threshold": float, "steps": int})
    keys = add_conf_flags(parser, _Stage, keys, **kwargs)
    return parser, keys


def test_conf_comments_are_the_lines_above_and_the_end_of_the_key_line(tmp_path):
    import importlib.util

    from colmap_guided.conf import conf_comments
    from colmap_guided.train import trainer

    assert conf_comments(_Stage) == {
        "ratio": "nearest-neighbour ratio test",
        "max_matches": "matches kept per pair, at most",
        "threshold": "pixels; None: no threshold",
        "refine": "sub-pixel refinement",
        "nested": "options of a part",
        "keep": "matches kept, in % of all",
    }
    source = (
        "default_conf = {\n"
        "    # a comment above a blank line belongs to no key\n"
        "\n"
        '    "a": [1,  # a\n'
        "        # not b's\n"
        "        2],\n"
        '    "b": 1,\n'
        "}\n"
    )
    (tmp_path / "stage_module.py").write_text(source)
    spec = importlib.util.spec_from_file_location("stage_module", tmp_path / "stage_module.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert conf_comments(module) == {"a": "a"}
    comments = conf_comments(trainer)  # keys with comments above and after, in a module
    assert comments["sparse_radius"] == "cells around each best match"
    assert comments["sparse_k"].startswith("sparse support as the pipeline matches")
    assert comments["impl"].startswith("filter during training: 'sparse' (the CPU inference")


def test_flags_from_default_conf_types_none_bools_and_lists():
    from colmap_guided.conf import conf_from_flags

    keys = ["ratio", "max_matches", "name", "threshold", "sizes", "steps", "refine", "verbose"]
    parser, got = _stage_parser(keys)
    assert got == keys
    args = parser.parse_args([])
    assert conf_from_flags(args, _Stage, keys) == {k: _Stage.default_conf[k] for k in keys}
    args = parser.parse_args(
        "--ratio 0.9 --max_matches 10 --name guided --threshold 2.5 --sizes 256 --steps 5 7"
        " --no_refine --verbose".split()
    )
    conf = conf_from_flags(args, _Stage, keys)
    assert conf == {
        "ratio": 0.9,
        "max_matches": 10,
        "name": "guided",
        "threshold": 2.5,
        "sizes": (256,),
        "steps": (5, 7),
        "refine": False,
        "verbose": True,
    }
    assert type(conf["max_matches"]) is int and type(conf["ratio"]) is float
    assert parser.parse_args(["--refine", "--threshold", "none"]).refine is True
    assert parser.parse_args(["--threshold", "None"]).threshold is None
    assert parser.parse_args(["--steps"]).steps == []
    for bad in (["--max_matches", "1.5"], ["--ratio", "none"], ["--threshold", "off"]):
        with pytest.raises(SystemExit):  # none is off only where the default is None
            parser.parse_args(bad)


def test_flag_help_is_the_comment_and_the_default():
    keys = [k for k in _Stage.default_conf if k != "nested"]
    parser, _ = _stage_parser(keys, choices={"name": ["raw", "guided"]})
    helps = {a.dest: a.help for a in parser._actions}
    assert helps["ratio"] == "nearest-neighbour ratio test (default: 0.8)"
    assert helps["max_matches"] == "matches kept per pair, at most (default: 256)"
    assert helps["name"] == "(default: raw)"
    assert helps["threshold"] == "pixels; None: no threshold (default: none)"
    assert helps["sizes"] == "(default: 512 1024)" and helps["steps"] == "(default: empty)"
    assert helps["refine"] == "sub-pixel refinement (default: --refine)"
    assert helps["verbose"] == "(default: --no_verbose)"
    text = parser.format_help()
    assert "--refine, --no_refine" in text and "--name {raw,guided}" in text
    assert "matches kept, in % of all (default: 50)" in text  # a % in a comment is not a format
    with pytest.raises(SystemExit):
        parser.parse_args(["--name", "dense"])


def test_flag_generator_errors_unknown_key_and_missing_type():
    with pytest.raises(
        ValueError, match=r"^Unknown stage option 'max_matchs'; did you mean 'max_m"
    ):
        _stage_parser(["ratio", "max_matchs"], what="stage")
    with pytest.raises(ValueError, match="Unknown _Stage option 'treshold'; did you mean 'thr"):
        _stage_parser(["ratio"], types={"treshold": float})
    with pytest.raises(TypeError, match="'threshold' .*give its type"):
        _stage_parser(["threshold"], types={})
    with pytest.raises(TypeError, match="'steps' .*give its type"):
        _stage_parser(["steps"], types={})
    with pytest.raises(TypeError, match="'nested'"):
        _stage_parser(["nested"])


def test_training_flags_are_the_trainer_and_data_options():
    """python -m colmap_guided.train: each generated flag's default is its option's default."""
    from colmap_guided.train import __main__ as cli
    from colmap_guided.train.data import CoarseTrainData
    from colmap_guided.train.trainer import default_conf

    conf = cli.conf_from_args(cli.parse_args(["--out", "o"]))
    assert {k: conf[k] for k in cli.TRAIN_KEYS} == {k: default_conf[k] for k in cli.TRAIN_KEYS}
    data = CoarseTrainData.default_conf
    assert {k: conf["data"][k] for k in cli.DATA_KEYS} == {k: data[k] for k in cli.DATA_KEYS}
    assert conf["data"]["train_scenes"] is None and conf["data"]["val_scenes"] == data["val_scenes"]
    args = cli.parse_args("--out o --lr_steps 100 200 --impl dense --max_cells none".split())
    conf = cli.conf_from_args(args)
    assert (conf["lr_steps"], conf["impl"], conf["data"]["max_cells"]) == (
        (100, 200),
        "dense",
        None,
    )
    assert (
        cli.conf_from_args(cli.parse_args(["--out", "o", "--max_cells", "24"]))["data"]["max_cells"]
        == 24
    )
    with pytest.raises(SystemExit):
        cli.parse_args(["--out", "o", "--impl", "fast"])


def test_pipeline_conf_is_the_stages_defaults_and_strict():
    """PipelineConf: each section's defaults are its stage's default_conf; an unknown key, in the
    conf or a section or the chosen matcher's options, is a one-line error naming the nearest."""
    from colmap_guided import mapping, pipeline
    from colmap_guided.pipeline import PipelineConf

    conf = PipelineConf()
    assert conf.features.to_dict() == {**features.default_conf, "type": "auto"}
    assert conf.mapping.to_dict() == mapping.default_conf
    assert conf.pairs.to_dict() == {
        k: v for k, v in pipeline.default_conf.items() if k != "matcher"
    }
    assert (conf.matcher.name, conf.matcher.options, conf.verification.options) == ("auto", {}, {})
    assert PipelineConf.from_dict({}) == conf and PipelineConf.from_dict(None) == conf
    given = PipelineConf.from_dict(
        {"matcher": {"name": "raw", "options": {"ratio": None}}, "mapping": {"num_threads": 1}}
    )
    assert given.matcher.options == {"ratio": None} and given.mapping.num_threads == 1
    assert given.mapping.mapper == mapping.default_conf["mapper"]
    for bad, line in (
        ({"maping": {}}, "Unknown pipeline option 'maping'; did you mean 'mapping'? known: "),
        ({"pairs": {"num_neighbours": 3}}, "Unknown pairs option 'num_neighbours'; did you mean "),
        ({"features": {"camera_mod": "single"}}, "Unknown feature option 'camera_mod'; did you "),
        ({"verification": {"min_inliers": 3}}, "Unknown verification option 'min_inliers'; did "),
        ({"matcher": {"name": "raw", "options": {"ratoi": 0.9}}}, "Unknown raw matcher option "),
    ):
        with pytest.raises(ValueError) as err:
            PipelineConf.from_dict(bad)
        assert str(err.value).startswith(line) and "\n" not in str(err.value)
    with pytest.raises(ValueError, match="did you mean 'ratio'"):
        PipelineConf().over(matcher="raw", matcher_conf={"ratoi": 0.9})
    with pytest.raises(ValueError, match="Unknown matcher 'rwa'; choose one of"):
        PipelineConf.from_dict({"matcher": {"name": "rwa"}})


def test_command_line_flags_are_the_pipeline_conf():
    """reconstruct's and match's flags: their defaults are PipelineConf's, their help the option's
    comment in its stage's default_conf."""
    from colmap_guided import mapping, pipeline
    from colmap_guided.__main__ import build_parser
    from colmap_guided.cli import conf_from_args
    from colmap_guided.conf import conf_comments
    from colmap_guided.matchers.guided import GuidedMatcher
    from colmap_guided.pipeline import PipelineConf

    parser = build_parser()
    args = parser.parse_args(["reconstruct", "scene"])
    assert conf_from_args(args) == PipelineConf()
    args = parser.parse_args(["match", "--database_path", "d", "--image_path", "i"])
    assert conf_from_args(args) == PipelineConf()
    args = parser.parse_args(
        "reconstruct scene --features sift --seed 3 --threads 1 --pairs sequential"
        " --num_neighbors 4 --aliked_weights w.pth --matcher raw".split()
    )
    conf = conf_from_args(args)
    assert (conf.features.type, conf.features.aliked) == ("sift", {"weights": "w.pth"})
    assert (conf.mapping.random_seed, conf.mapping.num_threads) == (3, 1)
    assert (conf.pairs.pairs, conf.pairs.num_neighbors) == ("sequential", 4)
    assert conf.matcher.name == "raw"
    # ALIKED sized down: the options set, no others
    args = parser.parse_args(
        "reconstruct scene --aliked_max_num_keypoints 1024 --aliked_max_image_size 1024".split()
    )
    aliked = {"max_num_keypoints": 1024, "max_image_size": 1024}
    assert conf_from_args(args).features.aliked == aliked
    rec = next(a for a in parser._actions if a.dest == "command").choices["reconstruct"]
    helps = {a.option_strings[0]: a.help for a in rec._actions if a.option_strings}
    comment = conf_comments(features)["stretch_contrast_below"].replace("%", "%%")
    assert helps["--stretch_contrast_below"] == f"{comment} (default: 0.5)"
    assert helps["--seed"] == f"{conf_comments(mapping)['random_seed']} (default: 0)"
    assert helps["--num_neighbors"] == f"{conf_comments(pipeline)['num_neighbors']} (default: 10)"
    assert helps["--matcher"] == f"{conf_comments(pipeline)['matcher']} (default: auto)"
    assert helps["--ratio"] == f"{conf_comments(GuidedMatcher)['ratio']} (default: the matcher's)"
