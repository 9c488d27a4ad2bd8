"""Escalation: the learned matcher's full work only where it changes the outcome.

The first matching pass is cheap on purpose: pairs are matched most similar first and a pair is
deferred once both its photos have ``enough`` strongly verified neighbours (``match.BestFirst``),
and guided LightGlue's pair gate matches nothing where the coarse network sees no overlap. Each of
those decisions is undone for the photos that mapping leaves out: their deferred, gated and cheaply
matched pairs are matched with the full matcher, and the model is extended with them
(``reconstruct``), for ``rounds`` rounds or until no new pair verifies.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from . import database as dbio

default_conf = {
    # each photo's pairs are matched most similar first until it has this many neighbours verified
    # with strong_inliers; the rest wait for escalation (None: every selected pair is matched)
    "enough": 5,
    "strong_inliers": 100,  # inliers that make a verified neighbour count towards enough
    # rounds in which photos left out of the model get their deferred, gated and cheaply matched
    # pairs matched by the full matcher and join the model (0: none)
    "rounds": 2,
    # pairs a left-out photo gets per round, its most similar first: an unrelated photo (always
    # left out) costs this many, not all its pairs
    "pairs_per_photo": 5,
}
# the options that turn a matcher's cheap decisions off: its pair gate and cheap pass
GATES_OFF = {"min_pair_score": None, "cheap_inliers": None}


def full_matcher(matcher):
    """``matcher`` with its pair gate off (the matcher itself when it has none)."""
    off = {k: v for k, v in GATES_OFF.items() if k in matcher.conf and matcher.conf[k] != v}
    return type(matcher)({**matcher.conf, **off}) if off else matcher


def pairs_to_escalate(
    database_path: Path,
    left: set[str],
    selected: list[tuple[str, str]],
    done: set,
    per_photo: int,
    cheap_inliers: int | None = None,
) -> list[tuple[str, str]]:
    """The ``selected`` pairs (most similar first) of the photos ``left`` out of the model that the
    first pass did not match with the full matcher, up to ``per_photo`` for each: deferred (no
    matches), gated (none kept) or, with a cheap pass that keeps pairs of ``cheap_inliers``
    verified inliers, those with that many (the full matcher finds more, which a photo that mapping
    could not place may need); ``done``: pairs escalated already."""
    with dbio.open_database(database_path) as db:
        ids = {name: image.image_id for name, image in dbio.images_by_name(db).items()}
        counts, inliers = dbio.pair_match_counts(db), dbio.pair_inlier_counts(db)
    taken, todo = Counter(), []
    for a, b in selected:
        wants = [name for name in (a, b) if name in left and taken[name] < per_photo]
        if not wants or (a, b) in done:
            continue
        key = (min(ids[a], ids[b]), max(ids[a], ids[b]))
        if counts.get(key, 0) == 0 or (
            cheap_inliers is not None and inliers.get(key, 0) >= cheap_inliers
        ):
            taken.update(wants)
            todo.append((a, b))
    return todo
