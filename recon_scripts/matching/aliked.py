"""Guided learned features (paper §4.4, Table 3): SIFT vs ALIKED, raw vs guided, in one run.

    python -m recon_scripts aliked [sets="sacre_coeur_hloc phototourism_superglue"]
        [methods="sift:guided aliked:raw ..."]

Features are extracted once per set and type (time per image, same run), then every config matches a
copy of that database, verifies and maps (``reconstruct``). A config is
FEATURES:MATCHER[:KEY=VALUE,...] with matcher options, e.g.
``aliked:raw:ratio=none,min_similarity=0.9``. Pairs of photos whose names start with different
landmarks (the name up to its first digit, phototourism_superglue's 4 landmarks) are counted as
wrong when they verify.
"""

from __future__ import annotations

import re
from pathlib import Path

from colmap_guided import database as dbio
from colmap_guided.reconstruct import reconstruct
from recon_scripts.bench import Benchmark
from recon_scripts.evaluation import matcher_specs


def landmark(name: str) -> str:
    return re.split(r"\d", Path(name).name, maxsplit=1)[0]


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


class AlikedBenchmark(Benchmark):
    name = "aliked"
    default_conf = {
        "sets": ["sacre_coeur_hloc", "phototourism_superglue"],
        "methods": ["sift:guided", "aliked:raw", "aliked:guided"],  # FEATURES:MATCHER spec
    }

    def configs(self) -> dict[str, dict]:
        configs = {}
        for text in self.conf["methods"]:
            kind, _, spec = text.partition(":")
            (spec,) = matcher_specs.parse_specs([spec])  # a preset, options over it
            configs[text] = {"features": kind, "matcher": spec.name, "matcher_conf": spec.conf}
        return configs

    def prepare(self, name, image_path, work):
        kinds = {c["features"] for c in self.configs().values()}
        return {kind: self.extract(image_path, work, {"type": kind}) for kind in sorted(kinds)}

    def run_config(self, name, image_path, prepared, label, config, out):
        db, extract_s = prepared[config["features"]]
        self.copy_database(db, out)
        res = reconstruct(
            image_path.parent,
            image_path=image_path,
            output=out,
            matcher=config["matcher"],
            matcher_conf=config["matcher_conf"],
            feature_conf={"type": config["features"]},
        )
        verified, wrong = wrong_pairs(out / "database.db")
        return {
            "verified_pairs": verified,
            "wrong_pairs": wrong,
            "registered": res["num_registered"],
            "num_images": res["num_images"],
            "match_s": res["timings"]["match"],
            "map_s": res["timings"]["map"],
            "extract_s_per_image": extract_s,
        }

    def progress(self, results, name, label):
        row = results[name][label]
        brief = {k: v for k, v in row.items() if k != "wrong_pairs"}
        return f"{name} {label} {brief} wrong: {row['wrong_pairs']}"

    def summarize(self, results):
        lines = [
            "| set | features:matcher | verified pairs | different-landmark pairs | "
            "registered | extract s/img | match s | map s |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for name, rows in results.items():
            for text, r in rows.items():
                lines.append(
                    f"| {name} | {text} | {r['verified_pairs']} | {len(r['wrong_pairs'])} | "
                    f"{r['registered']}/{r['num_images']} | {r['extract_s_per_image']:.2f} | "
                    f"{r['match_s']:.1f} | {r['map_s']:.1f} |"
                )
        return "\n".join(lines)
