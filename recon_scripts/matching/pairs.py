"""Pair selection (exhaustive vs retrieval at several k, optionally sequential) end to end.

    python -m recon_scripts pairs [sets="sacre_coeur_hloc opensfm_lund ..."] [k="5 10"]
        [matcher=guided]

One SIFT extraction per set; each pair selection matches, verifies and maps a copy of it (same
keypoints). Prints per set and selection: pairs matched (fraction of exhaustive), verified pairs,
exhaustive's verified pairs that the selection kept (recall), registered images of the largest
model, and the match + verify time as a ratio of exhaustive's (same run).
"""

from __future__ import annotations

import time
from pathlib import Path

from colmap_guided import database as dbio
from colmap_guided import features, mapping, report
from colmap_guided.match import match_database
from colmap_guided.matchers import get_matcher
from recon_scripts.bench import Benchmark


def verified_pairs(database_path: Path) -> list[list[str]]:
    with dbio.open_database(database_path) as db:
        names = dbio.image_names(db)
        pairs = dbio.pair_inlier_counts(db).items()
        return sorted(sorted((names[a], names[b])) for (a, b), n in pairs if n > 0)


class PairsBenchmark(Benchmark):
    name = "pairs"
    default_conf = {
        "sets": ["sacre_coeur_hloc", "phototourism_superglue", "opensfm_lund"],
        "k": [3, 5, 10],
        "sequential": False,  # also sequential pairs at each k
        "matcher": "guided",
        "camera_mode": "auto",
        "exhaustive": True,  # false for large sets: recall and time ratio left out
    }

    def configs(self):
        c = self.conf
        selections = (
            ([("exhaustive", None)] if c["exhaustive"] else [])
            + [("retrieval", k) for k in c["k"]]
            + ([("sequential", k) for k in c["k"]] if c["sequential"] else [])
        )
        return {
            mode + (f" k={k}" if k else ""): {"mode": mode, "k": k, "matcher": c["matcher"]}
            for mode, k in selections
        }

    def prepare(self, name, image_path, work):
        return {"db": self.extract(image_path, work, {"camera_mode": self.conf["camera_mode"]})[0]}

    def run_config(self, name, image_path, prepared, label, config, out):
        db = self.copy_database(prepared["db"], out)
        names = features.list_images(image_path)
        matcher = get_matcher(config["matcher"])
        start = time.time()
        stats = match_database(
            db, image_path, config["mode"], matcher, num_neighbors=config["k"] or 1
        )
        elapsed = time.time() - start
        models = mapping.run_mapping(db, image_path, out / "sparse", {"mapper": "incremental"})
        model = report.model_statistics(models, names)
        return {
            "num_images": len(names),
            "num_pairs": stats["num_pairs"],
            "num_verified_pairs": stats["num_verified_pairs"],
            "verified": verified_pairs(db),
            "num_registered": model["num_registered"],
            "num_points3D": model["num_points3D"],
            "time": elapsed,
            "select_time": stats["pairs"]["time"],
        }

    def progress(self, results, name, label):
        r = results[name][label]
        return f"{name} {label}: {r['num_pairs']} pairs, {r['time']:.1f} s"

    def summarize(self, results):
        lines = [
            f"Pair selection, {self.conf['matcher']} matcher, camera_mode="
            f"{self.conf['camera_mode']} (time = select + match + verify, ratio to exhaustive's "
            "in the same run)\n",
            "| set | pairs | pairs (of exhaustive) | verified | "
            "exhaustive's verified kept | registered | 3D points | time ratio |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for name, rows in results.items():
            ex = rows.get("exhaustive")
            truth = {tuple(p) for p in ex["verified"]} if ex else set()
            for label, r in rows.items():
                n = r["num_images"]
                kept = f"{len({tuple(p) for p in r['verified']} & truth)}/{len(truth)}"
                ratio = f"{r['time'] / ex['time']:.2f}" if ex else "–"
                lines.append(
                    f"| {name} | {label} | {r['num_pairs']} "
                    f"({r['num_pairs'] / (n * (n - 1) / 2):.0%}) | {r['num_verified_pairs']} "
                    f"| {kept if ex else '–'} | {r['num_registered']}/{n} | {r['num_points3D']} "
                    f"| {ratio} |"
                )
        return "\n".join(lines)
