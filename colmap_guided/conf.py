"""One way to merge options over a stage's defaults: an unknown key (a typo) is a one-line error."""

from __future__ import annotations

import difflib


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
