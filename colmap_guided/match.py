"""Stage 3+4: match image pairs into the database and verify them — the drop-in exhaustive_matcher.

Reads the keypoints and descriptors that `colmap feature_extractor` / pycolmap.extract_features wrote,
writes matches and two-view geometries, so that `colmap mapper` or pycolmap.incremental_mapping run on
the database afterwards unchanged. Pairs already matched (and verified) are skipped: a killed run resumes.
"""

from __future__ import annotations

import argparse
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import database as dbio
from . import verify
from .log import colmap_quiet, logger
from .matchers import MATCHERS, get_matcher
from .matchers.base import ImageData, Matcher, scoped_torch_threads
from .pairs import exhaustive_pairs, read_pairs

def _progress(iterable, desc: str, total: int):
    return tqdm(iterable, desc=desc, total=total, unit="pair", disable=None, dynamic_ncols=True, leave=False)


def match_database(
    database_path: Path,
    image_path: Path,
    pairs_path: Path | None = None,
    matcher: str | Matcher = "raw",
    matcher_conf: dict | None = None,
    verification_conf: dict | None = None,
    overwrite: bool = False,
) -> dict:
    """Match (exhaustively, or the pairs of ``pairs_path``) and verify; return statistics for the report."""
    matcher = matcher if isinstance(matcher, Matcher) else get_matcher(matcher, matcher_conf)
    verification_conf = {**matcher.verification_conf, **(verification_conf or {})}
    options = verify.two_view_options(verification_conf)
    stats = {"matcher": matcher.describe(), "verification": {**verify.default_conf, **verification_conf}}
    with dbio.open_database(database_path) as db:
        dbio.check_image_folder(db, image_path)
        images = {name: image for name, image in dbio.images_by_name(db).items() if db.exists_keypoints(image.image_id)}
        if len(images) < 2:
            raise ValueError(f"The database holds {len(images)} image(s) with keypoints; at least 2 are needed to match.")
        if overwrite:
            dbio.clear_matches(db)
        names = sorted(images)
        pairs = read_pairs(pairs_path, names) if pairs_path else exhaustive_pairs(names)
        id_pairs = [(images[a].image_id, images[b].image_id, a, b) for a, b in pairs]

        cache: dict[str, ImageData] = {}
        last_use = {}
        for index, (_, _, a, b) in enumerate(id_pairs):
            last_use[a] = last_use[b] = index

        todo = [p for p in id_pairs if not dbio.pair_has_matches(db, p[0], p[1])]
        logger.info("Matching %d pairs with the %s matcher (%d already matched)", len(todo), matcher.name, len(id_pairs) - len(todo))
        start = time.time()
        todo_index = {(p[0], p[1]) for p in todo}
        # Matchers with a backbone (guided) compute an image's features at its first pair: a bar of its own.
        backbone = getattr(matcher, "features", None)
        num_todo_images = len({name for p in todo for name in p[2:]})
        backbone_bar = tqdm(desc="backbone", total=num_todo_images, unit="img", disable=None, dynamic_ncols=True, leave=False) if callable(backbone) and todo else None

        def load(name: str) -> ImageData:
            if name not in cache:
                cache[name] = dbio.read_image_data(db, images[name], image_path)
                if backbone_bar is not None:
                    backbone(cache[name])
                    backbone_bar.update(1)
            return cache[name]

        # Pairs are matched by ``matcher.pair_workers`` threads (torch releases the GIL), in order, at most
        # two per worker ahead of the database writes; an image's cache is dropped once its last pair is written.
        pending: deque = deque()

        def write_done(limit: int) -> None:
            while len(pending) > limit:
                index, id_a, id_b, a, b, future = pending.popleft()
                if future is not None:
                    dbio.write_pair_matches(db, id_a, id_b, future.result())
                    bar.update(1)
                for name in (a, b):
                    if last_use[name] == index:
                        cache.pop(name, None)
                        matcher.release(name)

        workers = max(1, int(matcher.pair_workers))
        with scoped_torch_threads(matcher.torch_threads), _progress(None, "match", len(todo)) as bar, ThreadPoolExecutor(workers) as pool:
            try:
                for index, (id_a, id_b, a, b) in enumerate(id_pairs):
                    future = pool.submit(matcher.match, load(a), load(b)) if (id_a, id_b) in todo_index else None
                    pending.append((index, id_a, id_b, a, b, future))
                    write_done(2 * workers)
                write_done(0)
            except BaseException:  # stop the queued pairs; the written ones stay (resumable)
                for *_, future in pending:
                    if future is not None:
                        future.cancel()
                raise
        if backbone_bar is not None:
            backbone_bar.close()
        stats["match_time"] = time.time() - start
        stats["num_pairs"] = len(id_pairs)
        stats["num_pairs_matched_now"] = len(todo)

        start = time.time()
        verify_pairs(db, images, id_pairs, options)
        stats["verify_time"] = time.time() - start
        stats.update(dbio.database_summary(db))
    logger.info(
        "%d/%d pairs verified, %d inlier matches", stats["num_verified_pairs"], stats["num_pairs"], stats["num_inlier_matches"]
    )
    return stats


def verify_pairs(db, images: dict, id_pairs: list[tuple[int, int, str, str]], options) -> int:
    """Two-view geometry of every matched, not yet verified pair (id_a, id_b, name_a, name_b); returns how many."""
    unverified = [p for p in id_pairs if dbio.pair_has_matches(db, p[0], p[1]) and not dbio.pair_is_verified(db, p[0], p[1])]
    cameras, keypoints = {}, {}  # read once per camera / image, not once per pair
    with colmap_quiet():
        for id_a, id_b, a, b in _progress(unverified, "verify", len(unverified)):
            for name in (a, b):
                image = images[name]
                if image.camera_id not in cameras:
                    cameras[image.camera_id] = db.read_camera(image.camera_id)
                if name not in keypoints:
                    keypoints[name] = np.asarray(db.read_keypoints(image.image_id), np.float32)
            matches = dbio.read_pair_matches(db, id_a, id_b)
            geometry = verify.verify_pair(cameras[images[a].camera_id], keypoints[a], cameras[images[b].camera_id], keypoints[b], matches, options)
            dbio.write_pair_geometry(db, id_a, id_b, geometry)
    return len(unverified)


def add_matcher_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--matcher", default=None, choices=sorted(MATCHERS), help="raw: mutual NN + ratio; guided: paper eq. 1 (default)")
    parser.add_argument("--ratio", type=float, default=None, help="Lowe ratio threshold (0 disables)")
    parser.add_argument("--pairs", type=Path, default=None, help="pairs file (name_a name_b per line); exhaustive if omitted")
    parser.add_argument("--weights", type=Path, default=None, help="coarse filter weights (guided matcher)")
    parser.add_argument("--device", default=None, help="torch device for matching (cpu, cuda)")


def matcher_conf_from_args(args, matcher: str) -> dict:
    """The command-line options that the chosen matcher knows; an option it does not know is an error."""
    given = {"ratio": None if args.ratio is None else (args.ratio if args.ratio > 0 else None), "device": args.device, "weights": args.weights}
    given = {k: (str(v) if isinstance(v, Path) else v) for k, v in given.items() if getattr(args, k) is not None}
    known = MATCHERS[matcher].default_conf
    unknown = sorted(set(given) - set(known))
    if unknown:
        raise SystemExit(f"error: --{unknown[0]} does not apply to the {matcher} matcher")
    return given
