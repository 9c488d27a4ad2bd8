"""Relative pose AUC (paper Table 2 protocol) and WxBS of matcher variants on pairs of photos.

    python -m recon_scripts two_view [methods="raw guided_ratio0.9"] [max_pairs=10]
        [sets="lund_door_gtsfm train/strecha_castle ... wxbs"] [wxbs_max_pairs=33]

Pose: pairs of lund_door_gtsfm (reference COLMAP model), train/strecha_castle,
train/strecha_entry_P10 (Strecha reference cameras) and train/instantngp_fox (instant-ngp cameras) —
held out of training —, sampled deterministically among covisible pairs; 2000 SIFT (pycolmap) per
image as in the paper; essential matrix by OpenCV RANSAC at 1 px / mean focal; AUC of max(R, t)
angular error at 5/10/20°, over the pairs of every scene. WxBS (the set ``wxbs``): F by MAGSAC++,
share of hand-labelled correspondences within 3/5/10 px.

Writes two_view.{md,json,png} and wxbs.{md,json,png} beside OUTPUT; the summary holds both tables.
Methods are matcher variants ``name[:key=value,...]`` (recon_scripts/evaluation/matcher_specs.py); a
variant whose matcher is not in the registry, or cannot run, stops the run with its error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon_scripts.bench import Benchmark
from recon_scripts.evaluation import matcher_specs, tables, two_view
from recon_scripts.evaluation.reference import TWO_VIEW_SCENES

WXBS = "wxbs"  # the set of WxBS pairs (../shared/data/wxbs_v1.1)


def pose_table(result: dict) -> str:
    headers = [
        "matcher",
        "AUC@5°",
        "AUC@10°",
        "AUC@20°",
        "matches",
        "RANSAC inliers",
        "precision % (<3 px)",
        "s/pair",
    ]
    rows = []
    for label, r in result["results"].items():
        s = r["summary"]
        rows.append(
            [
                label,
                *s["auc"],
                f"{s['mean_matches']:.0f}",
                f"{s['mean_inliers']:.0f}",
                s["precision"],
                f"{s['time_per_pair']:.2f}",
            ]
        )
    return tables.markdown_table(headers, rows)


def pose_scene_table(result: dict) -> str:
    scenes = result["config"]["scenes"]
    headers = ["matcher"] + [f"{s.split('/')[-1]} AUC@5/10/20" for s in scenes]
    rows = []
    for label, r in result["results"].items():
        rows.append(
            [label]
            + [
                " / ".join(f"{v:.1f}" for v in r["per_scene"][s]["auc"])
                + f" (n={r['per_scene'][s]['num_pairs']})"
                for s in scenes
            ]
        )
    return tables.markdown_table(headers, rows)


def wxbs_table(result: dict) -> str:
    headers = [
        "matcher",
        "share @3 px",
        "@5 px",
        "@10 px",
        "pairs ≥50 % @5 px",
        "matches",
        "inliers",
        "s/pair",
    ]
    rows = []
    for label, r in result["results"].items():
        s = r["summary"]
        rows.append(
            [
                label,
                *s["share"],
                s.get("solved_5px", 0.0),
                f"{s['mean_matches']:.0f}",
                f"{s['mean_inliers']:.0f}",
                f"{s['time_per_pair']:.2f}",
            ]
        )
    return tables.markdown_table(headers, rows)


def wxbs_category_table(result: dict) -> str:
    cats = sorted({c for r in result["results"].values() for c in r["per_category"]})
    headers = ["matcher"] + [f"{c} @5 px" for c in cats]
    rows = [
        [label]
        + [r["per_category"].get(c, {"share": [0, float("nan"), 0]})["share"][1] for c in cats]
        for label, r in result["results"].items()
    ]
    return tables.markdown_table(headers, rows)


def plot_pose(result: dict, path: Path) -> None:
    fig, (ax1, ax2) = tables.figure(2, 6.5, 4.2)
    labels = list(result["results"])
    tables.grouped_bars(
        None,
        [f"AUC@{t:g}°" for t in result["config"]["thresholds_deg"]],
        {k: result["results"][k]["summary"]["auc"] for k in labels},
        "AUC (%)",
        "Relative pose AUC",
        (0, 100),
        ax=ax1,
    )
    for label in labels:
        errs = np.sort([min(r["err_pose"], 90.0) for r in result["results"][label]["pairs"]])
        if len(errs):
            ax2.plot(
                np.concatenate([[0], errs]),
                np.concatenate([[0], np.arange(1, len(errs) + 1) / len(errs)]),
                label=label,
                drawstyle="steps-post",
            )
    ax2.set_xlim(0, 20)
    ax2.set_ylim(0, 1)
    ax2.set_xlabel("pose error max(R, t) (°)")
    ax2.set_ylabel("share of pairs")
    ax2.set_title("Cumulative pose error")
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=7)
    tables.save_figure(fig, path)


def plot_wxbs(result: dict, path: Path) -> None:
    labels = list(result["results"])
    tables.grouped_bars(
        path,
        [f"@{t:g} px" for t in result["config"]["thresholds_px"]],
        {k: result["results"][k]["summary"]["share"] for k in labels},
        "GT correspondences consistent (%)",
        "WxBS",
        (0, 100),
    )


def count(value):
    """A number of pairs, or None (``null``, ``none`` or 0: all of them)."""
    return None if value in (None, "none") or int(value) <= 0 else int(value)


class TwoViewBenchmark(Benchmark):
    name = "two_view"
    default_conf = {
        "sets": [*TWO_VIEW_SCENES, WXBS],  # scenes of ../shared/data with reference cameras; wxbs
        "methods": list(matcher_specs.DEFAULT_TWO_VIEW_SPECS),  # matcher variants
        "max_pairs": 10,  # pairs per scene (null: all covisible pairs)
        "min_covisible": 50,  # shared 3D points for a pair to be sampled
        "seed": 0,  # of the pair sampling
        "max_num_features": 2000,  # SIFT per image (paper: 2000)
        "estimator": "cv2",  # essential matrix RANSAC: cv2 or pycolmap
        "reference": "auto",  # auto, reference (cameras) or pseudo_gt (the train scenes' models)
        "wxbs_max_pairs": None,  # WxBS pairs (null: all 34), round-robin over categories
        "wxbs_geometry": "F",  # or H
        "device": None,  # torch device for the matchers
        "weights": None,  # guided matcher weights
        "cache_dir": str(two_view.DEFAULT_CACHE),  # SIFT features, extracted once
    }

    def configs(self):
        c = self.conf
        specs = matcher_specs.parse_specs(
            c["methods"], {"device": c["device"], "weights": c["weights"]}
        )
        protocol = {
            "max_pairs": count(c["max_pairs"]),
            "wxbs_max_pairs": count(c["wxbs_max_pairs"]),
            **{k: c[k] for k in ("min_covisible", "seed", "max_num_features", "estimator")},
            **{k: c[k] for k in ("reference", "wxbs_geometry")},
        }
        return {spec.label: {"matcher": spec.name, "conf": spec.conf, **protocol} for spec in specs}

    def run_config(self, name, image_path, prepared, label, config, out):
        spec = matcher_specs.MatcherSpec(config["matcher"], config["conf"], label)
        cache_dir = Path(self.conf["cache_dir"])
        if name == WXBS:
            result = two_view.run_wxbs_benchmark(
                [spec],
                max_pairs=config["wxbs_max_pairs"],
                geometry=config["wxbs_geometry"],
                max_num_features=config["max_num_features"],
                cache_dir=cache_dir,
            )
        else:
            result = two_view.run_pose_benchmark(
                [name],
                [spec],
                config["max_pairs"],
                config["seed"],
                config["min_covisible"],
                config["max_num_features"],
                estimator=config["estimator"],
                reference_source=config["reference"],
                cache_dir=cache_dir,
            )
        return {**result, "machine": tables.machine_note()}

    def progress(self, results, name, label):
        summary = results[name][label]["results"][label]["summary"]
        scores = summary["share"] if name == WXBS else summary["auc"]
        return f"{name} {label}: " + " / ".join(f"{v:.1f}" for v in scores)

    def published(self, results: dict) -> dict:
        """stem -> (its result, its Markdown, its plot): two_view (the scenes) and wxbs."""
        out = {}
        parts = [r for name, rows in results.items() if name != WXBS for r in rows.values()]
        if parts:
            note = parts[0]["machine"]
            result = {**two_view.merge_pose_results(parts), "machine": note}
            out["two_view"] = (
                result,
                f"### Relative pose AUC ({len(result['pairs'])} pairs; {note['date']}, "
                f"{note['torch_device']}, {note['cpu_count']} CPUs)\n\n{pose_table(result)}\n\n"
                f"Per scene:\n\n{pose_scene_table(result)}\n",
                plot_pose,
            )
        if WXBS in results:
            parts = list(results[WXBS].values())
            note = parts[0]["machine"]
            result = {**parts[0], "results": {k: v for p in parts for k, v in p["results"].items()}}
            out["wxbs"] = (
                result,
                f"### WxBS ({result['config']['num_pairs']} pairs, "
                f"{result['config']['geometry']} by MAGSAC++; {note['date']})\n\n"
                f"{wxbs_table(result)}\n\nPer category (share @5 px):\n\n"
                f"{wxbs_category_table(result)}\n",
                plot_wxbs,
            )
        return out

    def summarize(self, results):
        return "\n".join(text for _, text, _ in self.published(results).values())

    def run(self) -> dict:
        results = super().run()
        folder = Path(self.conf["output"] or f"outputs/benchmark_{self.name}.json").parent
        for stem, (result, text, plot) in self.published(results).items():
            tables.write_json(folder / f"{stem}.json", result)
            (folder / f"{stem}.md").write_text(text, encoding="utf-8")
            plot(result, folder / f"{stem}.png")
        return results
