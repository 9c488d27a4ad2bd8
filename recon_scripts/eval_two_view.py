"""Two-view geometry benchmark (paper Table 2 protocol) + WxBS, for every matcher variant of the
registry.

    python -m recon_scripts.eval_two_view [--max_pairs 10] [--wxbs_max_pairs 33]
        [--output outputs/eval_two_view]
    python -m recon_scripts.eval_two_view --matchers raw guided_ratio0.9 --max_pairs 3 --no_wxbs

Pose: pairs of lund_door_gtsfm (reference COLMAP model), train/strecha_castle,
train/strecha_entry_P10 (Strecha reference cameras) and train/instantngp_fox (instant-ngp cameras) —
held out of training —, sampled deterministically among covisible pairs; 2000 SIFT (pycolmap) per
image as in the paper; essential matrix by OpenCV RANSAC at 1 px / mean focal; AUC of max(R, t)
angular error at 5/10/20°. WxBS: F by MAGSAC++, share of hand-labelled correspondences within
3/5/10 px.

Writes OUTPUT/two_view.{md,json,png} and OUTPUT/wxbs.{md,json,png}; prints the Markdown tables.
Matcher variants: ``name[:key=value,...]`` (see recon_scripts/evaluation/matcher_specs.py); a
variant whose matcher is not in the registry, or cannot run, stops the script with its error.
"""

from __future__ import annotations

import sys
from pathlib import Path

from colmap_guided.conf import at_most_zero, none_or
from colmap_guided.log import set_verbosity
from colmap_guided.paths import REPO_ROOT
from recon_scripts import script_parser
from recon_scripts.evaluation import matcher_specs, tables, two_view
from recon_scripts.evaluation.reference import TWO_VIEW_SCENES


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
    import numpy as np

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


def _parser():
    """The command line."""
    parser = script_parser(__doc__)
    parser.add_argument(
        "--scenes",
        nargs="+",
        default=list(TWO_VIEW_SCENES),
        help="scenes of ../shared/data with reference cameras",
    )
    parser.add_argument(
        "--matchers",
        nargs="+",
        default=list(matcher_specs.DEFAULT_TWO_VIEW_SPECS),
        help="matcher variants name[:key=value,...]",
    )
    parser.add_argument(
        "--max_pairs",
        type=none_or(int, old_off=at_most_zero),
        default=10,
        help="pairs per scene (none = all covisible pairs)",
    )
    parser.add_argument(
        "--min_covisible", type=int, default=50, help="shared 3D points for a pair to be sampled"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--max_num_features", type=int, default=2000, help="SIFT per image (paper: 2000)"
    )
    parser.add_argument(
        "--estimator", default="cv2", choices=["cv2", "pycolmap"], help="essential matrix RANSAC"
    )
    parser.add_argument(
        "--reference",
        default="auto",
        choices=["auto", "reference", "pseudo_gt"],
        help="reference cameras or the train scenes' pseudo-GT",
    )
    parser.add_argument("--no_pose", action="store_true")
    parser.add_argument("--no_wxbs", action="store_true")
    parser.add_argument(
        "--wxbs_max_pairs",
        type=none_or(int, old_off=at_most_zero),
        default=None,
        help="WxBS pairs (default none = all 34), round-robin over categories",
    )
    parser.add_argument("--wxbs_geometry", default="F", choices=["F", "H"])
    parser.add_argument("--device", default=None, help="torch device for the matchers")
    parser.add_argument("--weights", default=None, help="guided matcher weights")
    parser.add_argument("--cache_dir", type=Path, default=two_view.DEFAULT_CACHE)
    parser.add_argument("--output", type=Path, default=REPO_ROOT / "outputs" / "eval_two_view")
    parser.add_argument("--quiet", "-q", action="store_true")
    return parser


def publish(out: Path, note: dict, stem: str, result: dict, text: str, plot) -> None:
    """OUT/stem.json (with the machine), OUT/stem.md and OUT/stem.png; the Markdown printed."""
    result["machine"] = note
    tables.write_json(out / f"{stem}.json", result)
    (out / f"{stem}.md").write_text(text, encoding="utf-8")
    plot(result, out / f"{stem}.png")
    print(text)


def pose_benchmark(args, specs: list, note: dict) -> None:
    """The relative pose benchmark, published as OUTPUT/two_view.*."""
    result = two_view.run_pose_benchmark(
        args.scenes,
        specs,
        args.max_pairs,
        args.seed,
        args.min_covisible,
        args.max_num_features,
        estimator=args.estimator,
        reference_source=args.reference,
        cache_dir=args.cache_dir,
    )
    publish(
        args.output,
        note,
        "two_view",
        result,
        f"### Relative pose AUC ({sum(1 for _ in result['pairs'])} pairs; {note['date']}, "
        f"{note['torch_device']}, {note['cpu_count']} CPUs)\n\n{pose_table(result)}\n\n"
        f"Per scene:\n\n{pose_scene_table(result)}\n",
        plot_pose,
    )


def wxbs_benchmark(args, specs: list, note: dict) -> None:
    """The WxBS benchmark, published as OUTPUT/wxbs.*."""
    result = two_view.run_wxbs_benchmark(
        specs,
        max_pairs=args.wxbs_max_pairs,
        geometry=args.wxbs_geometry,
        max_num_features=args.max_num_features,
        cache_dir=args.cache_dir,
    )
    publish(
        args.output,
        note,
        "wxbs",
        result,
        f"### WxBS ({result['config']['num_pairs']} pairs, {args.wxbs_geometry} "
        f"by MAGSAC++; {note['date']})\n\n{wxbs_table(result)}\n\n"
        f"Per category (share @5 px):\n\n{wxbs_category_table(result)}\n",
        plot_wxbs,
    )


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    set_verbosity(False, args.quiet)
    extra = {"device": args.device, "weights": args.weights}
    specs = matcher_specs.parse_specs(args.matchers, extra)
    note = tables.machine_note()
    if not args.no_pose:
        pose_benchmark(args, specs, note)
    if not args.no_wxbs:
        wxbs_benchmark(args, specs, note)
    print(f"Results in {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
