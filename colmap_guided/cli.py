"""What the commands share on the command line: the flags of ``PipelineConf``'s options (help
from their ``default_conf`` comments), the matcher's flags, and the conf the flags give.
Each command's parser and run function live beside its module (``add_parser``)."""

from __future__ import annotations

import argparse
import dataclasses

from . import escalate, features, mapping, pipeline
from .conf import add_conf_flags, at_most_zero, conf_from_flags, none_or
from .executor import EXECUTORS
from .features import aliked
from .matchers import AUTO, PRESETS, check_options
from .matchers.guided import GuidedMatcher
from .matchers.lightglue import GuidedLightGlueMatcher
from .pipeline import PipelineConf

# PipelineConf's options given as reconstruct's and match's flags: option -> flag (some flags keep
# the shorter name they had)
FEATURE_FLAGS = {
    "camera_mode": "camera_mode",
    "camera_model": "camera_model",
    "stretch_contrast_below": "stretch_contrast_below",
    "smooth_noise_above": "smooth_noise_above",
    "type": "features",
}
ALIKED_FLAGS = {
    "weights": "aliked_weights",
    "max_num_keypoints": "aliked_max_num_keypoints",
    "max_image_size": "aliked_max_image_size",
}
MAPPING_FLAGS = {"mapper": "mapper", "random_seed": "seed", "num_threads": "threads"}
# of the matcher's conf (the guided matcher's comments); not given: the chosen matcher's own
MATCHER_FLAGS = ["ratio", "weights", "device"]
# of guided LightGlue's conf (the default matcher's comments); another matcher's error names it
LIGHTGLUE_FLAGS = ["cheap_matches"]
PAIRS_FLAGS = [f.name for f in dataclasses.fields(pipeline.PairsConf)]


def add_pipeline_flags(parser: argparse.ArgumentParser, reconstruct: bool) -> None:
    """reconstruct's (all) or match's (matcher and pairs) options of ``pipeline.PipelineConf``."""
    if reconstruct:
        group = parser.add_argument_group("feature options")
        add_conf_flags(
            group,
            features,
            FEATURE_FLAGS,
            types=dict.fromkeys(
                ["stretch_contrast_below", "smooth_noise_above"],
                none_or(float, old_off=lambda text: text == "off"),
            ),
            choices={
                "camera_mode": sorted(features.CAMERA_MODES),
                "type": [*sorted(features.FEATURE_TYPES), AUTO],
            },
            what="feature",
            flags=FEATURE_FLAGS,
            defaults={"type": pipeline.FeatureConf().type},
        )
        add_conf_flags(group, aliked, ALIKED_FLAGS, types={"weights": str}, flags=ALIKED_FLAGS)
        group = parser.add_argument_group("mapping options")
        add_conf_flags(
            group,
            mapping,
            MAPPING_FLAGS,
            types={"random_seed": none_or(int, old_off=lambda text: int(text) < 0)},
            choices={"mapper": mapping.MAPPERS},
            flags=MAPPING_FLAGS,
        )
        group = parser.add_argument_group("escalation options (where the learned matcher runs)")
        add_conf_flags(
            group, escalate, types={"enough": none_or(int), "orphan_after": none_or(int)}
        )
    group = add_matcher_flags(parser, MATCHER_FLAGS)
    add_conf_flags(
        group,
        pipeline,
        PAIRS_FLAGS,
        types={"ray_address": str},
        choices={"executor": EXECUTORS},
        what="pairs",
    )


def add_matcher_flags(parser: argparse.ArgumentParser, keys: list[str]):
    """--matcher and the matcher options ``keys`` (not given: the chosen matcher's own), in a
    "matching options" group, which it returns."""
    group = parser.add_argument_group("matching options")
    add_conf_flags(group, pipeline, ["matcher"], choices={"matcher": [*sorted(PRESETS), AUTO]})
    add_conf_flags(
        group,
        GuidedMatcher,
        keys,
        types={"ratio": none_or(float, old_off=at_most_zero), "weights": str},
        what="matcher",
        defaults=dict.fromkeys(keys, argparse.SUPPRESS),
    )
    add_conf_flags(
        group,
        GuidedLightGlueMatcher,
        LIGHTGLUE_FLAGS,
        types={"cheap_matches": none_or(int)},
        what="matcher",
        defaults=dict.fromkeys(LIGHTGLUE_FLAGS, argparse.SUPPRESS),
    )
    return group


def matcher_options(args: argparse.Namespace, keys: list[str] = MATCHER_FLAGS) -> dict:
    """The matcher options ``keys`` and ``LIGHTGLUE_FLAGS`` given as flags (those not given are
    left out)."""
    return {
        **conf_from_flags(args, GuidedMatcher, keys, "matcher"),
        **conf_from_flags(args, GuidedLightGlueMatcher, LIGHTGLUE_FLAGS, "matcher"),
    }


def matcher_conf_from_args(args: argparse.Namespace, matcher: str) -> dict:
    """The matcher options given as flags, checked against ``matcher`` (a preset): one it does not
    take is ``matchers.check_options``' one-line error naming a matcher that takes it."""
    given = matcher_options(args)
    check_options(matcher, given)
    return given


def conf_from_args(args: argparse.Namespace) -> PipelineConf:
    """The ``PipelineConf`` of reconstruct's or match's flags; the matcher options given are
    checked against the matcher once ``PipelineConf.resolve`` has chosen it."""
    conf = {
        "matcher": {"name": args.matcher, "options": matcher_options(args)},
        "pairs": conf_from_flags(args, pipeline, PAIRS_FLAGS),
    }
    if args.command == "reconstruct":
        given = conf_from_flags(args, aliked, ALIKED_FLAGS, flags=ALIKED_FLAGS)
        conf["features"] = {
            **conf_from_flags(args, features, FEATURE_FLAGS, "feature", FEATURE_FLAGS),
            # ALIKED options set off their default (they make --features auto mean ALIKED)
            "aliked": {k: v for k, v in given.items() if v != aliked.default_conf[k]},
        }
        conf["mapping"] = conf_from_flags(args, mapping, MAPPING_FLAGS, "mapping", MAPPING_FLAGS)
        conf["escalation"] = conf_from_flags(args, escalate, list(escalate.default_conf))
    return PipelineConf.from_dict(conf)
