"""Escalation: the learned matcher's full work only where it changes the outcome.

The first matching pass is cheap on purpose: pairs are matched most similar first and a pair is
deferred once both its photos have ``enough`` strongly verified neighbours (``BestFirst``), guided
LightGlue's pair gate matches nothing where the coarse network sees no overlap, and its probe on
each photo's best keypoints keeps what it verifies with margin and leaves what it finds nothing in.
Each of those decisions is undone for the photos that mapping leaves out: their deferred, left and
cheaply matched pairs are matched with the full matcher, and the model is extended with them
(``reconstruct``), for ``rounds`` rounds or until a round adds no photo.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

from . import database as dbio
from .image_data import PairKey, pair_order
from .log import logger

default_conf = {
    # each photo's pairs are matched most similar first until it has this many neighbours verified
    # with strong_inliers; the rest wait for escalation (None: every selected pair is matched)
    "enough": 5,
    "strong_inliers": 100,  # inliers that make a verified neighbour count towards enough
    # rounds in which photos left out of the model get their deferred, gated and cheaply matched
    # pairs matched by the full matcher and join the model (0: none); a round that adds no photo
    # is the last
    "rounds": 2,
    # pairs a left-out photo gets per round, its most similar first: an unrelated photo (always
    # left out) costs this many, not all its pairs
    "pairs_per_photo": 5,
    # photos placed in a model other than the largest get escalated too (off: only photos in no
    # model, and the model is extended with those alone; joining links the models)
    "other_models": True,
    # a photo whose first this many pairs matched by the full matcher (the gate's pairs not
    # counted) verified none is an orphan: its other pairs but its this many most similar are not
    # matched, and escalation takes its pairs only for their other photo (None: off); an archive's
    # photos of nothing else cost that many
    "orphan_after": 3,
    # deferred pairs that a group of photos no strong pair links to the others may try, most
    # similar first, before mapping (0: none); two groups would be two models
    "join_tries": 3,
    # after escalation, the pairs of two models' most similar photos that the full matcher tries,
    # to join the models into one (0: none)
    "join_pairs": 10,
    # a model whose two sides conflict on what they see is cut in two, before escalation and
    # before joining (join.split_models: two places that look alike mapped as one)
    "cut_models": True,
    # a placed photo whose pairs with its model's photos were all kept by a cheap decision, or that
    # observes fewer than check_points 3D points, gets this many of those pairs matched by the
    # full matcher and keeps its place only where its pose from them agrees (recheck.py; 0: none)
    "check_pairs": 2,
    "check_points": 50,
}
# the options that turn a matcher's cheap decisions off: its pair gate, cheap pass and probe
GATES_OFF = {"min_pair_score": None, "cheap_inliers": None, "probe_keypoints": None}
# the options of the cheap decisions that keep a pair's matches without the full matcher (on)
KEEPS = ("cheap_inliers", "probe_keypoints")


def full_matcher(matcher):
    """``matcher`` with its cheap decisions off (the matcher itself when it has none)."""
    off = {k: v for k, v in GATES_OFF.items() if k in matcher.conf and matcher.conf[k] != v}
    return type(matcher)({**matcher.conf, **off}) if off else matcher


def keeps_cheaply(matcher) -> bool:
    """Whether one of the matcher's cheap decisions may keep a pair's matches: a pair it writes
    may then not be the full matcher's result (``record_kept``)."""
    return any(matcher.conf.get(k) is not None for k in KEEPS)


KEPT_PAIRS = "kept_pairs.jsonl"  # in a run's workspace: the pairs a cheap decision kept


def record_kept(path: Path | None, pairs: list[tuple[str, str]]) -> None:
    """Append the pairs (name_a, name_b) whose matches a cheap decision kept to ``path`` (JSON
    lines: names may hold any character)."""
    if path is not None and pairs:
        with open(path, "a", encoding="utf-8") as f:
            f.writelines(json.dumps(list(pair)) + "\n" for pair in pairs)


def read_kept(path: Path | None) -> set[frozenset]:
    """The pairs ``record_kept`` wrote to ``path`` (none where it is missing)."""
    if path is None or not Path(path).is_file():
        return set()
    lines = Path(path).read_text(encoding="utf-8").splitlines()
    return {frozenset(json.loads(line)) for line in lines if line.strip()}


def forget_kept(path: Path | None, pairs: list[tuple[str, str]]) -> None:
    """The pairs matched again by the full matcher leave the record of ``path``."""
    kept = read_kept(path)
    if kept & {frozenset(pair) for pair in pairs}:
        tmp = Path(path).with_name(Path(path).name + ".partial")
        tmp.write_text("", encoding="utf-8")
        record_kept(tmp, [tuple(sorted(p)) for p in kept - {frozenset(q) for q in pairs}])
        tmp.replace(path)


def orphans(tried: Counter, verified: set, orphan_after: int | None) -> set[str]:
    """The photos with ``orphan_after`` pairs or more matched by the full matcher (``tried``:
    pairs per photo written with a two-view geometry) of which none verified (``verified``)."""
    if orphan_after is None:
        return set()
    return {name for name, n in tried.items() if n >= orphan_after and name not in verified}


def database_orphans(db, ids: dict[str, int], pairs, orphan_after: int | None) -> set[str]:
    """``orphans`` of the ``pairs`` (name_a, name_b; ``ids``: name -> image id) written in the
    open database ``db``: verified, with their inliers (none where they did not verify)."""
    if orphan_after is None:
        return set()
    tried, verified = Counter(), set()
    inliers = dbio.pair_inlier_counts(db)
    for a, b in pairs:
        key = (min(ids[a], ids[b]), max(ids[a], ids[b]))
        if dbio.pair_is_verified(db, *key):
            tried.update((a, b))
            if inliers.get(key, 0) > 0:
                verified.update((a, b))
    return orphans(tried, verified, orphan_after)


def pairs_to_escalate(
    database_path: Path,
    left: set[str],
    selected: list[tuple[str, str]],
    done: set,
    per_photo: int,
    kept: set[frozenset] = frozenset(),
    elsewhere: set[str] = frozenset(),
    orphan_after: int | None = None,
) -> list[PairKey]:
    """The ``selected`` pairs (most similar first) of the photos ``left`` out of the model that the
    first pass did not match with the full matcher, up to ``per_photo`` for each: deferred or
    left by a cheap decision (never written) or ``kept`` by one (``read_kept``: the full matcher
    may find more, which a photo that mapping could not place may need). A pair the full matcher
    wrote is its own result: matching it again would give it again. ``done``: pairs (name_a,
    name_b) escalated already. A pair of two photos placed ``elsewhere`` (in models other than the
    largest) is not taken: it cannot bring either into the model. An orphan (``orphans``, with
    ``orphan_after``: nothing it was matched with verified) is not left out: its pairs are taken
    only for their other photo. Returns (id_a, id_b, name_a, name_b)."""
    taken, todo = Counter(), []
    with dbio.open_database(database_path) as db:
        ids = {name: image.image_id for name, image in dbio.images_by_name(db).items()}
        left = left - database_orphans(db, ids, selected, orphan_after)
        for a, b in selected:
            wants = [name for name in (a, b) if name in left and taken[name] < per_photo]
            if not wants or (a, b) in done or {a, b} <= elsewhere:
                continue
            key = (min(ids[a], ids[b]), max(ids[a], ids[b]))
            if not dbio.pair_has_matches(db, *key) or frozenset((a, b)) in kept:
                taken.update(wants)
                todo.append((ids[a], ids[b], a, b))
    return todo


class BestFirst:
    """Enough is enough, per photo: pairs are taken most similar first (retrieval descriptors), in
    three passes. The first matches a pair only while both its photos lack ``enough`` neighbours
    verified with ``strong_inliers`` inliers, which spreads the work over every photo; the second
    matches what a photo still lacks, and defers, not matches, a pair once both its photos have
    enough; the third links groups of photos that no strong pair joins (``join``). Matched pairs
    are verified as they come, so the counts are known. Each decision is the one that the results
    of every pair started before it give (it waits for pairs in flight when they could change it),
    and pairs are written in the order they started: a run is deterministic, and a rerun after a
    kill, counting the pairs in the database, decides as the uninterrupted run (its last pass
    may try a few pairs more)."""

    def __init__(self, db, id_pairs, rule: dict, options, descriptors, apart=()):
        """``rule``: enough, strong_inliers, join_tries, orphan_after (``match_database``'s)."""
        self.enough, self.strong_inliers = rule["enough"], rule["strong_inliers"]
        self.join_tries, self.orphan_after = rule["join_tries"], rule["orphan_after"]
        self.options = options
        self.similarity = {
            key: float(descriptors[key[2]] @ descriptors[key[3]]) for key in id_pairs
        }
        # each photo's orphan_after most similar pairs: matched even once it is an orphan (past
        # max_images_held, pairs come in memory order and a photo's first pairs may be others)
        ranked: dict[str, list] = {}
        for key in sorted(id_pairs, key=lambda key: (-self.similarity[key], key)):
            for name in key[2:]:
                ranked.setdefault(name, []).append(key)
        self.first = {name: set(keys[: self.orphan_after or 0]) for name, keys in ranked.items()}
        # panels of one collage card: a publisher's different views (none of their pairs verified
        # on the scanned collages), deferred to escalation
        self.group = {name: i for i, names in enumerate(apart) for name in names}
        self.strong: Counter = Counter()
        self.pending: Counter = Counter()
        # photos linked by strong pairs (union-find: photo -> a photo of its group), the group's
        # size and the pairs it tried in the last pass to link to another group
        self.linked, self.size, self.tries = {}, Counter(), Counter()
        # pairs per photo matched by the full matcher (written), photos with one verified
        self.tried: Counter = Counter()
        self.verified: set[str] = set()
        inliers = dbio.pair_inlier_counts(db)  # the pairs that did not verify are not in it
        for key in id_pairs:
            pair = (min(key[:2]), max(key[:2]))
            if dbio.pair_is_verified(db, *pair):
                self.count(key, inliers.get(pair, 0))
        self.started: set = set()
        self.deferred: dict[PairKey, None] = {}  # in the order deferred
        self.orphaned: dict[PairKey, None] = {}  # pairs of an orphan, not matched
        self.joining = 0  # pairs matched in the last pass

    def order(self, todo: list[PairKey], by_similarity: bool) -> list[PairKey]:
        """The three passes, each most similar first; past ``max_images_held`` images, the memory
        order of ``pair_order`` with each photo's pairs most similar first."""
        if by_similarity:
            ordered = sorted(todo, key=lambda key: -self.similarity[key])
        else:
            ordered, first = pair_order(todo), {}
            for i, key in enumerate(ordered):
                first.setdefault(key[2], i)
            ordered.sort(key=lambda key: (first[key[2]], -self.similarity[key]))
        self.first_pass = len(ordered)
        return ordered + ordered + ordered

    def decide(self, position: int, key: PairKey) -> bool | None:
        """Match the pair at ``position`` of ``order``: True; pass over it: False; None: the pairs
        in flight decide it, wait for them."""
        if key in self.started or (position >= 2 * self.first_pass and key not in self.deferred):
            return False
        lone = [self.orphan(name) and key not in self.first[name] for name in key[2:]]
        if True in lone:
            self.orphaned[key] = None
            return False
        if None in lone:
            return None
        if self.together(key):
            if position >= self.first_pass:
                self.deferred[key] = None
            return False
        if position >= 2 * self.first_pass:
            return self.join(key)
        lacks = max if position < self.first_pass else min  # both photos lack / either does
        have = [self.strong[name] for name in key[2:]]
        match = lacks(have) < self.enough
        if match != (lacks(h + self.pending[n] for h, n in zip(have, key[2:])) < self.enough):
            return None
        if not match and position >= self.first_pass:
            self.deferred[key] = None
        return match

    def join(self, key: PairKey) -> bool | None:
        """The last pass: enough neighbours per photo can leave groups of photos that no strong
        pair links (two cliques of ``enough`` + 1), which mapping would make separate models. A
        deferred pair across two groups is matched, most similar first, while the smaller group
        has tried fewer than ``join_tries``; None: wait for the pairs in flight, which may link
        them."""
        if any(self.pending.values()):
            return None
        a, b = (self.root(name) for name in key[2:])
        if a == b:
            return False
        smaller = min(a, b, key=lambda root: (self.size[root], root))
        if self.tries[smaller] >= self.join_tries:
            return False
        self.tries[smaller] += 1
        self.joining += 1
        del self.deferred[key]
        return True

    def orphan(self, name: str) -> bool | None:
        """Whether the photo is an orphan (``orphans``); None: its pairs in flight decide it."""
        if self.orphan_after is None or name in self.verified:
            return False
        if self.tried[name] + self.pending[name] < self.orphan_after:
            return False
        return True if self.pending[name] == 0 else None

    def count(self, key: PairKey, num_inliers: int) -> None:
        """A pair matched by the full matcher, verified with ``num_inliers``."""
        self.tried.update(key[2:])
        if num_inliers > 0:
            self.verified.update(key[2:])
        if num_inliers >= self.strong_inliers:
            self.add_strong(key)

    def root(self, name: str) -> str:
        while self.linked.get(name, name) != name:
            name = self.linked[name]
        return name

    def add_strong(self, key: PairKey) -> None:
        """A strong pair: a neighbour more for both photos, their groups one (the larger's root
        and tries stay)."""
        self.strong.update(key[2:])
        a, b = (self.root(name) for name in key[2:])
        if a != b:
            a, b = sorted((a, b), key=lambda root: (-max(self.size[root], 1), root))
            self.linked[b], self.size[a] = a, max(self.size[a], 1) + max(self.size[b], 1)

    def together(self, key: PairKey) -> bool:
        """Both photos of the pair are panels of one card."""
        a, b = (self.group.get(name) for name in key[2:])
        return a is not None and a == b

    def escalation_order(self, id_pairs: list[PairKey]) -> list[tuple[str, str]]:
        """Most similar first, panels of one card after every other pair."""
        ordered = sorted(id_pairs, key=lambda key: (self.together(key), -self.similarity[key]))
        return [key[2:] for key in ordered]

    def describe(self) -> dict:
        """The rule and what it deferred, for the report (logged)."""
        logger.info(
            "%d pairs deferred: both photos already had %d neighbours with %d+ inliers",
            len(self.deferred),
            self.enough,
            self.strong_inliers,
        )
        logger.info("%d deferred pairs matched to link groups of photos", self.joining)
        lone = orphans(self.tried, self.verified, self.orphan_after)
        logger.info(
            "%d orphan photo(s): none of their first %s pairs verified (%d pairs not matched)",
            len(lone),
            self.orphan_after,
            len(self.orphaned),
        )
        rule = {"enough": self.enough, "strong_inliers": self.strong_inliers}
        return {
            "deferred": rule,
            "num_pairs_deferred": len(self.deferred),
            "num_pairs_joining": self.joining,
            "orphan_after": self.orphan_after,
            "orphans": sorted(lone),
            "num_pairs_orphaned": len(self.orphaned),
        }

    def start(self, key: PairKey) -> None:
        self.started.add(key)
        self.pending.update(key[2:])

    def finish(self, key: PairKey, num_inliers: int | None) -> None:
        """The pair's verified inliers; None: the matcher left it (its gate), not counted."""
        self.pending.subtract(key[2:])
        if num_inliers is not None:
            self.count(key, num_inliers)
