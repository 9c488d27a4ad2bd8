"""Matcher registry and presets: ``get_matcher(name, conf)`` for a preset name (below) or a matcher
of ``MATCHERS``."""

from __future__ import annotations

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
    # LightGlue 3-4.5x faster, fewer archival photos on the reference pose (docs/RESULTS.md)
    "guided_lightglue_fast": {"matcher": "guided_lightglue", "conf": {"max_keypoints": 1024}},
}


def preset(name: str) -> tuple[type[Matcher], dict]:
    """The matcher class and options of a preset; ValueError naming the presets for an unknown
    name."""
    if name not in PRESETS:
        raise ValueError(f"Unknown matcher {name!r}; choose one of {sorted(PRESETS)}.")
    return MATCHERS[PRESETS[name]["matcher"]], dict(PRESETS[name]["conf"])


# The guided matcher of each feature type, and the learned types ``auto`` prefers, the first
# installed wins.
GUIDED = {"sift": "guided", "aliked": "guided_lightglue", "xfeat": "guided_lighterglue"}
LEARNED = ("aliked",)


def installed_learned() -> tuple[str, ...]:
    """The learned feature types whose package (network, weights and matcher) is installed."""
    from colmap_guided import xfeat
    from colmap_guided.matchers import lightglue

    return tuple(
        kind for kind, ok in (("aliked", lightglue.installed()), ("xfeat", xfeat.installed())) if ok
    )


def resolve_auto(
    matcher: str, feature_type: str, installed: tuple[str, ...] | None = None
) -> tuple[str, str]:
    """(matcher preset, feature type) that ``auto`` stands for: the guided matcher (``GUIDED``) of
    the first of ``LEARNED`` whose package is installed (``installed``, default
    ``installed_learned()``), else guided SIFT. ``auto`` features follow an explicit matcher
    (LightGlue's: ALIKED; the others: SIFT), an ``auto`` matcher explicit features. Historical
    proxy, development split, 10 scenes x 3 seeds (docs/RESULTS.md)."""
    installed = installed_learned() if installed is None else installed
    if feature_type == AUTO:
        needs = None if matcher == AUTO else preset(matcher)[0].feature_types
        learned = next((kind for kind in LEARNED if kind in installed), "sift")
        feature_type = needs[0] if needs else (learned if matcher == AUTO else "sift")
    if matcher == AUTO:
        matcher = (
            GUIDED[feature_type]
            if feature_type == "sift" or feature_type in installed
            else "guided"
        )
    return matcher, feature_type


def get_matcher(name: str, conf: dict | None = None) -> Matcher:
    """The matcher of preset ``name`` with ``conf`` over the preset's options (unknown keys are an
    error)."""
    cls, options = preset(name)
    return cls({**options, **(conf or {})})


__all__ = [
    "AUTO",
    "DEFAULT_MATCHER",
    "GUIDED",
    "LEARNED",
    "MATCHERS",
    "PRESETS",
    "ImageData",
    "Matcher",
    "get_matcher",
    "preset",
    "resolve_auto",
]
