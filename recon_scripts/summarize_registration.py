"""Tables of eval_registration runs over seeds, one per LTLL protocol, methods of several runs side by side.

    python recon_scripts/summarize_registration.py OUT_A/results.json [OUT_B/results.json ...] [--reference SCENE=MODEL_DIR ...]

Per scene and method: historical photos on the reference pose (correct), off it (wrong), registered
photos of the whole set, distractors registered, over the seeds of the runs (min-max when they differ), and
the wall time of the first seed (later seeds map the first seed's database again). ``--reference`` checks a
scene whose manifest has no reference against a model of its own (e.g. pycolmap's model of the clean photos):
the registered models are read back from the runs' folders.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pycolmap

from colmap_guided.evaluation import registration
from colmap_guided.evaluation.tables import markdown_table
from colmap_guided.mapping import load_models


def _span(values: list) -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "–"
    return f"{min(values)}" if min(values) == max(values) else f"{min(values)}–{max(values)}"


def rescore(record: dict, scene: dict, method: str, reference: pycolmap.Reconstruction) -> dict:
    """Score a finished run again against ``reference`` from the models it wrote."""
    images = json.loads((Path(scene["scene_dir"]) / "manifest.json").read_text())["images"]
    workspace = registration.seed_runs_dir(scene["scene_dir"], scene.get("seed")) / registration.method_slug(method)
    models = load_models(workspace / "sparse")
    return {**record, **registration.score_registration(registration.largest_model(models), images, reference)}


def era_checks(record: dict, scene: dict) -> tuple[int | None, int | None]:
    """(correct, wrong) among the historical photos of one run."""
    if record.get("correct") is None:
        return None, None
    eras = {im["name"]: im["era"] for im in json.loads((Path(scene["scene_dir"]) / "manifest.json").read_text())["images"]}
    checks = record.get("pose_checks") or {}
    ok = sum(1 for n, c in checks.items() if eras.get(n) == "historical" and c.get("ok"))
    wrong = sum(1 for n, c in checks.items() if eras.get(n) == "historical" and c.get("ok") is False)
    return ok, wrong


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("results", nargs="+", type=Path)
    parser.add_argument("--reference", nargs="*", default=[], help="SCENE_PREFIX=MODEL_DIR: a reference for scenes without one")
    parser.add_argument("--label", nargs="*", default=[], help="METHOD=LABEL: one column for runs of the same method under different specs")
    args = parser.parse_args(argv)
    labels = dict(r.rsplit("=", 1) for r in args.label)
    refs = {k: pycolmap.Reconstruction(v) for k, _, v in (r.partition("=") for r in args.reference)}
    runs: dict = {}  # (scene, subset) -> method -> list of (seed, record, scene)
    methods: list[str] = []
    for path in args.results:
        for scene in json.loads(path.read_text())["scenes"]:
            for method, record in scene["methods"].items():
                if "error" in record:
                    continue
                column = labels.get(method, method)
                ref = next((r for k, r in refs.items() if scene["scene"] in (k, f"{k}_realistic")), None)
                if ref is not None and record.get("correct") is None:
                    record = rescore(record, scene, method, ref)
                runs.setdefault((scene["scene"], scene["subset"]), {}).setdefault(column, []).append((scene.get("seed"), record, scene))
                if column not in methods:
                    methods.append(column)
    for subset, title in (("historical", "historical photos + distractors"), ("all", "historical + modern photos + distractors")):
        rows, totals = [], {m: [] for m in methods}
        for (name, sub), by_method in sorted(runs.items()):
            if sub != subset:
                continue
            first = next(iter(by_method.values()))[0]
            n_hist = first[2]["eras"].get("historical", 0)
            row = [name, f"{n_hist}/{first[2]['eras'].get('modern', 0) if subset == 'all' else 0}/{first[2]['eras'].get('distractor', 0)}"]
            for m in methods:
                entries = by_method.get(m, [])
                if not entries:
                    row.append("–")
                    continue
                checks = [era_checks(rec, sc) for _, rec, sc in entries]
                hist = [int(rec.get("historical_registered", "0/0").split("/")[0]) for _, rec, _ in entries]
                reg = [rec["num_registered"] for _, rec, _ in entries]
                distr = [len(rec["distractors_registered"]) for _, rec, _ in entries]
                if checks[0][0] is None:
                    cell = f"hist. {_span(hist)} (no ref.)"
                else:
                    cell = f"**{_span([c[0] for c in checks])}** ✓ {_span([c[1] for c in checks])} ✗"
                    if all(by_method.get(other) for other in methods):  # means over the scenes every method ran
                        totals[m].append(np.mean([c[0] for c in checks]) / max(n_hist, 1))
                if subset == "all":
                    on_pose = "" if checks[0][0] is None else f" ({_span([rec['correct'] for _, rec, _ in entries])} ✓)"
                    cell += f" · all {_span(reg)}/{entries[0][1]['num_images']}{on_pose}"
                cell += f" · d {_span(distr)} · {entries[0][1].get('wall_time', 0):.0f} s ({len(entries)} seeds)"
                row.append(cell)
            rows.append(row)
        print(f"\n**Protocol: {title}** — historical photos on the reference pose (✓) / off it (✗) over the seeds; d = distractors registered\n")
        print(markdown_table(["scene", "images h/m/d", *methods], rows))
        print("\nMean share of historical photos on the reference pose (scenes with a reference that every method ran): " + ", ".join(f"{m} {100 * np.mean(v):.0f} %" for m, v in totals.items() if v))
    return 0


if __name__ == "__main__":
    sys.exit(main())
