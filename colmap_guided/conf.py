"""One way to merge options over a stage's defaults (an unknown key, a typo, is a one-line error),
and one spelling of an option that is off: None in Python, ``none`` on the command line."""

from __future__ import annotations

import difflib
from collections.abc import Callable
from typing import Any


def merge_conf(defaults: dict, conf: dict | None, what: str) -> dict:
    """``conf`` over ``defaults``; a key ``defaults`` does not have raises ValueError naming
    ``what``, the nearest known key and the known ones."""
    unknown = sorted(set(conf or {}) - set(defaults), key=str)
    if unknown:
        near = {
            key: close[0]
            for key in unknown
            if (close := difflib.get_close_matches(str(key), [str(k) for k in defaults], n=1))
        }
        if len(unknown) == 1:
            hint = f"; did you mean {near[unknown[0]]!r}?" if near else ";"
        else:
            hint = "; did you mean " + " and ".join(
                f"{near[key]!r} for {key!r}" for key in unknown if key in near
            )
            hint = hint + "?" if near else ";"
        keys = ", ".join(repr(key) for key in unknown)
        raise ValueError(
            f"Unknown {what} option{'s' if len(unknown) > 1 else ''} {keys}{hint} "
            f"known: {sorted(defaults)}"
        )
    return {**defaults, **(conf or {})}


def none_or(kind: Callable[[str], Any], old_off: Callable[[str], bool] | None = None):
    """An argparse type for an option that can be off: ``none`` (the one documented spelling) is
    None, other text ``kind(text)``. ``old_off``: the flag's other spellings of off (e.g. 0), read
    as None too so that existing command lines keep working."""

    def parse(text: str):
        text = text.strip()
        if text.lower() == "none" or (old_off is not None and old_off(text.lower())):
            return None
        return kind(text)

    parse.__name__ = getattr(kind, "__name__", "value")  # argparse's "invalid float value: ..."
    return parse


def at_most_zero(text: str) -> bool:
    """Whether a count or threshold given on the command line is 0 or below: off for the flags
    that read it so."""
    return float(text) <= 0
