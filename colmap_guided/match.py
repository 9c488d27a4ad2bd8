"""Stage 3+4: match image pairs into the database and verify them — the drop-in exhaustive_matcher.

Reads the keypoints and descriptors that `colmap feature_extractor` / pycolmap.extract_features
wrote, writes matches and two-view geometries, so that `colmap mapper` or
pycolmap.incremental_mapping run on the database afterwards unchanged. Pairs already matched
(and verified) are skipped: a killed run resumes.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections import Counter, deque
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from . import database as dbio
from . import escalate, features, verify
from .cli import add_pipeline_flags, conf_from_args
from .conf import merge_conf
from .escalate import BestFirst
from .executor import get_executor
from .image_data import MAX_IMAGES_HELD, HeldImages, PairKey, pair_order
from .log import add_verbosity_flags, colmap_quiet, logger, progress
from .matchers.base import Matcher, scoped_torch_threads
from .pairs import (
    global_descriptors,
    load_codebook,
    pair_mode,
    retrieves,
    select_pairs,
    vlad,
    write_pairs,
)
from .pipeline import PipelineConf


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
    join_tries: int = escalate.default_conf["join_tries"],
    orphan_after: int | None = None,
) -> dict:
    """Match the selected pairs and verify them; return statistics for the report.

    ``conf``: the matcher, pairs and verification options (``pipeline.PipelineConf``, default its
    defaults); the keyword options given (not None) go over it. ``pairs_path``: a pairs file or a
    mode of ``pairs.PAIR_MODES`` (auto: exhaustive for small sets, retrieval of ``num_neighbors``
    per image above). ``executor``: 'local' (threads) or 'ray' (a private local Ray instance, or
    the cluster at ``ray_address`` / RAY_ADDRESS). ``max_images_held``: images held in memory at
    once. ``enough``: match the pairs most similar first and defer a pair once both its photos have
    ``enough`` neighbours verified with ``strong_inliers`` (``BestFirst``, groups of photos that no
    strong pair links trying ``join_tries`` pairs to link them, the pairs of a photo whose first
    ``orphan_after`` verified none left unmatched); None: every pair."""
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
    if max_images_held < 2:
        raise ValueError(
            f"max_images_held must be at least 2 (the two images of a pair), got {max_images_held}."
        )
    with dbio.open_database(database_path) as db:
        feature_type = features.database_feature_type(db)
    return match_pairs(
        database_path,
        image_path,
        conf.matcher.resolve(feature_type).build(),
        conf,
        overwrite,
        max_images_held,
        enough,
        strong_inliers,
        join_tries,
        orphan_after=orphan_after,
    )


def match_pairs(
    database_path: Path,
    image_path: Path,
    matcher: Matcher,
    conf: PipelineConf,
    overwrite: bool = False,
    max_images_held: int = MAX_IMAGES_HELD,
    enough: int | None = None,
    strong_inliers: int = 100,
    join_tries: int = escalate.default_conf["join_tries"],
    apart=(),
    orphan_after: int | None = None,
    kept_path: Path | None = None,
) -> dict:
    """``match_database`` with the matcher made: its pairs (``conf.pairs``) and verification
    (``conf.verification`` over the matcher's) as they are, nothing decided again; with
    ``enough``, best first (``BestFirst``), pairs within a group of ``apart`` deferred. The pairs
    whose matches a cheap decision of the matcher kept are appended to ``kept_path``
    (``escalate.record_kept``)."""
    verification_conf = {**matcher.verification_conf, **conf.verification.options}
    options = verify.two_view_options(verification_conf)
    stats = {
        "matcher": matcher.describe(),
        "verification": merge_conf(verify.default_conf, verification_conf, "verification"),
    }
    logger.debug("%s matcher options: %s", matcher.name, matcher.conf)
    with dbio.open_database(database_path) as db:
        images = _images_to_match(db, image_path, matcher, overwrite)
        names = sorted(images)
        selected, mode, stats["pairs"], descriptors = _select(db, image_path, names, matcher, conf)
        id_pairs = [(images[a].image_id, images[b].image_id, a, b) for a, b in selected]
        todo = [p for p in id_pairs if not dbio.pair_has_matches(db, p[0], p[1])]
        done = len(id_pairs) - len(todo)
        log = "Matching %d %s pairs with the %s matcher (%d already matched)"
        logger.info(log, len(todo), mode, matcher.name, done)
        start, seconds, gated = time.time(), {"read": 0.0, "write": 0.0}, 0
        schedule = None
        if enough is not None and todo:
            if descriptors is None:
                descriptors = _global_descriptors(matcher, image_path, names, db)
            descriptors = dict(zip(names, descriptors))
            rule = {"enough": enough, "strong_inliers": strong_inliers}
            rule.update(join_tries=join_tries, orphan_after=orphan_after)
            schedule = BestFirst(db, id_pairs, rule, options, descriptors, apart)
            todo = schedule.order(todo, len(images) <= max_images_held)
        if todo:
            run = get_executor(
                conf.pairs.executor, matcher, conf.pairs.ray_address, verification_conf
            )
            try:
                with scoped_torch_threads(matcher.torch_threads):
                    todo = todo if schedule else pair_order(todo)
                    stats["memory"], seconds, gated = _match_pairs(
                        db,
                        image_path,
                        images,
                        todo,
                        matcher,
                        run,
                        max_images_held,
                        schedule,
                        kept_path,
                    )
            finally:
                run.close()
            stats["executor"] = run.describe()
        stats["match_time"] = time.time() - start
        # most similar first where the order was computed (escalation takes each photo's first)
        stats["selected"] = schedule.escalation_order(id_pairs) if schedule else selected
        # {name: retrieval descriptor} where computed (joining models takes the most similar)
        stats["descriptors"] = (
            dict(zip(names, descriptors)) if isinstance(descriptors, np.ndarray) else descriptors
        )
        stats["num_pairs"] = len(id_pairs)
        # written now; the pairs the matcher's gate left unmatched wait, as deferred ones, for
        # escalation
        stats["num_pairs_matched_now"] = (len(schedule.started) if schedule else len(todo)) - gated
        stats["num_pairs_gated"] = gated
        if schedule is not None:
            stats.update(schedule.describe())

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
        inliers = dbio.pair_inlier_counts(db)
        # of this run's pairs; the summary's counts are the database's
        stats["num_pairs_verified"] = sum(
            inliers.get((min(p[:2]), max(p[:2])), 0) > 0 for p in id_pairs
        )
    counts = [stats[k] for k in ("num_pairs_verified", "num_pairs", "num_inlier_matches")]
    logger.info("%d/%d pairs verified; the database holds %d inlier matches", *counts)
    return stats


def rematch(
    database_path: Path,
    image_path: Path,
    matcher: Matcher,
    conf: PipelineConf,
    todo: list[PairKey],
    pairs_path: Path,
    kept_path: Path | None = None,
) -> dict:
    """The pairs ``todo`` (id_a, id_b, name_a, name_b) matched again with ``matcher`` (escalation's
    full matcher): what they had is deleted (and they leave the record of ``kept_path``), they are
    written to ``pairs_path`` and matched."""
    with dbio.open_database(database_path) as db:
        dbio.delete_pairs(db, [key[:2] for key in todo])
    escalate.forget_kept(kept_path, [key[2:] for key in todo])
    write_pairs(pairs_path, [key[2:] for key in todo])
    pairs = conf.pairs.over({"pairs": str(pairs_path)})
    return match_pairs(database_path, image_path, matcher, dataclasses.replace(conf, pairs=pairs))


def _images_to_match(db, image_path: Path, matcher: Matcher, overwrite: bool) -> dict:
    """{name: image} of the database's images with keypoints, at least 2, of the features the
    matcher takes (their matches cleared first with ``overwrite``)."""
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
    return images


def _select(
    db: pycolmap.Database, image_path: Path, names: list[str], matcher: Matcher, conf: PipelineConf
) -> tuple:
    """The pairs to match (``conf.pairs``), their mode and record for the report, and
    the retrieval descriptors of ``names`` where retrieval computed them."""
    start, pairs = time.time(), conf.pairs
    mode = pair_mode(pairs.pairs, len(names), pairs.num_neighbors)
    descriptors = (
        _global_descriptors(matcher, image_path, names, db)
        if retrieves(mode, len(names), pairs.num_neighbors)
        else None
    )
    selected, mode = select_pairs(pairs.pairs, names, pairs.num_neighbors, descriptors)
    record = {
        "mode": mode if mode != "file" else str(pairs.pairs),
        "num_neighbors": pairs.num_neighbors if mode in ("retrieval", "sequential") else None,
        "time": time.time() - start,
    }
    return selected, mode, record, descriptors


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


def _global_descriptors(
    matcher: Matcher, image_path: Path, names: list[str], db: pycolmap.Database | None = None
) -> np.ndarray:
    """Retrieval descriptors of ``names``: the VLAD of their ALIKED descriptors where ``db`` holds
    ALIKED (``pairs.vlad``), else GeM of the matcher's own backbone (``retrieval_backbone``; else
    an ImageNet backbone) under the matcher's torch threads as in matching."""
    if db is not None and features.database_feature_type(db) == "aliked":
        words, images = load_codebook(), dbio.images_by_name(db)
        return np.stack(
            [vlad(dbio.read_descriptors(db, images[n].image_id)[0], words) for n in names]
        )
    coarse = matcher.retrieval_backbone()
    if coarse is None:
        from .coarse import CoarseMatcher

        coarse = CoarseMatcher({"mode": "raw", "device": str(matcher.device), "num_threads": None})
    with scoped_torch_threads(matcher.torch_threads):
        return global_descriptors(coarse, {name: Path(image_path) / name for name in names})


def _match_pairs(
    db,
    image_path: Path,
    images: dict,
    todo: list[PairKey],
    matcher: Matcher,
    run,
    max_held: int,
    schedule: BestFirst | None = None,
    kept_path: Path | None = None,
) -> tuple[dict, dict, int]:
    """Match ``todo`` (id_a, id_b, name_a, name_b) on the executor ``run``; the caller's process is
    the only database writer (one transaction per batch of finished pairs). Images are read (and
    ``matcher.prepare``d: the guided matcher's backbone features) by ``HeldImages``: at most
    ``max_held`` at once.
    With a ``schedule`` pairs it defers are skipped, and the others verified as they are written.
    Returns the most images held at once and the image reads, the seconds spent reading and
    writing, and how many pairs the matcher left unmatched (not written). Pairs a cheap decision
    kept go to ``kept_path``."""
    pairs = _PairRun(db, image_path, images, todo, matcher, run, schedule)
    # only a matcher with cheap decisions returns a geometry that is not the full matcher's
    pairs.kept_path = kept_path if escalate.keeps_cheaply(matcher) else None
    held = HeldImages(todo, pairs.load, max_held, on_drop=matcher.release)
    total = schedule.first_pass if schedule else len(todo)
    with progress(desc="match", unit="pair", total=total) as pairs.bar:
        for position, key in enumerate(todo):
            while schedule is not None and (need := schedule.decide(position, key)) is None:
                pairs.write_done()
            if schedule is not None and not need:
                held.skip(key)
                pairs.passed(key)
                continue
            if schedule is not None:
                schedule.start(key)
                pairs.started.append(key)
            # an image dropped after its last pair: the pair holds it
            run.submit(key, *held.pair(key))
            while run.in_flight >= run.capacity:
                pairs.write_done()
        while run.in_flight:
            pairs.write_done()
    if pairs.prepare_bar is not None:
        pairs.prepare_bar.close()
    memory = {
        "images_held_max": held.most_held,
        "image_reads": held.reads,
        "max_images_held": max_held,
    }
    return memory, pairs.seconds, pairs.unmatched


class _PairRun:
    """``_match_pairs``' state: images read for the executor, finished pairs written in the order
    they started (with a schedule), each image's matcher cache released after its last pair."""

    def __init__(self, db, image_path, images, todo, matcher, run, schedule):
        self.db, self.image_path, self.images = db, image_path, images
        self.matcher, self.run, self.schedule = matcher, run, schedule
        # unfinished pairs: the matcher's cache is released after the last
        self.remaining = Counter(name for p in todo for name in p[2:])
        self.prepare_bar = (
            tqdm(
                desc="prepare",
                total=len(self.remaining),
                unit="img",
                disable=None,
                dynamic_ncols=True,
                leave=False,
            )
            if matcher.prepares_images
            else None
        )
        self.seconds = {"read": 0.0, "write": 0.0}
        self.unmatched = 0  # pairs the matcher left unmatched (its pair gate)
        self.started, self.finished = deque(), {}  # with a schedule: pairs in start order
        self.by_id = {image.image_id: image for image in images.values()}
        self.bar, self.kept_path = None, None

    def load(self, name: str):
        """One image read and prepared, put where the executor's workers find it."""
        start = time.perf_counter()
        image = dbio.read_image_data(self.db, self.images[name], self.image_path)
        self.seconds["read"] += time.perf_counter() - start
        with self.matcher.timed("prepare"):
            self.matcher.prepare(image)
        if self.prepare_bar is not None:
            self.prepare_bar.update(1)
        return self.run.put(image)

    def write_done(self) -> None:
        """Wait for finished pairs and write them (with a schedule: verified now, in the order they
        started); the first error stops the run once the finished pairs are written."""
        done = self.run.wait()
        errors = [value for _, value in done if isinstance(value, BaseException)]
        done = [(key, value) for key, value in done if not isinstance(value, BaseException)]
        start = time.perf_counter()
        batch = [(key[0], key[1], *result) for key, result in done]
        self.unmatched += sum(item[2] is None for item in batch)
        # recorded before the database holds them: a rerun after a kill matches them as cheaply
        kept = [key[2:] for (key, _), item in zip(done, batch) if item[3] is not None]
        escalate.record_kept(self.kept_path, kept)
        if self.schedule is not None:
            for key, item in zip([key for key, _ in done], batch):
                if item[2] is not None:
                    item = _verified(self.db, self.by_id, *item, self.schedule.options)
                self.finished[key] = item
                self.schedule.finish(key, None if item[2] is None else len(item[3].inlier_matches))
            batch = []
            while self.started and self.started[0] in self.finished:
                batch.append(self.finished.pop(self.started.popleft()))
        # a pair the matcher left unmatched is not written: escalation (or a rerun) takes it
        dbio.write_pairs_matches(self.db, [item for item in batch if item[2] is not None])
        self.seconds["write"] += time.perf_counter() - start
        self.bar.update(len(done))
        if errors:
            raise errors[0]
        for key, _ in done:
            self.passed(key)

    def passed(self, key: PairKey) -> None:
        """The pair is done with: an image whose last pair it was is released."""
        for name in key[2:]:
            self.remaining[name] -= 1
            if self.remaining[name] == 0:
                self.matcher.release(name)


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "match", help="drop-in replacement of COLMAP's exhaustive_matcher on an existing database"
    )
    parser.add_argument("--database_path", type=Path, required=True)
    parser.add_argument("--image_path", type=Path, required=True)
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="delete existing matches and two-view geometries first",
    )
    add_pipeline_flags(parser, reconstruct=False)
    add_verbosity_flags(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    stats = match_database(
        args.database_path, args.image_path, overwrite=args.overwrite, conf=conf_from_args(args)
    )
    print(
        f"{stats['num_pairs_verified']}/{stats['num_pairs']} pairs verified; "
        f"{args.database_path} holds {stats['num_inlier_matches']} inlier matches"
    )
