"""pycolmap's default pipeline vs `reconstruct` (matcher x mapper x seed) on the same images.

    python -m recon_scripts pipeline [sets="sacre_coeur_hloc opensfm_lund ..."]
        [methods="raw guided guided:raw_matches=none"]
        [mappers="incremental global"] [seeds="0 1"]

Per set and seed round: pycolmap's default pipeline (extract_features + match_exhaustive +
incremental_mapping, default options, unseeded: its own run-to-run spread), the same database mapped
by each mapper (seeded), and each matcher's `reconstruct`: matched once, then mapped by each
mapper with each seed (matching and verification are deterministic, so the database is shared).
Prints registered images (largest model), images whose pose agrees with the set's reference model
(where it has one: lund_door_gtsfm), the model check, 3D points and the time ratio to the default
pipeline of the same round (extract + match + verify + that mapping). Matcher specs: e.g. guided
guided:raw_matches=none raw guided:type=aliked (feature options go to extraction).
"""

from __future__ import annotations

import time

from colmap_guided import features, model_check, report
from colmap_guided.database import num_verified_pairs, open_database
from colmap_guided.mapping import load_models, run_mapping
from colmap_guided.pipeline import PipelineConf
from colmap_guided.reconstruct import reconstruct
from recon_scripts.bench import Benchmark
from recon_scripts.evaluation import matcher_specs
from recon_scripts.evaluation.reference import load_colmap_model, reference_model_dir
from recon_scripts.evaluation.registration import (
    run_pycolmap_default,
    score_registration,
    split_stage_options,
)

DEFAULT = "pycolmap default"


def summarize_model(models, image_names, reference, timings, verified) -> dict:
    stats = report.model_statistics(models, image_names)
    largest = max(models.values(), key=lambda rec: rec.num_reg_images(), default=None)
    modern = [{"name": n, "era": "modern"} for n in image_names]
    score = score_registration(largest, modern, reference) if reference else {}
    return {
        "timings": timings,
        "num_verified_pairs": verified,
        "correct": score.get("correct"),
        "wrong": score.get("wrong"),
        "model_check": model_check.check_models(models),
        **stats,
    }


class PipelineBenchmark(Benchmark):
    name = "pipeline"
    default_conf = {
        "sets": [
            *("sacre_coeur_hloc", "sceaux_castle", "opensfm_lund", "phototourism_superglue"),
            *("gtsfm_1dsfm_sample", "lund_door_gtsfm", "opensfm_berlin"),
        ],
        "methods": ["guided"],
        "mappers": ["incremental", "global"],
        "seeds": [0],
        "threads": -1,  # mapping threads (1: each seeded run repeats exactly)
        "camera_mode": "auto",
        "peer": "lightglue",  # the matcher spec the others' times are also divided by
    }

    def configs(self):
        c = self.conf
        mapping = {
            "mappers": c["mappers"],
            "threads": c["threads"],
            "camera_mode": c["camera_mode"],
        }
        configs = {f"{DEFAULT} seed={s}": {"seeds": [s], **mapping} for s in c["seeds"]}
        return configs | {m: {"matcher": m, "seeds": c["seeds"], **mapping} for m in c["methods"]}

    def prepare(self, name, image_path, work):
        ref_dir = reference_model_dir(name)
        return {
            "names": features.list_images(image_path),
            "reference": load_colmap_model(ref_dir) if ref_dir else None,
        }

    def map(self, db, image_path, out, mapper, seed, threads):
        start = time.time()
        conf = {"mapper": mapper, "random_seed": seed, "num_threads": threads}
        return run_mapping(db, image_path, out, conf), time.time() - start

    def run_config(self, name, image_path, prepared, label, config, out):
        """{"rows": [[seed, pipeline, stats]], "profile": where a matcher's time went}."""
        names, reference = prepared["names"], prepared["reference"]
        rows = []

        def add(seed, pipeline, models, timings, verified):
            stats = summarize_model(models, names, reference, timings, verified)
            rows.append([seed, pipeline, stats])

        if "matcher" not in config:
            (seed,) = config["seeds"]
            models, timings = run_pycolmap_default(image_path, out, config["camera_mode"])
            with open_database(out / "database.db") as database:
                verified = num_verified_pairs(database)
            add(seed, DEFAULT, models, timings, verified)
            for mapper in config["mappers"]:  # pycolmap's database, our mapping
                db = out / "database.db"
                models, t = self.map(db, image_path, out / mapper, mapper, seed, config["threads"])
                add(seed, f"pycolmap matching + {mapper}", models, {**timings, "map": t}, verified)
            return {"rows": rows}
        matcher, feature_conf, _, escalation = split_stage_options(config["matcher"])
        first = (config["mappers"][0], config["seeds"][0])
        res = reconstruct(
            image_path.parent,
            conf=PipelineConf.from_dict({"escalation": escalation}),
            image_path=image_path,
            output=out,
            matcher=matcher_specs.build(matcher_specs.parse_spec(matcher)),
            feature_conf={"camera_mode": config["camera_mode"], **feature_conf},
            mapping_conf=dict(zip(("mapper", "random_seed"), first), num_threads=config["threads"]),
        )
        verified = res["database"]["num_verified_pairs"]
        # Where the run's time went: stages, and within matching read / coarse / fine / write.
        profile = {
            "extract": res["timings"]["extract"],
            **res["database"]["profile"],
            **{k: v for k, v in res["timings"].items() if k in ("map",) or "escalate" in k},
        }
        print(
            f"{name} {label}, {res['database']['num_pairs']} pairs: "
            + ", ".join(f"{k} {v:.1f} s" for k, v in profile.items()),
            flush=True,
        )
        for seed in config["seeds"]:
            for mapper in config["mappers"]:
                if (mapper, seed) == first:
                    models, timings = load_models(out / "sparse"), res["timings"]
                else:
                    sparse = out / f"sparse_{mapper}_{seed}"
                    db, threads = out / "database.db", config["threads"]
                    models, t = self.map(db, image_path, sparse, mapper, seed, threads)
                    timings = {**res["timings"], "map": t}
                add(seed, f"{label} + {mapper}", models, timings, verified)
        return {"rows": rows, "profile": profile}

    def table_rows(self, results) -> list[tuple]:
        """(set, seed, pipeline, stats, total s, ratio to pycolmap default of that set and seed)"""
        rows = []
        for name, by_label in results.items():
            flat = [row for result in by_label.values() for row in result["rows"]]
            base = {seed: sum(s["timings"].values()) for seed, p, s in flat if p == DEFAULT}
            for seed, pipeline, stats in flat:
                total = sum(stats["timings"].values())
                rows.append((name, seed, pipeline, stats, total, total / base[seed]))
        return rows

    def progress(self, results, name, label):
        mine = [(seed, pipeline) for seed, pipeline, _ in results[name][label]["rows"]]
        rows = self.table_rows({name: results[name]})
        return "\n".join(row_markdown(row) for row in rows if (row[1], row[2]) in mine)

    def summarize(self, results):
        c, rows = self.conf, self.table_rows(results)
        lines = [
            f"Pipeline benchmark, camera_mode={c['camera_mode']}, mapping threads {c['threads']} "
            "(time ratio = total wall time / pycolmap default's, same set and seed round)\n",
            "| set | seed | pipeline | verified pairs | registered | "
            "correct (reference) | model check | 3D points | total s | time ratio |",
            "|---|---|---|---|---|---|---|---|---|---|",
            *map(row_markdown, rows),
            *peer_ratios(rows, f"{c['peer']} + {c['mappers'][0]}", c["seeds"][0]),
            *summed(rows),
        ]
        return "\n".join(lines)


def summed(rows: list[tuple]) -> list[str]:
    """Each pipeline over every set (seed rounds averaged): photos registered, on the reference
    pose where a set has one, wall time, and its ratio to pycolmap's default summed the same way;
    the largest per-set ratio beside it."""
    by = {}
    for name, _, label, stats, total, ratio in rows:
        entry = by.setdefault(label, {"sets": set(), "reg": 0, "ok": 0, "s": 0.0, "max": 0.0})
        entry["sets"].add(name)
        entry["reg"] += stats["num_registered"]
        entry["ok"] += stats["correct"] or 0
        entry["s"] += total
        entry["max"] = max(entry["max"], ratio)
    base = by.get(DEFAULT)
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
    checked = stats["model_check"]
    check = "ok" if checked["ok"] else f"{len(checked['problems'])} problem(s)"
    return (
        f"| {name} | {seed} | {label} | {stats['num_verified_pairs']} | "
        f"{stats['num_registered']}/{stats['num_images']} | {correct} | "
        f"{check} | {stats['num_points3D']} | {total:.1f} | {ratio:.2f} |"
    )
