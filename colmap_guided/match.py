"""Stage 3+4: match image pairs into the database and verify them — the drop-in exhaustive_matcher.

Reads the keypoints and descriptors that `colmap feature_extractor` / pycolmap.extract_features
wrote, writes matches and two-view geometries, so that `colmap mapper` or
pycolmap.incremental_mapping run on the database afterwards unchanged. Pairs already matched
(and verified) are skipped: a killed run resumes.
"""

from __future__ import annotations

import time
from collections import Counter, defaultdict, deque
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import database as dbio
from . import features, verify
from .conf import merge_conf
from .executor import get_executor
from .image_data import MAX_IMAGES_HELD, HeldImages, PairKey
from .log import colmap_quiet, logger
from .matchers import AUTO, get_matcher, resolve_auto
from .matchers.base import Matcher, scoped_torch_threads
from .pairs import global_descriptors, select_pairs
from .pipeline import PipelineConf


def _progress(iterable, desc: str, total: int):
    return tqdm(
        iterable, desc=desc, total=total, unit="pair", disable=None, dynamic_ncols=True, leave=False
    )


def match_database(
    database_path: Path,
    image_path: Path,
    pairs_path: str | Path | None = None,
    matcher: str | Matcher | None = None,
    matcher_conf: dict | None = None,
    verification_conf: dict | None = None,
    overwrite: bool = False,
    num_neighbors: int | None = None,
    executor: str | None = None,
    ray_address: str | None = None,
    max_images_held: int = MAX_IMAGES_HELD,
    conf: PipelineConf | None = None,
    enough: int | None = None,
    strong_inliers: int = 100,
) -> dict:
    """Match the selected pairs and verify them; return statistics for the report.

    ``conf``: the matcher, pairs and verification options (``pipeline.PipelineConf``, default its
    defaults); the keyword options given (not None) go over it. ``pairs_path``: a pairs file or a
    mode of ``pairs.PAIR_MODES`` (auto: exhaustive for small sets, retrieval of ``num_neighbors``
    per image above). ``executor``: 'local' (threads) or 'ray' (a private local Ray instance, or
    the cluster at ``ray_address`` / RAY_ADDRESS). ``max_images_held``: images held in memory at
    once. ``enough``: match the pairs most similar first and defer a pair once both its photos have
    ``enough`` neighbours verified with ``strong_inliers`` (``BestFirst``); None: every pair."""
    conf = (conf or PipelineConf()).over(
        matcher,
        matcher_conf,
        pairs={
            "pairs": pairs_path,
            "num_neighbors": num_neighbors,
            "executor": executor,
            "ray_address": ray_address,
        },
        verification=verification_conf,
    )
    matcher, matcher_conf, pairs = conf.matcher.name, conf.matcher.options, conf.pairs
    if max_images_held < 2:
        raise ValueError(
            f"max_images_held must be at least 2 (the two images of a pair), got {max_images_held}."
        )
    if matcher == AUTO:
        with dbio.open_database(database_path) as db:
            feature_type = features.database_feature_type(db)
        matcher, _, matcher_conf = resolve_auto(AUTO, AUTO, matcher_conf, feature_type)
    matcher = matcher if isinstance(matcher, Matcher) else get_matcher(matcher, matcher_conf)
    verification_conf = {**matcher.verification_conf, **conf.verification.options}
    options = verify.two_view_options(verification_conf)
    stats = {
        "matcher": matcher.describe(),
        "verification": merge_conf(verify.default_conf, verification_conf, "verification"),
    }
    logger.debug("%s matcher options: %s", matcher.name, matcher.conf)
    with dbio.open_database(database_path) as db:
        dbio.check_image_folder(db, image_path)
        images = dbio.images_with_keypoints(db)
        if len(images) < 2:
            raise ValueError(
                f"The database holds {len(images)} image(s) with "
                "keypoints; at least 2 are needed to match."
            )
        features.check_matcher_features(matcher, features.database_feature_type(db))
        if overwrite:
            dbio.clear_matches(db)
        names = sorted(images)
        start = time.time()
        described: dict[str, np.ndarray] = {}

        def descriptors(ns: list[str]) -> np.ndarray:  # computed once, for retrieval and order
            missing = [n for n in ns if n not in described]
            if missing:
                with scoped_torch_threads(matcher.torch_threads):  # the backbone, as in matching
                    described.update(
                        zip(missing, _global_descriptors(matcher, image_path, missing))
                    )
            return np.stack([described[n] for n in ns])

        selected, mode = select_pairs(pairs.pairs, names, pairs.num_neighbors, descriptors)
        stats["pairs"] = {
            "mode": mode if mode != "file" else str(pairs.pairs),
            "num_neighbors": pairs.num_neighbors if mode in ("retrieval", "sequential") else None,
            "time": time.time() - start,
        }
        id_pairs = [(images[a].image_id, images[b].image_id, a, b) for a, b in selected]
        todo = [p for p in id_pairs if not dbio.pair_has_matches(db, p[0], p[1])]
        logger.info(
            "Matching %d %s pairs with the %s matcher (%d already matched)",
            len(todo),
            mode,
            matcher.name,
            len(id_pairs) - len(todo),
        )
        start, seconds = time.time(), {"read": 0.0, "write": 0.0}
        schedule = None
        if enough is not None and todo:
            schedule = BestFirst(
                db, id_pairs, enough, strong_inliers, options, dict(zip(names, descriptors(names)))
            )
            todo = schedule.order(todo, len(images) <= max_images_held)
        if todo:
            run = get_executor(pairs.executor, matcher, pairs.ray_address, verification_conf)
            try:
                with scoped_torch_threads(matcher.torch_threads):
                    stats["memory"], seconds = _match_pairs(
                        db,
                        image_path,
                        images,
                        todo if schedule else pair_order(todo),
                        matcher,
                        run,
                        max_images_held,
                        schedule,
                    )
            finally:
                run.close()
            stats["executor"] = run.describe()
        stats["match_time"] = time.time() - start
        # most similar first where the order was computed (escalation takes each photo's first)
        stats["selected"] = (
            [key[2:] for key in sorted(id_pairs, key=lambda key: -schedule.similarity[key])]
            if schedule
            else selected
        )
        stats["num_pairs"] = len(id_pairs)
        stats["num_pairs_matched_now"] = len(schedule.started) if schedule else len(todo)
        if schedule is not None:
            stats["deferred"] = {"enough": enough, "strong_inliers": strong_inliers}
            stats["num_pairs_deferred"] = len(schedule.deferred)
            logger.info(
                "%d pairs deferred: both photos already had %d neighbours with %d+ inliers",
                len(schedule.deferred),
                enough,
                strong_inliers,
            )

        start = time.time()
        verify.verify_pairs(db, images, pair_order(id_pairs), options, max_images_held)
        stats["verify_time"] = time.time() - start
        # Where the pairs' time went, in seconds summed over them (the matcher's steps: this
        # process's only).
        stats["profile"] = {
            "read": seconds["read"],
            **matcher.steps,
            "write": seconds["write"],
            "verify": stats["verify_time"],
        }
        stats.update(dbio.database_summary(db))
    logger.info(
        "%d/%d pairs verified, %d inlier matches",
        stats["num_verified_pairs"],
        stats["num_pairs"],
        stats["num_inlier_matches"],
    )
    return stats


def _verified(db, by_id: dict, id_a, id_b, matches, geometry, options) -> tuple:
    """(id_a, id_b, matches, geometry), the geometry computed now where the matcher gave none."""
    if geometry is None:
        with colmap_quiet():
            geometry = verify.verify_pair(
                dbio.read_camera(db, by_id[id_a].camera_id),
                dbio.read_keypoints(db, id_a),
                dbio.read_camera(db, by_id[id_b].camera_id),
                dbio.read_keypoints(db, id_b),
                matches,
                options,
            )
    return id_a, id_b, matches, geometry


def _global_descriptors(matcher: Matcher, image_path: Path, names: list[str]) -> np.ndarray:
    """Retrieval descriptors from the matcher's own backbone (``retrieval_backbone``; else an
    ImageNet backbone)."""
    coarse = matcher.retrieval_backbone()
    if coarse is None:
        from .coarse import CoarseMatcher

        coarse = CoarseMatcher({"mode": "raw", "device": str(matcher.device), "num_threads": None})
    return global_descriptors(coarse, {name: Path(image_path) / name for name in names})


def most_images_held(todo: list[tuple]) -> int:
    """Images held at once when pairs (.., .., name_a, name_b) are matched in this order, each image
    from its first pair to its last."""
    last = {name: i for i, key in enumerate(todo) for name in key[2:]}
    held, most = set(), 0
    for i, key in enumerate(todo):
        held.update(key[2:])
        most = max(most, len(held))
        held.difference_update(name for name in key[2:] if last[name] == i)
    return most


def pair_order(todo: list[tuple]) -> list[tuple]:
    """``todo`` (.., .., name_a, name_b) in the order that holds fewer images at once: as given
    (name order, where a folder per scene keeps a scene together) or grouped along a Cuthill-McKee
    order of the images (breadth first through the pair graph, fewest pairs first), which keeps
    together an archive whose file names say nothing (retrieval pairs of 437 photos under random
    names: 78 images held at once instead of 340)."""
    neighbours: dict[str, set] = defaultdict(set)
    for key in todo:
        neighbours[key[2]].add(key[3])
        neighbours[key[3]].add(key[2])
    position: dict[str, int] = {}
    for seed in sorted(neighbours, key=lambda n: (len(neighbours[n]), n)):
        if seed in position:
            continue
        queue = deque([seed])
        position[seed] = len(position)
        while queue:
            for other in sorted(
                neighbours[queue.popleft()] - position.keys(), key=lambda n: (len(neighbours[n]), n)
            ):
                position[other] = len(position)
                queue.append(other)
    grouped = sorted(todo, key=lambda key: sorted((position[key[2]], position[key[3]])))
    return grouped if most_images_held(grouped) < most_images_held(todo) else list(todo)


class BestFirst:
    """Enough is enough, per photo: pairs are taken most similar first (retrieval descriptors), in
    two passes. The first matches a pair only while both its photos lack ``enough`` neighbours
    verified with ``strong_inliers`` inliers, which spreads the work over every photo; the second
    matches what a photo still lacks, and defers, not matches, a pair once both its photos have
    enough. Matched pairs are verified as they come, so the counts are known. Each decision is the
    one that the results of every pair started before it give (it waits for pairs in flight when
    they could change it), and pairs are written in the order they started: a run is
    deterministic, and a rerun after a kill, counting the pairs in the database, decides as the
    uninterrupted run."""

    def __init__(self, db, id_pairs, enough, strong_inliers, options, descriptors: dict):
        self.enough, self.strong_inliers, self.options = enough, strong_inliers, options
        self.similarity = {
            key: float(descriptors[key[2]] @ descriptors[key[3]]) for key in id_pairs
        }
        self.strong: Counter = Counter()
        self.pending: Counter = Counter()
        inliers = dbio.pair_inlier_counts(db)
        for key in id_pairs:
            if inliers.get((min(key[:2]), max(key[:2])), 0) >= strong_inliers:
                self.strong.update(key[2:])
        self.started: set = set()
        self.deferred: list[PairKey] = []

    def order(self, todo: list[PairKey], by_similarity: bool) -> list[PairKey]:
        """Both passes: most similar first; past ``max_images_held`` images, the memory order of
        ``pair_order`` with each photo's pairs most similar first."""
        if by_similarity:
            ordered = sorted(todo, key=lambda key: -self.similarity[key])
        else:
            ordered, first = pair_order(todo), {}
            for i, key in enumerate(ordered):
                first.setdefault(key[2], i)
            ordered.sort(key=lambda key: (first[key[2]], -self.similarity[key]))
        self.first_pass = len(ordered)
        return ordered + ordered

    def decide(self, position: int, key: PairKey) -> bool | None:
        """Match the pair at ``position`` of ``order``: True; pass over it: False; None: the pairs
        in flight decide it, wait for them."""
        if key in self.started:
            return False
        lacks = max if position < self.first_pass else min  # both photos lack / either does
        have = [self.strong[name] for name in key[2:]]
        match = lacks(have) < self.enough
        if match != (lacks(h + self.pending[n] for h, n in zip(have, key[2:])) < self.enough):
            return None
        if not match and position >= self.first_pass:
            self.deferred.append(key)
        return match

    def start(self, key: PairKey) -> None:
        self.started.add(key)
        self.pending.update(key[2:])

    def finish(self, key: PairKey, num_inliers: int) -> None:
        self.pending.subtract(key[2:])
        if num_inliers >= self.strong_inliers:
            self.strong.update(key[2:])


def _match_pairs(
    db,
    image_path: Path,
    images: dict,
    todo: list[PairKey],
    matcher: Matcher,
    run,
    max_held: int,
    schedule: BestFirst | None = None,
) -> tuple[dict, dict]:
    """Match ``todo`` (id_a, id_b, name_a, name_b) on the executor ``run``; the caller's process is
    the only database writer (one transaction per batch of finished pairs). Images are read (and
    ``matcher.prepare``d: the guided matcher's backbone features) by ``HeldImages``: at most
    ``max_held`` at once.
    With a ``schedule`` pairs it defers are skipped, and the others verified as they are written.
    Returns the most images held at once and the image reads, and the seconds spent reading and
    writing."""
    # unfinished pairs: the matcher's cache is released after the last
    remaining = Counter(name for p in todo for name in p[2:])
    prepare_bar = (
        tqdm(
            desc="prepare",
            total=len(remaining),
            unit="img",
            disable=None,
            dynamic_ncols=True,
            leave=False,
        )
        if matcher.prepares_images
        else None
    )
    seconds = {"read": 0.0, "write": 0.0}

    def load(name: str):
        start = time.perf_counter()
        image = dbio.read_image_data(db, images[name], image_path)
        seconds["read"] += time.perf_counter() - start
        with matcher.timed("prepare"):
            matcher.prepare(image)
        if prepare_bar is not None:
            prepare_bar.update(1)
        return run.put(image)

    held = HeldImages(todo, load, max_held, on_drop=matcher.release)
    started, finished = deque(), {}  # with a schedule: pairs in the order they started
    by_id = {image.image_id: image for image in images.values()}
    with _progress(None, "match", schedule.first_pass if schedule else len(todo)) as bar:

        def write_done() -> None:
            done = run.wait()
            errors = [value for _, value in done if isinstance(value, BaseException)]
            done = [(key, value) for key, value in done if not isinstance(value, BaseException)]
            start = time.perf_counter()
            batch = [(key[0], key[1], *result) for key, result in done]
            if schedule is not None:  # verified now, written in the order they started
                for key, item in zip([key for key, _ in done], batch):
                    finished[key] = _verified(db, by_id, *item, schedule.options)
                    schedule.finish(key, len(finished[key][3].inlier_matches))
                batch = []
                while started and started[0] in finished:
                    batch.append(finished.pop(started.popleft()))
            dbio.write_pairs_matches(db, batch)
            seconds["write"] += time.perf_counter() - start
            bar.update(len(done))
            if errors:  # the finished pairs are written (resumable); the first error stops the run
                raise errors[0]
            for key, _ in done:
                passed(key)

        def passed(key: PairKey) -> None:
            for name in key[2:]:
                remaining[name] -= 1
                if remaining[name] == 0:
                    matcher.release(name)

        for position, key in enumerate(todo):
            while schedule is not None and (need := schedule.decide(position, key)) is None:
                write_done()
            if schedule is not None and not need:
                held.skip(key)
                passed(key)
                continue
            if schedule is not None:
                schedule.start(key)
                started.append(key)
            # an image dropped after its last pair: the pair holds it
            run.submit(key, *held.pair(key))
            while run.in_flight >= run.capacity:
                write_done()
        while run.in_flight:
            write_done()
    if prepare_bar is not None:
        prepare_bar.close()
    memory = {
        "images_held_max": held.most_held,
        "image_reads": held.reads,
        "max_images_held": max_held,
    }
    return memory, seconds
