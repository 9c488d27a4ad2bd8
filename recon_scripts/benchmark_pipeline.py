"""Benchmark: pycolmap's default pipeline vs `reconstruct` (matcher x mapper x seed) on the same
images, in one run.

    python -m recon_scripts.benchmark_pipeline [--sets sacre_coeur_hloc opensfm_lund ...]
        [--matchers raw guided guided:raw_matches=none]
        [--mappers incremental global] [--seeds 0 1]

Per set and seed round: pycolmap's default pipeline (extract_features + match_exhaustive +
incremental_mapping, default options, unseeded: its own run-to-run spread), the same database mapped
by each --mapper (seeded), and each matcher's `reconstruct`: matched once, then mapped by each
mapper with each seed (matching and verification are deterministic, so the database is shared).
Prints registered images (largest model), images whose pose agrees with the set's reference model
(where it has one: lund_door_gtsfm), the model check, 3D points and the time ratio to the default
pipeline of the same round (extract + match + verify + that mapping). Writes JSON.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

from colmap_guided import features, model_check, report
from colmap_guided.database import num_verified_pairs, open_database
from colmap_guided.log import set_verbosity
from colmap_guided.mapping import MAPPERS, load_models, run_mapping
from colmap_guided.paths import shared_data_dir
from colmap_guided.pipeline import PipelineConf
from colmap_guided.reconstruct import reconstruct
from recon_scripts.evaluation import matcher_specs
from recon_scripts.evaluation.reference import load_colmap_model, reference_model_dir
from recon_scripts.evaluation.registration import (
    method_slug,
    run_pycolmap_default,
    score_registration,
    split_stage_options,
)

DEFAULT_SETS = [
    "sacre_coeur_hloc",
    "sceaux_castle",
    "opensfm_lund",
    "phototourism_superglue",
    "gtsfm_1dsfm_sample",
    "lund_door_gtsfm",
    "opensfm_berlin",
]


def summarize(
    models: dict, image_names: list[str], reference, timings: dict, verified: int
) -> dict:
    stats = report.model_statistics(models, image_names)
    largest = max(models.values(), key=lambda rec: rec.num_reg_images(), default=None)
    score = (
        score_registration(largest, [{"name": n, "era": "modern"} for n in image_names], reference)
        if reference
        else {}
    )
    checked = model_check.check_models(models)
    return {
        "timings": timings,
        "num_verified_pairs": verified,
        "correct": score.get("correct"),
        "wrong": score.get("wrong"),
        "model_check": checked,
        **stats,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sets", nargs="+", default=DEFAULT_SETS)
    parser.add_argument(
        "--matchers",
        nargs="+",
        default=["guided"],
        help="matcher specs, e.g. guided guided:raw_matches=none "
        "raw guided:type=aliked (feature options go to extraction)",
    )
    parser.add_argument("--mappers", nargs="+", default=["incremental", "global"], choices=MAPPERS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument(
        "--threads",
        type=int,
        default=-1,
        help="mapping threads (1: each seeded run repeats exactly)",
    )
    parser.add_argument("--camera_mode", default="auto")
    parser.add_argument(
        "--peer",
        default="lightglue",
        help="the matcher spec of --matchers the others' times are also divided by",
    )
    parser.add_argument("--output", type=Path, default=Path("outputs/benchmark_pipeline.json"))
    args = parser.parse_args(argv)
    set_verbosity(quiet=True)
    # (label, matcher spec, feature options): 'guided:type=aliked' = guided matching of ALIKED
    # features; unknown options: the matcher raises
    specs = []
    for text in args.matchers:
        matcher, feature_conf, _, escalation = split_stage_options(text)
        specs.append((text, matcher_specs.parse_spec(matcher), feature_conf, escalation))
    rows, results = [], {}

    def add(name, seed, label, stats, base_time):
        total = sum(stats["timings"].values())
        rows.append((name, seed, label, stats, total, total / base_time))
        results.setdefault(name, {}).setdefault(str(seed), {})[label] = stats
        print(row_markdown(rows[-1]), flush=True)  # as it comes: a run stopped early keeps its rows
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(results, indent=2, default=str))

    with tempfile.TemporaryDirectory() as tmp:
        for name in args.sets:
            image_path = shared_data_dir() / name / "images"
            names = features.list_images(image_path)
            ref_dir = reference_model_dir(name)
            reference = load_colmap_model(ref_dir) if ref_dir else None
            work = Path(tmp) / name
            base_times = {}
            for seed in args.seeds:
                models, timings = run_pycolmap_default(
                    image_path, work / f"default_{seed}", args.camera_mode
                )
                with open_database(work / f"default_{seed}" / "database.db") as database:
                    verified = num_verified_pairs(database)
                base_times[seed] = sum(timings.values())
                add(
                    name,
                    seed,
                    "pycolmap default",
                    summarize(models, names, reference, timings, verified),
                    base_times[seed],
                )
                for mapper in args.mappers:  # pycolmap's database, our mapping
                    start = time.time()
                    models = run_mapping(
                        work / f"default_{seed}" / "database.db",
                        image_path,
                        work / f"default_{seed}" / mapper,
                        {"mapper": mapper, "random_seed": seed, "num_threads": args.threads},
                    )
                    t = {
                        **{k: v for k, v in timings.items() if k != "map"},
                        "map": time.time() - start,
                    }
                    add(
                        name,
                        seed,
                        f"pycolmap matching + {mapper}",
                        summarize(models, names, reference, t, verified),
                        base_times[seed],
                    )
            for label, spec, feature_conf, escalation in specs:
                out = work / method_slug(label)
                first = {
                    "mapper": args.mappers[0],
                    "random_seed": args.seeds[0],
                    "num_threads": args.threads,
                }
                res = reconstruct(
                    image_path.parent,
                    conf=PipelineConf.from_dict({"escalation": escalation}),
                    image_path=image_path,
                    output=out,
                    matcher=matcher_specs.build(spec),
                    feature_conf={"camera_mode": args.camera_mode, **feature_conf},
                    mapping_conf=first,
                )
                verified = res["database"]["num_verified_pairs"]
                # Where the run's time went: stages, and within matching the read / coarse / fine /
                # write steps.
                profile = {
                    "extract": res["timings"]["extract"],
                    **res["database"]["profile"],
                    **{k: v for k, v in res["timings"].items() if k in ("map",) or "escalate" in k},
                }
                results.setdefault(name, {}).setdefault("profile", {})[label] = profile
                print(
                    f"{name} {label}, {res['database']['num_pairs']} pairs: "
                    + ", ".join(f"{k} {v:.1f} s" for k, v in profile.items()),
                    flush=True,
                )
                for seed in args.seeds:
                    for mapper in args.mappers:
                        if (mapper, seed) == (args.mappers[0], args.seeds[0]):
                            models, timings = load_models(out / "sparse"), res["timings"]
                        else:
                            start = time.time()
                            models = run_mapping(
                                out / "database.db",
                                image_path,
                                out / f"sparse_{mapper}_{seed}",
                                {
                                    "mapper": mapper,
                                    "random_seed": seed,
                                    "num_threads": args.threads,
                                },
                            )
                            timings = {**res["timings"], "map": time.time() - start}
                        add(
                            name,
                            seed,
                            f"{label} + {mapper}",
                            summarize(models, names, reference, timings, verified),
                            base_times[seed],
                        )
            shutil.rmtree(work, ignore_errors=True)
    print(
        f"\nPipeline benchmark, camera_mode={args.camera_mode}, mapping threads {args.threads} "
        "(time ratio = total wall time / pycolmap default's, same set and seed round)\n"
    )
    print(
        "| set | seed | pipeline | verified pairs | registered | "
        "correct (reference) | model check | 3D points | total s | time ratio |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(row_markdown(row) for row in rows))
    print("\n".join(peer_ratios(rows, f"{args.peer} + {args.mappers[0]}", args.seeds[0])))
    print("\n".join(summed(rows)))


def summed(rows: list[tuple]) -> list[str]:
    """Each pipeline over every set (seed rounds averaged): photos registered, on the reference
    pose where a set has one, wall time, and its ratio to pycolmap's default summed the same way;
    the largest per-set ratio beside it."""
    by = {}
    for name, _, label, stats, total, ratio in rows:
        entry = by.setdefault(
            label, {"sets": set(), "n": 0, "reg": 0, "ok": 0, "s": 0.0, "max": 0.0}
        )
        entry["sets"].add(name)
        entry["n"] += 1
        entry["reg"] += stats["num_registered"]
        entry["ok"] += stats["correct"] or 0
        entry["s"] += total
        entry["max"] = max(entry["max"], ratio)
    base = by.get("pycolmap default")
    lines = [
        "\nSummed over the sets\n",
        "| pipeline | sets | registered | on the reference pose | total s | ratio to pycolmap | "
        "largest set ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, e in by.items():
        ratio = e["s"] / base["s"] if base else float("nan")
        lines.append(
            f"| {label} | {len(e['sets'])} | {e['reg']} | {e['ok']} | {e['s']:.1f} | "
            f"{ratio:.2f} | {e['max']:.2f} |"
        )
    return lines


def peer_ratios(rows: list[tuple], peer: str, seed: int) -> list[str]:
    """Per set, each pipeline's end-to-end and match-stage (matching + verification) time over
    ``peer``'s, first mapper and seed; nothing where ``peer`` did not run."""

    def stage(stats):
        return stats["timings"].get("match", 0.0) + stats["timings"].get("verify", 0.0)

    first = {(row[0], row[2]): row for row in rows if row[1] == seed}
    lines = [
        f"\nTimes over {peer}'s, same set and round\n",
        "| set | pipeline | total s | total ratio | match + verify s | match ratio |",
        "|---|---|---|---|---|---|",
    ]
    for (name, label), row in first.items():
        base = first.get((name, peer))
        if base is not None:
            lines.append(
                f"| {name} | {label} | {row[4]:.1f} | {row[4] / base[4]:.2f} | "
                f"{stage(row[3]):.1f} | {stage(row[3]) / max(stage(base[3]), 1e-9):.2f} |"
            )
    return lines if len(lines) > 3 else []


def row_markdown(row: tuple) -> str:
    name, seed, label, stats, total, ratio = row
    correct = "–" if stats["correct"] is None else f"{stats['correct']}"
    check = (
        "ok"
        if stats["model_check"]["ok"]
        else f"{len(stats['model_check']['problems'])} problem(s)"
    )
    return (
        f"| {name} | {seed} | {label} | {stats['num_verified_pairs']} | "
        f"{stats['num_registered']}/{stats['num_images']} | {correct} | "
        f"{check} | {stats['num_points3D']} | {total:.1f} | {ratio:.2f} |"
    )


if __name__ == "__main__":
    main()
