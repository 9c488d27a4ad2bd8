"""Matcher variants for the benchmarks, picked from the registry by name.

A spec is ``name[:key=value[,key=value...]]``, e.g. ``raw:ratio=none`` (mutual check only),
``raw:ratio=0.8`` (ratio + mutual), ``guided:ratio=0.9``, ``guided_epipolar``. Values are parsed as JSON
when they can be (``none``/``null`` -> None, numbers, true/false), else kept as strings.
A spec whose matcher the registry does not have, or whose option the matcher does not know, raises
ValueError: a benchmark never drops a row silently.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

# Paper Table 2 rows that this project can produce (the best ratio among 0.8/0.9/0.95 is reported there).
DEFAULT_TWO_VIEW_SPECS = (
    "raw:ratio=none",  # bidirectional check only
    "raw:ratio=0.8",  # ratio test + bidirectional check (the paper's strong baseline)
    "guided:ratio=none",
    "guided:ratio=0.8",
    "guided:ratio=0.9",
    "guided:ratio=0.95",
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


def registry():
    """(MATCHERS, get_matcher) of the project's registry."""
    from colmap_guided.matchers import MATCHERS, get_matcher

    return MATCHERS, get_matcher


def parse_specs(texts, extra_conf: dict | None = None) -> list[MatcherSpec]:
    """Parse specs; ValueError for one the registry cannot build. ``extra_conf`` (e.g. device, weights)
    is added to each spec for the options its matcher knows."""
    matchers, _ = registry()
    out = []
    for text in texts:
        spec = parse_spec(text)
        if spec.name not in matchers:
            raise ValueError(f"Matcher {spec.name!r} of {text!r} is not in the registry ({', '.join(sorted(matchers))})")
        known = matchers[spec.name].default_conf
        unknown = sorted(set(spec.conf) - set(known))
        if unknown:
            raise ValueError(f"The {spec.name} matcher has no option {', '.join(unknown)} ({text!r}); known: {', '.join(sorted(known))}")
        for key, value in (extra_conf or {}).items():
            if key in known and key not in spec.conf and value is not None:
                spec.conf[key] = value
        out.append(spec)
    return out


def build(spec: MatcherSpec):
    _, get_matcher = registry()
    return get_matcher(spec.name, spec.conf)
