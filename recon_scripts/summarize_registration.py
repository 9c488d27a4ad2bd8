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

PROTOCOLS = (
    ("historical", "historical photos + distractors"),
    ("all", "historical + modern photos + distractors"),
)


def _span(values: list) -> str:
    """The range of the values given, "–" without any."""
    values = [v for v in values if v is not None]
    if not values:
        return "–"
    return f"{min(values)}" if min(values) == max(values) else f"{min(values)}–{max(values)}"


def add_reference_flag(parser) -> None:
    """The ``--reference SCENE_PREFIX=MODEL_DIR`` option."""
    parser.add_argument(
        "--reference",
        nargs="*",
        default=[],
        help="SCENE_PREFIX=MODEL_DIR: a reference for scenes without one",
    )


def load_references(specs: list[str]) -> dict[str, pycolmap.Reconstruction]:
    """``--reference`` values as {scene prefix: model}."""
    return {k: pycolmap.Reconstruction(v) for k, _, v in (r.partition("=") for r in specs)}


def reference_for(scene: str, refs: dict) -> pycolmap.Reconstruction | None:
    """The ``--reference`` model of ``scene`` (or of its realistic look), if any."""
    return next((r for k, r in refs.items() if scene in (k, f"{k}_realistic")), None)


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


def _on_pose(subset: str, record: dict, check: tuple) -> int:
    """Photos on the reference pose that a protocol counts: historical ones, or all."""
    return check[0] if subset == "historical" else record["correct"]


def _off_pose(subset: str, record: dict, check: tuple) -> int:
    """Photos off the reference pose that a protocol counts: historical ones, or all."""
    return check[1] if subset == "historical" else len(record.get("wrong") or [])


def _parser():
    """The command line."""
    parser = script_parser(__doc__)
    parser.add_argument("results", nargs="+", type=Path)
    add_reference_flag(parser)
    parser.add_argument(
        "--label",
        nargs="*",
        default=[],
        help="METHOD=LABEL: one row for runs of the same method under "
        "different specs; RESULTS:METHOD=LABEL: that file's runs of "
        "METHOD only (the same method before and after a change)",
    )
    return parser


def collect_runs(paths: list[Path], labels: dict, refs: dict) -> tuple[dict, list[str]]:
    """{(scene, subset): {row: [(seed, record, scene)]}} of the runs, and the row order."""
    runs: dict = {}
    methods: list[str] = []
    for path in paths:
        for scene in json.loads(path.read_text())["scenes"]:
            for method, record in scene["methods"].items():
                if "error" in record:
                    continue
                column = labels.get(f"{path}:{method}", labels.get(method, method))
                ref = reference_for(scene["scene"], refs)
                if ref is not None and record.get("correct") is None:
                    record = rescore(record, scene, method, ref)
                runs.setdefault((scene["scene"], scene["subset"]), {}).setdefault(
                    column, []
                ).append((scene.get("seed"), record, scene))
                if column not in methods:
                    methods.append(column)
    return runs, methods


def _scene_cell(subset: str, entries: list, checks: list) -> str:
    """One method's cell for one scene: photos on / off the pose over the seeds."""
    if checks[0][0] is None:
        hist = [int(rec.get("historical_registered", "0/0").split("/")[0]) for _, rec, _ in entries]
        return f"{_span(hist)} reg. (no ref.)"
    cell = f"{_span([c[0] for c in checks])} ✓ {_span([c[1] for c in checks])} ✗"
    if subset == "all":
        cell += (
            f" · {_span([rec['correct'] for _, rec, _ in entries])}/{entries[0][1]['num_images']}"
        )
    return cell


def _against_baseline(name: str, subset: str, entries: list, checks: list, base: dict):
    """The runs below the baseline's run of the same seed, and how many reach 1.25x it."""
    below, above = [], 0
    for (seed, rec, _), c in zip(entries, checks):
        mine = _on_pose(subset, rec, c)
        if seed in base and mine < base[seed]:
            below.append(f"{name} s{seed} {mine}<{base[seed]}")
        above += seed in base and mine >= 1.25 * base[seed] and mine > base[seed]
    return below, above


def _method_row(m: str, subset: str, by_scene: dict, methods: list, baseline, base_counts):
    """One method's row of a protocol table, and its sums over the scenes with a reference."""
    row, shares, wrong, distr, below, above, total = [m], [], [], [], [], 0, None
    for name, by_method in by_scene.items():
        entries = by_method.get(m, [])
        if not entries:
            row.append("–")
            continue
        checks = [era_checks(rec, sc) for _, rec, sc in entries]
        distr += [len(rec["distractors_registered"]) for _, rec, _ in entries]
        row.append(_scene_cell(subset, entries, checks))
        if checks[0][0] is None:
            continue
        total = total or [0, 0, 0, 0]
        for (_, rec, _), c in zip(entries, checks):
            total[0] += _on_pose(subset, rec, c)
            total[1] += _off_pose(subset, rec, c)
            total[3] += 1
        wrong.append(max(c[1] for c in checks))
        # means over the scenes every method ran
        if all(by_method.get(other) for other in methods):
            n_hist = entries[0][2]["eras"].get("historical", 0)
            shares.append(np.mean([c[0] for c in checks]) / max(n_hist, 1))
        if baseline and m != baseline and base_counts[name]:
            b, a = _against_baseline(name, subset, entries, checks, base_counts[name])
            below, above = below + b, above + a
    if total:
        total[2] = len(below)
    row += [f"{100 * np.mean(shares):.0f} %" if shares else "–", str(sum(wrong)), str(sum(distr))]
    if baseline:
        runs_total = sum(len(by_method.get(m, [])) for by_method in by_scene.values())
        listed = f" ({'; '.join(below)})" if below else ""
        row += (
            ["–", "–"] if m == baseline else [f"{len(below)} of {runs_total}{listed}", str(above)]
        )
    return row, total


def _print_protocol(subset: str, title: str, scenes: list, rows: list, baseline) -> None:
    """One protocol's table under its caption."""
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


def print_protocols(runs: dict, methods: list, baseline) -> dict:
    """A table per protocol, a row per method; returns each method's sums per protocol."""
    totals: dict = {}
    for subset, title in PROTOCOLS:
        scenes = sorted(name for name, sub in runs if sub == subset)
        if not scenes:
            continue
        by_scene = {name: runs[(name, subset)] for name in scenes}
        # the baseline's count per scene and seed, the one the goal is about (historical only:
        # historical photos)
        base_counts = {
            name: {
                seed: _on_pose(subset, rec, era_checks(rec, sc))
                for seed, rec, sc in by_method.get(baseline, [])
            }
            for name, by_method in by_scene.items()
        }
        rows = []
        for m in methods:
            row, total = _method_row(m, subset, by_scene, methods, baseline, base_counts)
            rows.append(row)
            if total:
                totals.setdefault(m, {})[subset] = total
        _print_protocol(subset, title, scenes, rows, baseline)
    return totals


def print_totals(totals: dict, methods: list, baseline) -> None:
    """Photos on / off the pose summed over scenes and seeds, a row per method."""
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
    head = ["method", "historical + modern (all photos)", "historical only (historical photos)"]
    print(markdown_table(head, rows))


def print_times(runs: dict, methods: list) -> None:
    """Time per image and per pair of each method, first seed of each run."""
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
    head = [
        "method",
        "extract s/image (median)",
        "match + verify s/pair (median)",
        "wall s (sum over scenes)",
    ]
    print(markdown_table(head, rows))


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    labels = dict(r.rsplit("=", 1) for r in args.label)
    runs, methods = collect_runs(args.results, labels, load_references(args.reference))
    baseline = "pycolmap" if "pycolmap" in methods else None
    totals = print_protocols(runs, methods, baseline)
    if totals:
        print_totals(totals, methods, baseline)
    print_times(runs, methods)
    return 0


if __name__ == "__main__":
    sys.exit(main())
