"""One way to merge options over a stage's defaults: an unknown key (a typo) is a one-line error."""

from __future__ import annotations


def merge_conf(defaults: dict, conf: dict | None, what: str) -> dict:
    """``conf`` over ``defaults``; a key ``defaults`` does not have raises ValueError naming
    ``what``."""
    unknown = set(conf or {}) - set(defaults)
    if unknown:
        raise ValueError(f"Unknown {what} option(s) {sorted(unknown)}; known: {sorted(defaults)}")
    return {**defaults, **(conf or {})}
