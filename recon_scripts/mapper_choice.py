"""What can the choice of mapper do? Each finished database of eval_registration runs, mapped again
by each mapper, scored against the reference, and what each way of choosing among those models would
place on the pose.

    python -m recon_scripts.mapper_choice RESULTS/results.json --method guided
        [--baseline PYCOLMAP_RESULTS/results.json]
        [--reference sacre_coeur_hloc=MODEL_DIR]
            [--variant colmap_thresholds:abs_pose_min_num_inliers=30,init_min_num_inliers=100]
            [--json choice.json]

Per (scene, subset, seed) run of METHOD that a reference covers: its database mapped by incremental
and by global mapping (the run's seed, one thread), and by incremental mapping under each
--variant's mapping options; each largest model scored against the reference (photos on / off the
reference pose). Then one row per way of choosing: each model alone, ``auto`` (mapping._auto's rule:
the model check, then the larger model, then the verified inliers its poses explain, then
incremental) and the oracle (the model with the most photos on the pose, then the fewest off it):
photos on / off the pose summed over the runs, and the runs with fewer photos on the pose than
pycolmap's default pipeline of the same seed in RESULTS. The oracle bounds what any choice among
these models can do with this database.
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
from pathlib import Path

import pycolmap

from colmap_guided import mapping
from colmap_guided.log import colmap_quiet
from recon_scripts import script_parser
from recon_scripts.evaluation import registration
from recon_scripts.evaluation.matcher_specs import parse_spec
from recon_scripts.evaluation.tables import markdown_table, write_json
from recon_scripts.summarize_registration import rescore


def map_and_score(
    database: Path,
    scene: dict,
    seed: int,
    conf: dict,
    reference: pycolmap.Reconstruction,
    work: Path,
) -> dict:
    """The database mapped with ``conf`` (seeded, one thread); its largest model scored against the
    reference."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    conf = mapping.check_conf({**conf, "random_seed": seed, "num_threads": 1})
    pycolmap.set_random_seed(seed)
    with colmap_quiet():
        models = mapping._run(conf, database, Path(scene["scene_dir"]) / "images", work)
    largest = registration.largest_model(models)
    images = json.loads((Path(scene["scene_dir"]) / "manifest.json").read_text())["images"]
    score = registration.score_registration(largest, images, reference)
    return {
        "registered": score["num_registered"],
        "correct": score["correct"],
        "wrong": len(score["wrong"] or []),
        "auto_key": list(mapping.auto_key(largest, database)),
    }


def choose(models: dict[str, dict], rule: str) -> dict:
    if rule == "auto":  # incremental first: max keeps the first of equal keys
        return max((models["incremental"], models["global"]), key=lambda m: tuple(m["auto_key"]))
    if rule == "oracle":
        return max(models.values(), key=lambda m: (m["correct"], -m["wrong"]))
    return models[rule]


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument(
        "results", type=Path, help="results.json of an eval_registration run of METHOD"
    )
    parser.add_argument(
        "--baseline",
        type=Path,
        help="results.json with pycolmap's runs of the same scenes (default: RESULTS)",
    )
    parser.add_argument(
        "--method", default="guided", help="the method whose databases are mapped again"
    )
    parser.add_argument(
        "--reference",
        nargs="*",
        default=[],
        help="SCENE_PREFIX=MODEL_DIR: a reference for scenes without one",
    )
    parser.add_argument(
        "--variant",
        nargs="*",
        default=[],
        help="NAME:key=value,...: incremental mapping under these mapping options too",
    )
    parser.add_argument("--json", type=Path, help="write every run's models here")
    args = parser.parse_args(argv)
    refs = {k: pycolmap.Reconstruction(v) for k, _, v in (r.partition("=") for r in args.reference)}
    variants = {
        name: parse_spec(f"x:{options}").conf
        for name, _, options in (v.partition(":") for v in args.variant)
    }
    columns = ["incremental", "global", *variants, "auto", "oracle"]
    baselines = {
        (s["scene"], s["subset"], s.get("seed")): s
        for s in json.loads((args.baseline or args.results).read_text())["scenes"]
    }
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in json.loads(args.results.read_text())["scenes"]:
            base_scene = baselines.get((scene["scene"], scene["subset"], scene.get("seed")), {})
            record, baseline = (
                scene["methods"].get(args.method),
                base_scene.get("methods", {}).get("pycolmap"),
            )
            ref_path = scene.get("reference")
            reference = (
                pycolmap.Reconstruction(ref_path)
                if ref_path
                else next(
                    (r for k, r in refs.items() if scene["scene"] in (k, f"{k}_realistic")), None
                )
            )
            if not record or "error" in record or reference is None:
                continue
            database = (
                registration.seed_runs_dir(scene["scene_dir"], scene.get("seed"))
                / registration.method_slug(args.method)
                / "database.db"
            )
            confs = {
                "incremental": {"mapper": "incremental"},
                "global": {"mapper": "global"},
                **{n: {"mapper": "incremental", **c} for n, c in variants.items()},
            }
            models = {
                name: map_and_score(
                    database, scene, scene.get("seed") or 0, conf, reference, Path(tmp) / name
                )
                for name, conf in confs.items()
            }
            if baseline and "error" not in baseline and baseline.get("correct") is None:
                baseline = rescore(baseline, base_scene, "pycolmap", reference)
            runs.append(
                {
                    "scene": scene["scene"],
                    "subset": scene["subset"],
                    "seed": scene.get("seed"),
                    "models": models,
                    "pycolmap": baseline.get("correct")
                    if baseline and "error" not in baseline
                    else None,
                }
            )
    for subset, title in (
        ("historical", "historical photos + distractors"),
        ("all", "historical + modern photos + distractors"),
    ):
        chosen = [r for r in runs if r["subset"] == subset]
        if not chosen:
            continue
        rows = []
        for rule in columns:
            picks = [(r, choose(r["models"], rule)) for r in chosen]
            below = [
                f"{r['scene']} s{r['seed']} {m['correct']}<{r['pycolmap']}"
                for r, m in picks
                if r["pycolmap"] is not None and m["correct"] < r["pycolmap"]
            ]
            rows.append(
                [
                    rule,
                    sum(m["correct"] for _, m in picks),
                    sum(m["wrong"] for _, m in picks),
                    f"{len(below)} of {len(picks)}" + (f" ({'; '.join(below)})" if below else ""),
                ]
            )
        print(
            f"\n**{args.method}, {title}** — photos on the reference pose ✓ / off it ✗ summed "
            f"over {len(chosen)} runs; runs below pycolmap's default pipeline (same seed)\n"
        )
        print(markdown_table(["models chosen by", "✓", "✗", "runs below pycolmap"], rows))
    if args.json:
        write_json(args.json, runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
