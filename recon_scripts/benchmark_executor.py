"""Benchmark: the match stage on the local executor (threads) vs Ray, in one run.

    python -m recon_scripts.benchmark_executor [--set sacre_coeur_hloc] [--pairs exhaustive]
        [--rounds 2] [--ray_address HOST:PORT]

One SIFT extraction; each round matches the same pairs from scratch with ``--executor local`` and
``--executor ray`` (interleaved). Without ``--ray_address`` Ray is a private local instance with one
worker per core, started once before the rounds (its start time is printed apart). Prints match
times, their ratio per round, and checks that both executors wrote the same matches.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import colmap_guided  # noqa: F401  (zlib before pycolmap)
from colmap_guided import database as dbio
from colmap_guided import features
from colmap_guided.log import set_verbosity
from colmap_guided.match import match_database
from colmap_guided.paths import shared_data_dir


def matches(path: Path) -> dict:
    with dbio.open_database(path) as db:
        ims = dbio.images_by_name(db)
        return {
            (a, b): dbio.read_pair_matches(db, ims[a].image_id, ims[b].image_id).tolist()
            for a in ims
            for b in ims
            if a < b and dbio.pair_has_matches(db, ims[a].image_id, ims[b].image_id)
        }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", default="sacre_coeur_hloc")
    parser.add_argument("--pairs", default="exhaustive")
    parser.add_argument("--num_neighbors", type=int, default=10)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--ray_address", default=None)
    args = parser.parse_args(argv)
    set_verbosity(quiet=True)
    import ray

    image_path = shared_data_dir() / args.set / "images"
    start = time.time()
    if args.ray_address is None:
        cores = len(os.sched_getaffinity(0))
        ray.init(
            address="local",
            num_cpus=cores,
            include_dashboard=False,
            log_to_driver=False,
            configure_logging=False,
        )
    else:
        ray.init(address=args.ray_address, log_to_driver=False, configure_logging=False)
    ray_start = time.time() - start
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "base.db"
        features.extract_features(base, image_path, features.list_images(image_path))
        for r in range(args.rounds):
            times, dumps = {}, {}
            for executor in ("local", "ray"):
                db = Path(tmp) / f"{executor}.db"
                shutil.copy(base, db)
                stats = match_database(
                    db,
                    image_path,
                    args.pairs,
                    "guided",
                    num_neighbors=args.num_neighbors,
                    executor=executor,
                )
                times[executor], dumps[executor] = stats["match_time"], matches(db)
                workers = stats["executor"]["workers"]
            rows.append(
                (
                    r,
                    stats["num_pairs"],
                    workers,
                    times["local"],
                    times["ray"],
                    dumps["local"] == dumps["ray"],
                )
            )
    ray.shutdown()
    print(
        f"\nMatch stage, {args.set}, {args.pairs} pairs; Ray started in {ray_start:.1f} s "
        "(not in the times below)\n"
    )
    print("| round | pairs | Ray workers | local s | ray s | ray / local | same matches |")
    print("|---|---|---|---|---|---|---|")
    for r, n, w, lo, ra, same in rows:
        print(f"| {r} | {n} | {w} | {lo:.1f} | {ra:.1f} | {ra / lo:.2f} | {same} |")


if __name__ == "__main__":
    main()
