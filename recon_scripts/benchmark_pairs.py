"""Benchmark: pair selection (exhaustive vs retrieval at several k, optionally sequential) end to
end.

    python -m recon_scripts.benchmark_pairs [--sets sacre_coeur_hloc opensfm_lund ...] [--k 5 10]
        [--matcher guided]

One SIFT extraction per set; for each pair selection the matches are cleared, matched, verified and
mapped again (same keypoints). Prints per set and selection: pairs matched (fraction of exhaustive),
verified pairs, exhaustive's verified pairs that the selection kept (recall), registered images of
the largest model, and the match + verify time as a ratio of exhaustive's (same run). A set is a
folder of ../shared/data with images/, or ``train/SCENE``. Writes JSON.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import colmap_guided  # noqa: F401  (zlib before pycolmap)
from colmap_guided import database as dbio
from colmap_guided import features, mapping, report
from colmap_guided.log import set_verbosity
from colmap_guided.match import match_database
from colmap_guided.matchers import get_matcher
from colmap_guided.paths import shared_data_dir


def verified_pairs(database_path: Path) -> set[tuple[str, str]]:
    with dbio.open_database(database_path) as db:
        names = dbio.image_names(db)
        return {
            tuple(sorted((names[a], names[b])))
            for (a, b), n in dbio.pair_inlier_counts(db).items()
            if n > 0
        }


def main(argv=None):
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument(
        "--sets", nargs="+", default=["sacre_coeur_hloc", "phototourism_superglue", "opensfm_lund"]
    )
    parser.add_argument("--k", type=int, nargs="+", default=[3, 5, 10])
    parser.add_argument("--sequential", action="store_true", help="also sequential pairs at each k")
    parser.add_argument("--matcher", default="guided")
    parser.add_argument("--camera_mode", default="auto")
    parser.add_argument(
        "--no_exhaustive",
        action="store_true",
        help="skip exhaustive (large sets): recall and time ratio left out",
    )
    parser.add_argument("--output", type=Path, default=Path("outputs/benchmark_pairs.json"))
    args = parser.parse_args(argv)
    set_verbosity(quiet=True)
    matcher = get_matcher(args.matcher)
    selections = (
        ([] if args.no_exhaustive else [("exhaustive", None)])
        + [("retrieval", k) for k in args.k]
        + ([("sequential", k) for k in args.k] if args.sequential else [])
    )
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.sets:
            image_path = shared_data_dir() / name / "images"
            names = features.list_images(image_path)
            base = Path(tmp) / name / "base.db"
            base.parent.mkdir(parents=True)
            features.extract_features(base, image_path, names, {"camera_mode": args.camera_mode})
            results[name] = {}
            for mode, k in selections:
                db = Path(tmp) / name / f"{mode}_{k}.db"
                shutil.copy(base, db)
                start = time.time()
                stats = match_database(db, image_path, mode, matcher, num_neighbors=k or 1)
                elapsed = time.time() - start
                models = mapping.run_mapping(
                    db,
                    image_path,
                    Path(tmp) / name / f"sparse_{mode}_{k}",
                    {"mapper": "incremental"},
                )
                model = report.model_statistics(models, names)
                results[name][f"{mode}" + (f" k={k}" if k else "")] = {
                    "num_images": len(names),
                    "num_pairs": stats["num_pairs"],
                    "num_verified_pairs": stats["num_verified_pairs"],
                    "verified": sorted(verified_pairs(db)),
                    "num_registered": model["num_registered"],
                    "num_points3D": model["num_points3D"],
                    "time": elapsed,
                    "select_time": stats["pairs"]["time"],
                }
            shutil.rmtree(Path(tmp) / name, ignore_errors=True)
    print(
        f"\nPair selection, {args.matcher} matcher, camera_mode={args.camera_mode} "
        "(time = select + match + verify, ratio to exhaustive's in the same run)\n"
    )
    print(
        "| set | pairs | pairs (of exhaustive) | verified | "
        "exhaustive's verified kept | registered | 3D points | time ratio |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, rows in results.items():
        ex = rows.get("exhaustive")
        for label, r in rows.items():
            n = r["num_images"]
            kept = (
                f"{len(set(map(tuple, r['verified'])) & set(map(tuple, ex['verified'])))}"
                f"/{len(ex['verified'])}"
                if ex
                else "–"
            )
            ratio = f"{r['time'] / ex['time']:.2f}" if ex else "–"
            print(
                f"| {name} | {label} | {r['num_pairs']} ({r['num_pairs'] / (n * (n - 1) / 2):.0%}) "
                f"| {r['num_verified_pairs']} | {kept} | {r['num_registered']}/{n} "
                f"| {r['num_points3D']} | {ratio} |"
            )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
