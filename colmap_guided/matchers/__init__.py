"""Matcher registry: ``get_matcher(name, conf)`` for raw, guided, guided_epipolar, guided_homography, guided_colmap, lightglue."""

from __future__ import annotations

from colmap_guided.matchers.base import ImageData, Matcher
from colmap_guided.matchers.colmap import ColmapGuidedMatcher
from colmap_guided.matchers.geometric import (
    EpipolarGuidedMatcher,
    HomographyGuidedMatcher,
)
from colmap_guided.matchers.guided import GuidedMatcher
from colmap_guided.matchers.raw import RawMatcher

from colmap_guided.matchers.lightglue import LightGlueMatcher

MATCHERS: dict[str, type[Matcher]] = {
    cls.name: cls for cls in (RawMatcher, GuidedMatcher, EpipolarGuidedMatcher, HomographyGuidedMatcher, ColmapGuidedMatcher, LightGlueMatcher)
}
DEFAULT_MATCHER = "guided"


def get_matcher(name: str, conf: dict | None = None) -> Matcher:
    """A matcher by name with ``conf`` overriding its ``default_conf`` (unknown keys are an error)."""
    if name not in MATCHERS:
        raise ValueError(f"Unknown matcher {name!r}; choose one of {sorted(MATCHERS)}.")
    return MATCHERS[name](conf)


__all__ = ["DEFAULT_MATCHER", "MATCHERS", "ImageData", "Matcher", "get_matcher"]
