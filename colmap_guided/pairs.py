"""Which image pairs to match: exhaustive (COLMAP's exhaustive_matcher) or a pairs file.

A pairs file has one pair per line, ``name_a name_b`` (hloc / COLMAP matches_importer format);
names that contain spaces are separated by a tab instead, or resolved against the known names.
"""

from __future__ import annotations

from itertools import combinations
from pathlib import Path


def exhaustive_pairs(names: list[str]) -> list[tuple[str, str]]:
    return list(combinations(sorted(names), 2))


def _split_line(line: str, known: set[str]) -> tuple[str, str] | None:
    if "\t" in line:
        parts = [p.strip() for p in line.split("\t") if p.strip()]
        return (parts[0], parts[1]) if len(parts) >= 2 else None
    tokens = line.split(" ")
    for cut in range(1, len(tokens)):
        a, b = " ".join(tokens[:cut]), " ".join(tokens[cut:])
        if a in known and b in known:
            return a, b
    return (tokens[0], tokens[1]) if len(tokens) >= 2 else None


def read_pairs(path: Path, names: list[str]) -> list[tuple[str, str]]:
    """Pairs from a file, deduplicated (a-b and b-a are one pair), self-pairs dropped, in file order."""
    known = set(names)
    pairs, seen = [], set()
    for lineno, raw in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        pair = _split_line(line, known)
        if pair is None:
            raise ValueError(f"{path}:{lineno}: expected two image names per line, got {raw!r}.")
        for name in pair:
            if name not in known:
                raise ValueError(f"{path}:{lineno}: image {name!r} is not in the database/image folder; fix the pairs file.")
        key = tuple(sorted(pair))
        if pair[0] != pair[1] and key not in seen:
            seen.add(key)
            pairs.append(pair)
    return pairs


def write_pairs(path: Path, pairs: list[tuple[str, str]]) -> None:
    sep = lambda a, b: "\t" if (" " in a or " " in b) else " "  # noqa: E731
    Path(path).write_text("".join(f"{a}{sep(a, b)}{b}\n" for a, b in pairs), encoding="utf-8")
