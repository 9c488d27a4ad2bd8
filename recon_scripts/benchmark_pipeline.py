"""Benchmark: pycolmap's default pipeline vs `reconstruct --matcher M` on the same images, in one run.

    python recon_scripts/benchmark_pipeline.py [--sets sacre_coeur_hloc opensfm_lund ...] [--matchers raw guided]

Prints per set: registered images (largest model), 3D points, wall time per stage, and the time ratio of
each matcher's pipeline to the default one (measured in the same run, same machine). Writes JSON.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

from colmap_guided import features, report
from colmap_guided.database import num_verified_pairs, open_database
from colmap_guided.evaluation.registration import run_pycolmap_default
from colmap_guided.log import set_verbosity
from colmap_guided.paths import shared_data_dir
from colmap_guided.reconstruct import reconstruct

DEFAULT_SETS = ["sacre_coeur_hloc", "sceaux_castle", "opensfm_lund", "phototourism_superglue", "gtsfm_1dsfm_sample", "lund_door_gtsfm", "opensfm_berlin"]


def run_default(image_path: Path, work: Path, camera_mode: str) -> dict:
    """extract_features + match_exhaustive + incremental_mapping with pycolmap's defaults."""
    models, timings = run_pycolmap_default(image_path, work, camera_mode)
    with open_database(work / "database.db") as database:
        verified = num_verified_pairs(database)
    return {"timings": timings, "num_verified_pairs": verified, **report.model_statistics(models, features.list_images(image_path))}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", nargs="+", default=DEFAULT_SETS)
    parser.add_argument("--matchers", nargs="+", default=["raw"])
    parser.add_argument("--camera_mode", default="auto")
    parser.add_argument("--output", type=Path, default=Path("outputs/benchmark_pipeline.json"))
    args = parser.parse_args(argv)
    set_verbosity(quiet=True)
    rows, results = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.sets:
            image_path = shared_data_dir() / name / "images"
            base = run_default(image_path, Path(tmp) / name / "default", args.camera_mode)
            base_time = sum(base["timings"].values())
            results[name] = {"default": base}
            rows.append((name, "pycolmap default", base, base_time, 1.0))
            for matcher in args.matchers:
                res = reconstruct(image_path.parent, image_path=image_path, output=Path(tmp) / name / matcher, matcher=matcher, feature_conf={"camera_mode": args.camera_mode})
                total = sum(res["timings"].values())
                results[name][matcher] = {"timings": res["timings"], "num_verified_pairs": res["database"]["num_verified_pairs"], **res["model"]}
                rows.append((name, matcher, res["model"] | {"num_verified_pairs": res["database"]["num_verified_pairs"]}, total, total / base_time))
            shutil.rmtree(Path(tmp) / name, ignore_errors=True)
    print(f"\nPipeline benchmark, camera_mode={args.camera_mode} (time ratio = total wall time / pycolmap default's, same run)\n")
    print("| set | pipeline | verified pairs | registered | 3D points | reproj. px | total s | time ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for name, label, stats, total, ratio in rows:
        print(f"| {name} | {label} | {stats['num_verified_pairs']} | {stats['num_registered']}/{stats['num_images']} | {stats['num_points3D']} | {stats['mean_reprojection_error']:.2f} | {total:.1f} | {ratio:.2f} |")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(results, indent=2, default=str))


if __name__ == "__main__":
    main()
