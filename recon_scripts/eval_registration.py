"""Registration benchmark (paper Fig. 5a): registered ratio per scene, historical-only and all
images.

    python -m recon_scripts.eval_registration [--max_scenes 2] [--methods pycolmap raw guided]
    python -m recon_scripts.eval_registration --manifest datasets/ltll_manifest.json
        --root /data/LTLL --scan
    python -m recon_scripts.eval_registration --manifest datasets/shared_manifest.json
        --scenes lund_door_gtsfm --subsets all

Default manifest: the offline historical proxy (OUTPUT_PROXY/proxy_manifest.json, built first with
make_historical_proxy's defaults when missing). For each scene and subset (historical = historical
images + distractors; all = every image) it runs pycolmap's default pipeline and `reconstruct` with
each matcher spec, then reports the registered ratio of the largest model, the registrations that
agree with the reference model (lund_door_gtsfm's reference, the train scenes' pseudo-GT: rotation <
5°, centre < 10 % of the scene depth after a robust similarity alignment) and the distractors
registered (must be 0). Beside it (--wxbs_max_pairs, 0 = skip): the WxBS appearance-change pairs
(WGABS, WLABS, WGALBS), the closest real stand-in for historical photos, scored by hand-labelled
correspondences.

Writes OUTPUT/results.{md,json}, OUTPUT/registered.png (grouped bars per scene),
OUTPUT/wxbs_appearance.*.
"""

from __future__ import annotations

import sys
from pathlib import Path

from colmap_guided.log import logger, set_verbosity
from colmap_guided.paths import REPO_ROOT
from colmap_guided.workspace import Workspace
from recon_scripts import script_parser
from recon_scripts.evaluation import manifest as mf
from recon_scripts.evaluation import matcher_specs, proxy, registration, tables, two_view

DEFAULT_PROXY = REPO_ROOT / "outputs" / "historical_proxy"
WXBS_APPEARANCE = ("WGABS", "WLABS", "WGALBS")


def _parser():
    """The command line."""
    parser = script_parser(__doc__)
    parser.add_argument(
        "--manifest",
        type=Path,
        default=None,
        help="multi-scene manifest (default: the historical proxy)",
    )
    parser.add_argument(
        "--proxy_dir",
        type=Path,
        default=DEFAULT_PROXY,
        help="where the default proxy is (built if missing)",
    )
    mf.add_manifest_flags(
        parser,
        output=REPO_ROOT / "outputs" / "eval_registration",
        methods=["pycolmap", "raw", "guided"],
        methods_help="'pycolmap' (its default pipeline), 'pycolmap_mapping' (its database, this "
        "project's mapping) and/or matcher specs of the registry; a spec may carry feature "
        "options (guided:stretch_contrast_below=none)",
    )
    parser.add_argument("--max_rotation_deg", type=float, default=registration.MAX_ROTATION_DEG)
    parser.add_argument("--max_center_frac", type=float, default=registration.MAX_CENTER_FRAC)
    parser.add_argument(
        "--wxbs_max_pairs",
        type=int,
        default=6,
        help="WxBS appearance pairs beside the table (0 = skip)",
    )
    parser.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=None,
        help="random seeds of every mapper (pycolmap's default pipeline too), one run "
        "each; runs go to runs/seed<N>/ and the later seeds map the first seed's "
        "databases again (default: one run, unseeded pycolmap, reconstruct's seed 0)",
    )
    parser.add_argument(
        "--remap",
        action="store_true",
        help="with --resume: map the finished databases again (after a change "
        "of the mapping stage or of --threads), extraction and matching reused",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="threads of every mapper (pycolmap's default pipeline too); 1 = "
        "every seeded run repeats exactly (default: each pipeline's, all cores)",
    )
    return parser


def load_manifest(args, parser) -> tuple[Path, dict]:
    """The manifest's path and contents (the default proxy built if missing; --scan's scenes)."""
    manifest_path = args.manifest
    if manifest_path is None:
        manifest_path = args.proxy_dir / "proxy_manifest.json"
        if not manifest_path.is_file():
            logger.info("Building the historical proxy in %s", args.proxy_dir)
            proxy.build_proxy(args.proxy_dir)
    data = mf.load_manifest(manifest_path, args.root)
    if args.scan:
        if data["_root"] is None:
            parser.error("--scan needs --root")
        data["scenes"] = mf.scan_root(data["_root"])
        data["root"] = str(Path(data["_root"]).resolve())
        mf.save_manifest(args.output / "manifest_scanned.json", data)
    return manifest_path, data


def matcher_parts(methods: list[str]) -> list[str]:
    """The matcher specs of the methods other than pycolmap's, without their stage options."""
    return [
        registration.split_stage_options(m)[0]
        for m in methods
        if m not in registration.PYCOLMAP_METHODS
    ]


def evaluate_scenes(args, data: dict, scenes: list, manifest_path: Path, extra: dict) -> list:
    """Every method on every scene, subset and seed; results.json rewritten after each subset."""
    tol = {"max_rotation_deg": args.max_rotation_deg, "max_center_frac": args.max_center_frac}
    results = []
    layouts = args.output / "scenes"
    for scene in scenes:
        for subset in args.subsets:
            scene_dir = mf.layout_scene(data, scene, subset, layouts)
            if scene_dir is None:
                logger.info("%s: fewer than 2 %s images, skipped.", scene["name"], subset)
                continue
            for seed in args.seeds or [None]:
                first = (
                    registration.seed_runs_dir(scene_dir, args.seeds[0])
                    if args.seeds and seed != args.seeds[0]
                    else None
                )
                results.append(
                    registration.evaluate_scene(
                        scene_dir,
                        args.methods,
                        extra_conf=extra,
                        resume=args.resume,
                        seed=seed,
                        databases_from=first,
                        remap=args.remap,
                        threads=args.threads,
                        **tol,
                    )
                )
            tables.write_json(
                args.output / "results.json",
                {"manifest": str(manifest_path), "methods": args.methods, "scenes": results},
            )
    return results


def wxbs_text(output: Path, max_pairs: int, specs: list[str], extra: dict) -> str:
    """The WxBS appearance-change table of ``specs``, its results written; "" when skipped."""
    if not (max_pairs and specs):
        return ""
    w = two_view.run_wxbs_benchmark(
        specs, max_pairs=max_pairs, categories=WXBS_APPEARANCE, extra_conf=extra
    )
    tables.write_json(output / "wxbs_appearance.json", w)
    rows = [
        [label, *r["summary"]["share"], f"{r['summary']['mean_matches']:.0f}"]
        for label, r in w["results"].items()
    ]
    return (
        f"\nWxBS appearance-change pairs ({w['config']['num_pairs']}"
        f" of {', '.join(WXBS_APPEARANCE)}; share of hand-labelled "
        "correspondences consistent with the estimated F):\n\n"
        + tables.markdown_table(["matcher", "@3 px", "@5 px", "@10 px", "matches"], rows)
        + "\n"
    )


def main(argv=None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    set_verbosity(False, args.quiet)
    try:  # refused before any work: a folder of the user's files, or one holding the photos
        Workspace.claim(args.output, "evaluation").record(*registration.REPORT_FILES, "scenes")
    except ValueError as err:
        logger.error("%s", err)
        return 2
    manifest_path, data = load_manifest(args, parser)
    scenes = mf.select_scenes(data, args.scenes, args.max_scenes)
    if not scenes:
        logger.error("%s lists no scene with images (LTLL: pass --root and --scan).", manifest_path)
        return 2
    specs = matcher_parts(args.methods)
    matcher_specs.parse_specs(specs)  # ValueError now, not after hours
    extra = {"device": args.device, "weights": args.weights}
    results = evaluate_scenes(args, data, scenes, manifest_path, extra)
    distractors = sum(
        len(r["methods"][m].get("distractors_registered", []))
        for r in results
        for m in args.methods
        if m in r["methods"]
    )
    extra_text = f"\n\nDistractors registered, all runs: {distractors} (must be 0)\n"
    extra_text += wxbs_text(args.output, args.wxbs_max_pairs, specs, extra)
    text = registration.write_report(
        args.output, data.get("name", "manifest"), manifest_path, args.methods, results, extra_text
    )
    print(text)
    print(f"Results in {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
