"""Tables of eval_registration runs over seeds, one per LTLL protocol, methods of several runs side
by side.

    python -m recon_scripts.summarize_registration OUT_A/results.json [OUT_B/results.json ...]
        [--reference SCENE=MODEL_DIR ...]

One table per protocol, a row per method and a column per scene: historical photos on the reference
pose (correct), off it (wrong), and for the whole set the photos on the reference pose, over the
seeds of the runs (min-max when they differ); then the mean share, the wrong ones, distractors
registered and, beside pycolmap's default pipeline, the (scene, seed) runs with fewer photos on the
reference pose than it and those with at least 1.25x as many. Then the time per image and per pair
of each method (first seed). ``--reference`` checks a scene whose manifest has no reference against
a model of its own (e.g. pycolmap's model of the clean photos): the registered models are read back
from the runs' folders.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pycolmap

from colmap_guided.mapping import load_models
from recon_scripts import script_parser
from recon_scripts.evaluation import registration
from recon_scripts.evaluation.tables import markdown_table


def _span(values: list) -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "–"
    return f"{min(values)}" if min(values) == max(values) else f"{min(values)}–{max(values)}"


def rescore(record: dict, scene: dict, method: str, reference: pycolmap.Reconstruction) -> dict:
    """Score a finished run again against ``reference`` from the models it wrote."""
    images = json.loads((Path(scene["scene_dir"]) / "manifest.json").read_text())["images"]
    workspace = registration.seed_runs_dir(
        scene["scene_dir"], scene.get("seed")
    ) / registration.method_slug(method)
    models = load_models(workspace / "sparse")
    return {
        **record,
        **registration.score_registration(
            registration.largest_model(models), images, reference, record.get("same_picture")
        ),
    }


def era_checks(record: dict, scene: dict) -> tuple[int | None, int | None]:
    """(correct, wrong) among the historical photos of one run."""
    if record.get("correct") is None:
        return None, None
    images = json.loads((Path(scene["scene_dir"]) / "manifest.json").read_text())["images"]
    # (a collage card registered whole is among the wrong ones; its panels are photos)
    eras = {im["name"]: im["era"] for im in [*images, *registration.photos(images)]}
    checks = record.get("pose_checks") or {}
    ok = sum(1 for n, c in checks.items() if eras.get(n) == "historical" and c.get("ok"))
    wrong = sum(1 for n in record.get("wrong") or [] if eras.get(n) == "historical")
    return ok, wrong


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("results", nargs="+", type=Path)
    parser.add_argument(
        "--reference",
        nargs="*",
        default=[],
        help="SCENE_PREFIX=MODEL_DIR: a reference for scenes without one",
    )
    parser.add_argument(
        "--label",
        nargs="*",
        default=[],
        help="METHOD=LABEL: one row for runs of the same method under "
        "different specs; RESULTS:METHOD=LABEL: that file's runs of "
        "METHOD only (the same method before and after a change)",
    )
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
                column = labels.get(f"{path}:{method}", labels.get(method, method))
                ref = next(
                    (r for k, r in refs.items() if scene["scene"] in (k, f"{k}_realistic")), None
                )
                if ref is not None and record.get("correct") is None:
                    record = rescore(record, scene, method, ref)
                runs.setdefault((scene["scene"], scene["subset"]), {}).setdefault(
                    column, []
                ).append((scene.get("seed"), record, scene))
                if column not in methods:
                    methods.append(column)
    baseline = "pycolmap" if "pycolmap" in methods else None
    totals: dict = {}  # method -> subset -> [on the pose, off it, runs below the baseline, runs]
    for subset, title in (
        ("historical", "historical photos + distractors"),
        ("all", "historical + modern photos + distractors"),
    ):
        scenes = sorted(name for name, sub in runs if sub == subset)
        if not scenes:
            continue
        # the baseline's count per scene and seed, the one the goal is about (historical only:
        # historical photos)
        base_counts = {
            name: {
                seed: (era_checks(rec, sc)[0] if subset == "historical" else rec["correct"])
                for seed, rec, sc in runs[(name, subset)].get(baseline, [])
            }
            for name in scenes
        }
        rows = []
        for m in methods:
            row, shares, wrong, distr, below, above = [m], [], [], [], [], 0
            for name in scenes:
                by_method = runs[(name, subset)]
                entries = by_method.get(m, [])
                if not entries:
                    row.append("–")
                    continue
                n_hist = entries[0][2]["eras"].get("historical", 0)
                checks = [era_checks(rec, sc) for _, rec, sc in entries]
                distr += [len(rec["distractors_registered"]) for _, rec, _ in entries]
                if checks[0][0] is None:
                    hist = [
                        int(rec.get("historical_registered", "0/0").split("/")[0])
                        for _, rec, _ in entries
                    ]
                    row.append(f"{_span(hist)} reg. (no ref.)")
                    continue
                cell = f"{_span([c[0] for c in checks])} ✓ {_span([c[1] for c in checks])} ✗"
                if subset == "all":
                    cell += (
                        f" · {_span([rec['correct'] for _, rec, _ in entries])}"
                        f"/{entries[0][1]['num_images']}"
                    )
                row.append(cell)
                total = totals.setdefault(m, {}).setdefault(subset, [0, 0, 0, 0])
                for (_, rec, _), c in zip(entries, checks):
                    total[0] += c[0] if subset == "historical" else rec["correct"]
                    total[1] += c[1] if subset == "historical" else len(rec.get("wrong") or [])
                    total[3] += 1
                wrong.append(max(c[1] for c in checks))
                # means over the scenes every method ran
                if all(by_method.get(other) for other in methods):
                    shares.append(np.mean([c[0] for c in checks]) / max(n_hist, 1))
                if baseline and m != baseline and base_counts[name]:
                    base = base_counts[name]
                    for (seed, rec, sc), c in zip(entries, checks):
                        mine = c[0] if subset == "historical" else rec["correct"]
                        if seed in base and mine < base[seed]:
                            below.append(f"{name} s{seed} {mine}<{base[seed]}")
                        above += seed in base and mine >= 1.25 * base[seed] and mine > base[seed]
            if m in totals and subset in totals[m]:
                totals[m][subset][2] = len(below)
            runs_total = sum(len(runs[(n, subset)].get(m, [])) for n in scenes)
            row += [
                f"{100 * np.mean(shares):.0f} %" if shares else "–",
                str(sum(wrong)),
                str(sum(distr)),
            ]
            if baseline:
                row += [
                    "–"
                    if m == baseline
                    else f"{len(below)} of {runs_total}"
                    + (f" ({'; '.join(below)})" if below else ""),
                    "–" if m == baseline else str(above),
                ]
            rows.append(row)
        head = [
            "method",
            *scenes,
            "historical ✓ (mean share)",
            "historical ✗ (worst seed, summed)",
            "distractors",
        ]
        if baseline:
            head += ["runs below pycolmap", "runs ≥ 1.25× pycolmap"]
        what = "historical photos on the reference pose ✓ / off it ✗" + (
            ", then all photos on the reference pose / all" if subset == "all" else ""
        )
        print(
            f"\n**Protocol: {title}** — {what}, over the seeds (a range when they differ); "
            "mean share over the scenes that every method ran; runs below pycolmap: (scene, "
            f"seed) runs with fewer {'historical ' if subset == 'historical' else ''}photos "
            "on the reference pose than pycolmap's default pipeline with the same seed\n"
        )
        print(markdown_table(head, rows))
    if totals:
        print(
            "\n**Totals** — photos on the reference pose ✓ / off it ✗, "
            "summed over the scenes (scored against a reference) and seeds"
            + ("; runs below pycolmap's default pipeline" if baseline else "")
            + "\n"
        )

        def total_cell(m, t):
            return (
                "–"
                if t is None
                else f"{t[0]} / {t[1]}"
                + ("" if m == baseline or not baseline else f", {t[2]} of {t[3]} below")
            )

        rows = [
            [m, total_cell(m, totals[m].get("all")), total_cell(m, totals[m].get("historical"))]
            for m in methods
            if m in totals
        ]
        print(
            markdown_table(
                [
                    "method",
                    "historical + modern (all photos)",
                    "historical only (historical photos)",
                ],
                rows,
            )
        )
    print(
        "\n**Time** (first seed; extract per image, match per "
        "pair of the exhaustive pairs, distractors included)\n"
    )
    rows = []
    for m in methods:
        extract, match, total = [], [], []
        for (name, subset), by_method in sorted(runs.items()):
            entries = [
                e for e in by_method.get(m, []) if e[0] == min(s for s, _, _ in by_method[m])
            ]
            for _, rec, sc in entries[:1]:
                n = sum(sc["eras"].values())
                t = rec.get("timings", {})
                extract.append(t.get("extract", 0) / n)
                match.append((t.get("match", 0) + t.get("verify", 0)) / (n * (n - 1) / 2))
                total.append(rec.get("wall_time", 0))
        if extract:
            rows.append(
                [m, f"{np.median(extract):.2f}", f"{np.median(match):.2f}", f"{np.sum(total):.0f}"]
            )
    print(
        markdown_table(
            [
                "method",
                "extract s/image (median)",
                "match + verify s/pair (median)",
                "wall s (sum over scenes)",
            ],
            rows,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
