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
from recon_scripts.summarize_registration import (
    PROTOCOLS,
    add_reference_flag,
    load_references,
    reference_for,
    rescore,
)


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
    """The model that ``rule`` picks among one run's models."""
    if rule == "auto":  # incremental first: max keeps the first of equal keys
        return max((models["incremental"], models["global"]), key=lambda m: tuple(m["auto_key"]))
    if rule == "oracle":
        return max(models.values(), key=lambda m: (m["correct"], -m["wrong"]))
    return models[rule]


def _parser():
    """The command line."""
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
    add_reference_flag(parser)
    parser.add_argument(
        "--variant",
        nargs="*",
        default=[],
        help="NAME:key=value,...: incremental mapping under these mapping options too",
    )
    parser.add_argument("--json", type=Path, help="write every run's models here")
    return parser


def load_variants(specs: list[str]) -> dict[str, dict]:
    """``--variant`` values as {name: mapping options}."""
    return {
        name: parse_spec(f"x:{options}").conf
        for name, _, options in (v.partition(":") for v in specs)
    }


def remap_run(
    scene: dict, base_scene: dict, method: str, variants: dict, refs: dict, tmp: Path
) -> dict | None:
    """One run's database remapped by each mapper and scored beside pycolmap; None if unscored."""
    record = scene["methods"].get(method)
    baseline = base_scene.get("methods", {}).get("pycolmap")
    ref_path = scene.get("reference")
    reference = (
        pycolmap.Reconstruction(ref_path) if ref_path else reference_for(scene["scene"], refs)
    )
    if not record or "error" in record or reference is None:
        return None
    database = (
        registration.seed_runs_dir(scene["scene_dir"], scene.get("seed"))
        / registration.method_slug(method)
        / "database.db"
    )
    confs = {
        "incremental": {"mapper": "incremental"},
        "global": {"mapper": "global"},
        **{n: {"mapper": "incremental", **c} for n, c in variants.items()},
    }
    models = {
        name: map_and_score(database, scene, scene.get("seed") or 0, conf, reference, tmp / name)
        for name, conf in confs.items()
    }
    if baseline and "error" not in baseline and baseline.get("correct") is None:
        baseline = rescore(baseline, base_scene, "pycolmap", reference)
    return {
        "scene": scene["scene"],
        "subset": scene["subset"],
        "seed": scene.get("seed"),
        "models": models,
        "pycolmap": baseline.get("correct") if baseline and "error" not in baseline else None,
    }


def remap_runs(results: Path, baseline: Path | None, method: str, variants: dict, refs: dict):
    """``remap_run`` of every run in ``results``, pycolmap's runs from ``baseline``."""
    baselines = {
        (s["scene"], s["subset"], s.get("seed")): s
        for s in json.loads((baseline or results).read_text())["scenes"]
    }
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in json.loads(results.read_text())["scenes"]:
            base_scene = baselines.get((scene["scene"], scene["subset"], scene.get("seed")), {})
            run = remap_run(scene, base_scene, method, variants, refs, Path(tmp))
            if run is not None:
                runs.append(run)
    return runs


def choice_rows(runs: list[dict], rules: list[str]) -> list[list]:
    """A row per way of choosing: photos on / off the pose, and the runs below pycolmap."""
    rows = []
    for rule in rules:
        picks = [(r, choose(r["models"], rule)) for r in runs]
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
    return rows


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    refs = load_references(args.reference)
    variants = load_variants(args.variant)
    runs = remap_runs(args.results, args.baseline, args.method, variants, refs)
    for subset, title in PROTOCOLS:
        chosen = [r for r in runs if r["subset"] == subset]
        if not chosen:
            continue
        print(
            f"\n**{args.method}, {title}** — photos on the reference pose ✓ / off it ✗ summed "
            f"over {len(chosen)} runs; runs below pycolmap's default pipeline (same seed)\n"
        )
        rows = choice_rows(chosen, ["incremental", "global", *variants, "auto", "oracle"])
        print(markdown_table(["models chosen by", "✓", "✗", "runs below pycolmap"], rows))
    if args.json:
        write_json(args.json, runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
