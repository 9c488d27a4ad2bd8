"""Photos registered and on the reference pose per scene (LTLL protocol, paper Fig. 5a):
historical photos only, and historical + modern.

    python -m recon_scripts registration [methods="pycolmap raw guided"] [seeds="0 1 2"] [threads=1]
    python -m recon_scripts registration split=test proxy_dir=outputs/proxy_test methods=[]
    python -m recon_scripts registration manifest=datasets/ltll_manifest.json root=/data/LTLL \\
        scan=true
    python -m recon_scripts registration manifest=datasets/shared_manifest.json \\
        sets=lund_door_gtsfm subsets=all
    python -m recon_scripts registration merge="outputs/a.json outputs/b.json" \\
        references=sacre_coeur_hloc=outputs/refs/sacre_coeur_hloc/sparse/0

Sets: the scenes of ``manifest`` (default all, or the first ``max_scenes``; an LTLL copy: its
folders under ``root`` with ``scan=true``). Without a manifest: the offline historical proxy,
PROXY_DIR/proxy_manifest.json, built first where it is missing (recon_scripts/evaluation/proxy.py:
the ``split``'s sets or ``sources``, each ``looks``, ``distractors`` unrelated photos, long side
``max_size``, ``crop``, the first ``max_images``, ``proxy_seed``); a proxy built with other options
is refused. ``methods=[]`` only builds it (or scans the copy).

For each scene, subset (historical = historical photos + distractors; all = every photo) and seed
(``seeds``: the random seed of every mapper, null = one unseeded pycolmap run and reconstruct's seed
0; ``threads``: the mappers' threads, 1 = a seeded run repeats exactly) it runs each method:
``pycolmap`` (its default pipeline), ``pycolmap_mapping`` (its database, this project's mapping) or
a matcher spec of the registry through ``reconstruct`` (a spec may carry feature, mapping and
escalation options: guided:stretch_contrast_below=none, raw:mapper=global). A method starts from
the finished database of one with the same features and matcher (mapping only) or the same
features (matching and mapping), and later seeds map the first seed's databases. Scored: the
registered ratio of the largest model, the photos whose pose agrees with the reference model
(rotation < ``max_rotation_deg``, centre < ``max_center_frac`` of the scene depth after a robust
similarity fit) and the distractors registered (must be 0). Runs: WORK/<scene>/<scene>__<subset>/
runs[/seed<N>]/<method>/; ``resume=true`` takes a finished run (its eval.json) as it is,
``remap=true`` maps the finished databases again (after a change of the mapping stage or of
``threads``). Beside the table (``wxbs_max_pairs``, 0 = skip): the WxBS appearance-change pairs
(WGABS, WLABS, WGALBS), scored by hand-labelled correspondences.

The summary: per scene and subset the registered photos, the mean registered ratio per subset and
the agreement with the reference; then one table per protocol, a row per method and a column per
scene: historical photos on the reference pose (✓), off it (✗), and for the whole set the photos on
the reference pose, over the seeds (min-max when they differ), the mean share, the wrong ones,
distractors registered and, beside pycolmap's default pipeline, the (scene, seed) runs with fewer
photos on the reference pose than it and those with at least 1.25x as many; the totals, and the time
per image and per pair of each method (first seed). ``references`` (SCENE=MODEL_DIR) checks a scene
whose manifest has no reference against a model of its own (e.g. pycolmap's model of the clean
photos), from the models the runs wrote; ``label`` (METHOD=LABEL, or RESULTS:METHOD=LABEL for one
output's runs of METHOD only) puts runs under another row. ``merge``: those tables of earlier
outputs side by side (this preset's JSON, or an earlier evaluation's results.json), nothing run.
Beside OUTPUT: OUTPUT_registered.png (bars per scene), OUTPUT_wxbs_appearance.json and, with
``scan``, OUTPUT_manifest_scanned.json.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap

from colmap_guided.log import logger, set_verbosity
from colmap_guided.mapping import load_models
from recon_scripts.bench import Benchmark, same
from recon_scripts.evaluation import manifest as mf
from recon_scripts.evaluation import matcher_specs, proxy, registration, tables, two_view
from recon_scripts.evaluation.tables import markdown_table

WXBS_APPEARANCE = ("WGABS", "WLABS", "WGALBS")
PROTOCOLS = (
    ("historical", "historical photos + distractors"),
    ("all", "historical + modern photos + distractors"),
)


class RegistrationBenchmark(Benchmark):
    name = "registration"
    default_conf = {
        "sets": [],  # scenes of the manifest (empty: all)
        "max_scenes": None,  # the first N of them
        "manifest": None,  # multi-scene manifest (none: the historical proxy of proxy_dir)
        "root": None,  # local copy of the dataset (over the manifest's root)
        "scan": False,  # the manifest's scenes from the folders under root (LTLL)
        "proxy_dir": "outputs/historical_proxy",  # the proxy, built there where missing
        "split": "dev",  # dev: thresholds are chosen here; test: landmarks the weights never saw
        "sources": [],  # sets of ../shared/data instead of the split's (e.g. sceaux_castle)
        "looks": list(proxy.LOOKS),  # realistic prints, damaged ones and/or postcards
        "distractors": 3,  # photos of unrelated scenes added to each scene
        "max_size": 1024,  # long side of every proxy photo (none: as it is)
        "crop": 0.1,  # historical photos keep >= 1 - crop of each side
        "max_images": None,  # the first N photos of each set (none: all)
        "proxy_seed": 0,
        "subsets": ["historical", "all"],
        "methods": ["pycolmap", "raw", "guided"],
        "seeds": [None],
        "threads": None,  # mapping threads (none: each pipeline's, all cores)
        "resume": False,
        "remap": False,
        "device": None,
        "weights": None,
        "max_rotation_deg": registration.MAX_ROTATION_DEG,
        "max_center_frac": registration.MAX_CENTER_FRAC,
        "wxbs_max_pairs": 6,
        "references": [],  # SCENE=MODEL_DIR: a reference for scenes without one
        "label": [],  # METHOD=LABEL or RESULTS:METHOD=LABEL: the runs' row in the summary
        "merge": [],  # outputs summarized side by side, nothing run
    }

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        c = self.conf
        for key, known in (
            ("subsets", mf.SUBSETS),
            ("looks", proxy.LOOKS),
            ("split", proxy.SPLITS),
        ):
            if not set(c[key] if isinstance(c[key], list) else [c[key]]) <= set(known):
                raise ValueError(f"{key} must be among {sorted(known)}, got {c[key]!r}")
        matcher_specs.parse_specs(matcher_parts(c["methods"]))  # ValueError now, not after hours
        self.resume = c["resume"] or c["remap"]  # the runs decide what is done, not the cache

    def output(self) -> Path:
        return Path(self.conf["output"] or f"outputs/benchmark_{self.name}.json")

    def beside(self, name: str) -> Path:
        """OUTPUT_<name>, beside OUTPUT."""
        return self.output().with_name(f"{self.output().stem}_{name}")

    def historical_proxy(self) -> Path:
        """The proxy's manifest, built first where missing; one built otherwise is refused."""
        c = self.conf
        build = {
            "sources": c["sources"] or list(proxy.SPLITS[c["split"]]),
            "looks": c["looks"],
            "seed": c["proxy_seed"],
            "n_distractors": c["distractors"],
            "max_size": c["max_size"] or None,
            "crop": c["crop"],
            "max_images": c["max_images"] or None,
        }
        path = Path(c["proxy_dir"]) / "proxy_manifest.json"
        if not path.is_file():
            logger.info("Building the historical proxy in %s", c["proxy_dir"])
            proxy.build_proxy(c["proxy_dir"], **build)
        built = json.loads(path.read_text()).get("build")
        if built is not None and not same(built, build):
            raise ValueError(
                f"{path} was built with {built}, not {build}; pass another proxy_dir, "
                f"or manifest={path}"
            )
        return path

    def load_manifest(self) -> tuple[Path, dict]:
        """The manifest's path and contents (the proxy built if missing; scan's scenes)."""
        c = self.conf
        path = Path(c["manifest"]) if c["manifest"] else self.historical_proxy()
        data = mf.load_manifest(path, c["root"])
        if c["scan"]:
            if data["_root"] is None:
                raise ValueError("scan=true needs root=FOLDER")
            data["scenes"] = mf.scan_root(data["_root"])
            data["root"] = str(Path(data["_root"]).resolve())
            mf.save_manifest(self.beside("manifest_scanned.json"), data)
        return path, data

    def run(self) -> dict:
        set_verbosity(quiet=True)
        c = self.conf
        self.labels = dict(r.rsplit("=", 1) for r in c["label"])
        self.refs = load_references(c["references"])
        if c["merge"]:
            sources = {path: scenes_of(json.loads(Path(path).read_text())) for path in c["merge"]}
            print(protocol_tables(sources, self.labels, self.refs))
            return {}
        path, self.data = self.load_manifest()
        if not c["methods"]:
            print(f"Manifest: {path}")
            return {}
        scenes = mf.select_scenes(self.data, c["sets"], c["max_scenes"])
        if not scenes:
            raise ValueError(f"{path} lists no scene with images (LTLL: pass root and scan=true)")
        self.scenes = {scene["name"]: scene for scene in scenes}
        c["sets"] = list(self.scenes)
        specs = matcher_parts(c["methods"])
        self.wxbs = wxbs_text(self.beside("wxbs_appearance.json"), c["wxbs_max_pairs"], specs, c)
        return super().run()

    def configs(self):
        c = self.conf
        shared = {
            "manifest": str(Path(c["manifest"] or c["proxy_dir"]).resolve()),
            **{k: c[k] for k in ("root", "scan", "subsets", "threads", "device", "weights")},
            **{k: c[k] for k in ("max_rotation_deg", "max_center_frac")},
        }
        return {
            method + ("" if seed is None else f" seed={seed}"): {
                "method": method,
                "seed": seed,
                **shared,
            }
            for seed in c["seeds"]
            for method in c["methods"]
        }

    def images(self, name, work):
        return mf.scene_image_dir(self.data, self.scenes[name])

    def prepare(self, name, image_path, work):
        """The scene laid out per subset: WORK/<scene>/<scene>__<subset> (None: < 2 photos)."""
        layouts = {}
        for subset in self.conf["subsets"]:
            layouts[subset] = mf.layout_scene(self.data, self.scenes[name], subset, work)
            if layouts[subset] is None:
                logger.info("%s: fewer than 2 %s images, skipped.", name, subset)
        return layouts

    def run_config(self, name, image_path, prepared, label, config, out):
        """One method and seed on each subset: {"runs": [a record per subset, as
        ``registration.evaluate_scene`` gives it, with the photos of its manifest]}."""
        c, seed, first = self.conf, config["seed"], self.conf["seeds"][0]
        runs = []
        for subset in config["subsets"]:
            scene_dir = prepared[subset]
            if scene_dir is None:
                continue
            # later seeds map the first seed's databases
            first_runs = registration.seed_runs_dir(scene_dir, first)
            record = registration.evaluate_scene(
                scene_dir,
                [config["method"]],
                extra_conf={"device": config["device"], "weights": config["weights"]},
                resume=c["resume"],
                seed=seed,
                databases_from=None if seed == first else first_runs,
                remap=c["remap"],
                threads=config["threads"],
                reuse_from=c["methods"],
                max_rotation_deg=config["max_rotation_deg"],
                max_center_frac=config["max_center_frac"],
            )
            images = json.loads((scene_dir / "manifest.json").read_text())["images"]
            runs.append({**record, "images": images})
        return {"runs": runs}

    def progress(self, results, name, label):
        return f"{name} {label}: " + "; ".join(
            f"{run['subset']} {registration._cell(rec)}, {registration._check_cell(rec)}"
            for run in results[name][label]["runs"]
            for rec in run["methods"].values()
        )

    def summarize(self, results):
        methods, scenes = self.conf["methods"], scene_records(results, self.conf)
        distractors = sum(
            len(r["methods"][m].get("distractors_registered", []))
            for r in scenes
            for m in methods
            if m in r["methods"]
        )
        registration.plot_registration(scenes, methods, self.beside("registered.png"))
        return (
            registration.report_markdown(self.data.get("name", "manifest"), methods, scenes)
            + f"\n\nDistractors registered, all runs: {distractors} (must be 0)\n"
            + self.wxbs
            + "\n"
            + protocol_tables({str(self.output()): scenes}, self.labels, self.refs)
        )


def matcher_parts(methods: list[str]) -> list[str]:
    """The matcher specs of the methods other than pycolmap's, without their stage options."""
    return [
        registration.split_stage_options(m)[0]
        for m in methods
        if m not in registration.PYCOLMAP_METHODS
    ]


def wxbs_text(path: Path, max_pairs: int, specs: list[str], conf: dict) -> str:
    """The WxBS appearance-change table of ``specs``, its results written to ``path``; "" when
    skipped."""
    if not (max_pairs and specs):
        return ""
    extra = {"device": conf["device"], "weights": conf["weights"]}
    w = two_view.run_wxbs_benchmark(
        specs, max_pairs=max_pairs, categories=WXBS_APPEARANCE, extra_conf=extra
    )
    tables.write_json(path, w)
    rows = [
        [label, *r["summary"]["share"], f"{r['summary']['mean_matches']:.0f}"]
        for label, r in w["results"].items()
    ]
    return (
        f"\nWxBS appearance-change pairs ({w['config']['num_pairs']}"
        f" of {', '.join(WXBS_APPEARANCE)}; share of hand-labelled "
        "correspondences consistent with the estimated F):\n\n"
        + markdown_table(["matcher", "@3 px", "@5 px", "@10 px", "matches"], rows)
        + "\n"
    )


def scene_records(results: dict, conf: dict) -> list[dict]:
    """{scene: {label: result}} as a record per scene, subset and seed holding every method, in the
    order of the sets, subsets and seeds."""
    merged: dict = {}
    for by_label in results.values():
        for result in by_label.values():
            for run in result["runs"]:
                key = (run["scene"], run["subset"], run["seed"])
                merged.setdefault(key, {**run, "methods": {}})["methods"].update(run["methods"])
    order = (list(results), conf["subsets"], conf["seeds"])
    return [merged[k] for k in sorted(merged, key=lambda k: [o.index(x) for o, x in zip(order, k)])]


def scenes_of(data: dict) -> list[dict]:
    """The scene records of an output: this preset's JSON, or an evaluation's results.json."""
    return data["scenes"] if "scenes" in data else scene_records(data["results"], data["conf"])


# ------------------------------------------------------------------------ the protocol tables


def _span(values: list) -> str:
    """The range of the values given, "–" without any."""
    values = [v for v in values if v is not None]
    if not values:
        return "–"
    return f"{min(values)}" if min(values) == max(values) else f"{min(values)}–{max(values)}"


def load_references(specs: list[str]) -> dict[str, pycolmap.Reconstruction]:
    """``references`` values as {scene prefix: model}."""
    return {k: pycolmap.Reconstruction(v) for k, _, v in (r.partition("=") for r in specs)}


def reference_for(scene: str, refs: dict) -> pycolmap.Reconstruction | None:
    """The ``references`` model of ``scene`` (or of its realistic look), if any."""
    return next((r for k, r in refs.items() if scene in (k, f"{k}_realistic")), None)


def scene_images(scene: dict) -> list[dict]:
    """The manifest entries of a scene record (read from its layout where the record has none)."""
    if "images" in scene:
        return scene["images"]
    return json.loads((Path(scene["scene_dir"]) / "manifest.json").read_text())["images"]


def rescore(record: dict, scene: dict, method: str, reference: pycolmap.Reconstruction) -> dict:
    """Score a finished run again against ``reference`` from the models it wrote."""
    images = scene_images(scene)
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
    images = scene_images(scene)
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


def collect_runs(sources: dict[str, list], labels: dict, refs: dict) -> tuple[dict, list[str]]:
    """{(scene, subset): {row: [(seed, record, scene)]}} of the runs of {output: scene records},
    and the row order."""
    runs: dict = {}
    methods: list[str] = []
    for path, scenes in sources.items():
        for scene in scenes:
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


def _protocol_table(subset: str, title: str, scenes: list, rows: list, baseline) -> list[str]:
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
    return [
        f"\n**Protocol: {title}** — {what}, over the seeds (a range when they differ); "
        "mean share over the scenes that every method ran; runs below pycolmap: (scene, "
        f"seed) runs with fewer {'historical ' if subset == 'historical' else ''}photos "
        "on the reference pose than pycolmap's default pipeline with the same seed\n",
        markdown_table(head, rows),
    ]


def protocols(runs: dict, methods: list, baseline) -> tuple[list[str], dict]:
    """A table per protocol, a row per method, and each method's sums per protocol."""
    lines, totals = [], {}
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
        lines += _protocol_table(subset, title, scenes, rows, baseline)
    return lines, totals


def totals_table(totals: dict, methods: list, baseline) -> list[str]:
    """Photos on / off the pose summed over scenes and seeds, a row per method."""

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
    return [
        "\n**Totals** — photos on the reference pose ✓ / off it ✗, "
        "summed over the scenes (scored against a reference) and seeds"
        + ("; runs below pycolmap's default pipeline" if baseline else "")
        + "\n",
        markdown_table(head, rows),
    ]


def times_table(runs: dict, methods: list) -> list[str]:
    """Time per image and per pair of each method, first seed of each run."""
    rows = []
    for m in methods:
        extract, match, total = [], [], []
        for (name, subset), by_method in sorted(runs.items()):
            seeds = [-1 if s is None else s for s, _, _ in by_method.get(m, [])]
            entries = [e for e, s in zip(by_method.get(m, []), seeds) if s == min(seeds)]
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
    return [
        "\n**Time** (first seed; extract per image, match per "
        "pair of the exhaustive pairs, distractors included)\n",
        markdown_table(head, rows),
    ]


def protocol_tables(sources: dict[str, list], labels: dict, refs: dict) -> str:
    """The LTLL tables of {output: scene records}, their methods side by side."""
    runs, methods = collect_runs(sources, labels, refs)
    baseline = "pycolmap" if "pycolmap" in methods else None
    lines, totals = protocols(runs, methods, baseline)
    if totals:
        lines += totals_table(totals, methods, baseline)
    return "\n".join(lines + times_table(runs, methods))
