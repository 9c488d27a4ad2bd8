"""Benchmark of guided learned features (paper §4.4, Table 3): SIFT vs ALIKED, raw vs guided, in one
run.

    python -m recon_scripts.benchmark_aliked [--sets sacre_coeur_hloc phototourism_superglue]
        [--configs sift:guided aliked:raw ...]

Features are extracted once per set and type (time per image, same run), then every config matches a
copy of that database, verifies and maps (``reconstruct``). A config is
FEATURES:MATCHER[:KEY=VALUE,...] with matcher options, e.g.
``aliked:raw:ratio=none,min_similarity=0.9``. Pairs of photos whose names start with different
landmarks (the name up to its first digit, phototourism_superglue's 4 landmarks) are counted as
wrong when they verify. Prints a markdown table; writes JSON.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import tempfile
import time
from pathlib import Path

import colmap_guided  # noqa: F401  (before pycolmap: see colmap_guided/__init__.py)
from colmap_guided import database as dbio
from colmap_guided import features
from colmap_guided.log import set_verbosity
from colmap_guided.paths import shared_data_dir
from colmap_guided.reconstruct import reconstruct
from recon_scripts.evaluation import matcher_specs

DEFAULT_CONFIGS = ["sift:guided", "aliked:raw", "aliked:guided"]


def landmark(name: str) -> str:
    return re.split(r"\d", Path(name).name, maxsplit=1)[0]


def parse_config(text: str) -> tuple[str, str, dict]:
    """FEATURES:SPEC, SPEC a matcher spec of evaluation.matcher_specs (a preset, options over
    it)."""
    kind, _, spec = text.partition(":")
    (spec,) = matcher_specs.parse_specs([spec])
    return kind, spec.name, spec.conf


def wrong_pairs(database_path: Path) -> tuple[int, list]:
    """Verified pairs (with inliers) and those joining different landmarks: [(a, b, inliers)]."""
    with dbio.open_database(database_path) as db:
        names = dbio.image_names(db)
        counts = dbio.pair_inlier_counts(db)
    verified, wrong = 0, []
    for (id_a, id_b), n in counts.items():
        if n > 0:
            verified += 1
            if landmark(names[id_a]) != landmark(names[id_b]):
                wrong.append((names[id_a], names[id_b], int(n)))
    return verified, wrong


def main(argv=None):
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--sets", nargs="+", default=["sacre_coeur_hloc", "phototourism_superglue"])
    parser.add_argument("--configs", nargs="+", default=DEFAULT_CONFIGS)
    parser.add_argument("--output", type=Path, default=Path("outputs/benchmark_aliked.json"))
    parser.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="keep the feature databases here (reruns skip extraction)",
    )
    args = parser.parse_args(argv)
    set_verbosity(quiet=True)
    configs = [parse_config(c) for c in args.configs]
    results, rows = {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.sets:
            image_path = shared_data_dir() / name / "images"
            names = features.list_images(image_path)
            feature_dbs = {}
            for kind in sorted({c[0] for c in configs}):
                db = (args.cache or Path(tmp)) / name / f"features_{kind}" / "database.db"
                db.parent.mkdir(parents=True, exist_ok=True)
                timing = db.parent / "extract_s_per_image.txt"
                if not timing.exists():
                    start = time.time()
                    features.extract_features(db, image_path, names, {"type": kind})
                    timing.write_text(str((time.time() - start) / len(names)))
                feature_dbs[kind] = (db, float(timing.read_text()))
            results[name] = {"extract_s_per_image": {k: v[1] for k, v in feature_dbs.items()}}
            for text, (kind, matcher, conf) in zip(args.configs, configs):
                out = Path(tmp) / name / text.replace(":", "_")
                out.mkdir(parents=True)
                shutil.copy(feature_dbs[kind][0], out / "database.db")
                res = reconstruct(
                    image_path.parent,
                    image_path=image_path,
                    output=out,
                    matcher=matcher,
                    matcher_conf=conf,
                    feature_conf={"type": kind},
                )
                verified, wrong = wrong_pairs(out / "database.db")
                row = {
                    "verified_pairs": verified,
                    "wrong_pairs": wrong,
                    "registered": res["num_registered"],
                    "num_images": res["num_images"],
                    "match_s": res["timings"]["match"],
                    "map_s": res["timings"]["map"],
                    "extract_s_per_image": feature_dbs[kind][1],
                }
                results[name][text] = row
                rows.append((name, text, row))
                print(
                    name,
                    text,
                    {k: v for k, v in row.items() if k != "wrong_pairs"},
                    "wrong:",
                    wrong,
                    flush=True,
                )
    print(
        "\n| set | features:matcher | verified pairs | different-landmark pairs | "
        "registered | extract s/img | match s | map s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, text, r in rows:
        print(
            f"| {name} | {text} | {r['verified_pairs']} | {len(r['wrong_pairs'])} | "
            f"{r['registered']}/{r['num_images']} | {r['extract_s_per_image']:.2f} | "
            f"{r['match_s']:.1f} | {r['map_s']:.1f} |"
        )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
