"""Matcher variants for the benchmarks: a preset of ``matchers.PRESETS`` by name, with options over
it.

A spec is ``preset[:key=value[,key=value...]]``, e.g. ``raw_mutual`` (mutual check only), ``raw``
(ratio + mutual), ``guided_ratio0.9``, ``guided:window_cells=2`` (an option swept outside the
presets). Values are parsed as JSON when they can be (``none``/``null`` -> None, numbers,
true/false), else kept as strings. A spec whose preset does not exist, or whose option its matcher
does not know, raises ValueError: a benchmark never drops a row silently. A parsed spec names the
matcher (``name``) and holds the preset's options with the overrides (``conf``); ``label`` is its
text.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

# Paper Table 2 rows that this project can produce (the best ratio among 0.8/0.9/0.95 is reported
# there).
DEFAULT_TWO_VIEW_SPECS = (
    "raw_mutual",  # bidirectional check only
    "raw",  # ratio test 0.8 + bidirectional check (the paper's strong baseline)
    "guided_mutual",
    "guided",  # ratio 0.8
    "guided_ratio0.9",
    "guided_ratio0.95",
    "guided_epipolar",
    "guided_homography",
    "guided_colmap",  # COLMAP's own guided_matching option
)


@dataclass
class MatcherSpec:
    name: str
    conf: dict = field(default_factory=dict)
    text: str = ""

    @property
    def label(self) -> str:
        return self.text or self.name


def _parse_value(text: str):
    low = text.strip().lower()
    if low in ("none", "null", "off"):
        return None
    try:
        return json.loads(low if low in ("true", "false") else text)
    except json.JSONDecodeError:
        return text


def parse_spec(text: str) -> MatcherSpec:
    name, _, rest = text.partition(":")
    conf = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"matcher option {item!r} in {text!r} is not key=value")
        conf[key.strip()] = _parse_value(value)
    return MatcherSpec(name.strip(), conf, text)


def matcher_class(name: str):
    """The matcher class of a registry name."""
    from colmap_guided.matchers import MATCHERS

    return MATCHERS[name]


def parse_specs(texts, extra_conf: dict | None = None) -> list[MatcherSpec]:
    """Parse specs into (matcher, preset options + overrides); ValueError for one that cannot be
    built. ``extra_conf`` (e.g. device, weights) is added to each spec for the options its matcher
    knows."""
    from colmap_guided.matchers import PRESETS, preset

    out = []
    for text in texts:
        spec = parse_spec(text)
        if spec.name not in PRESETS:
            raise ValueError(
                f"Matcher {spec.name!r} of {text!r} is not in "
                f"the registry ({', '.join(sorted(PRESETS))})"
            )
        cls, options = preset(spec.name)
        known = cls.default_conf
        unknown = sorted(set(spec.conf) - set(known))
        if unknown:
            raise ValueError(
                f"The {cls.name} matcher has no option {', '.join(unknown)} "
                f"({text!r}); known: {', '.join(sorted(known))}"
            )
        spec = MatcherSpec(cls.name, {**options, **spec.conf}, text)
        for key, value in (extra_conf or {}).items():
            if key in known and key not in spec.conf and value is not None:
                spec.conf[key] = value
        out.append(spec)
    return out


def build(spec: MatcherSpec):
    from colmap_guided.matchers import get_matcher

    return get_matcher(spec.name, spec.conf)
