"""Command line: `python -m colmap_guided {reconstruct,match,coarse} ...`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .log import logger, set_verbosity


def _add_common(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--verbose", "-v", action="store_true", help="debug messages and COLMAP's own log")
    group.add_argument("--quiet", "-q", action="store_true", help="only warnings and the final summary")


def build_parser() -> argparse.ArgumentParser:
    from . import features, match

    parser = argparse.ArgumentParser(prog="python -m colmap_guided", description="Guided feature matching for COLMAP (Darmon et al., 3DV 2020).")
    sub = parser.add_subparsers(dest="command", required=True)

    rec = sub.add_parser("reconstruct", help="SIFT, guided matching, verification, incremental mapping and a report for one scene")
    rec.add_argument("scene_dir", type=Path, help="folder with images/ (or the photos themselves)")
    rec.add_argument("--image_path", type=Path, default=None, help="photos folder (default SCENE_DIR/images)")
    rec.add_argument("--output", type=Path, default=None, help="workspace (default SCENE_DIR/colmap_guided)")
    rec.add_argument("--camera_mode", default=features.default_conf["camera_mode"], choices=sorted(features.CAMERA_MODES), help="camera grouping (default auto, as COLMAP)")
    rec.add_argument("--camera_model", default=features.default_conf["camera_model"])
    rec.add_argument("--overwrite", action="store_true", help="delete the workspace and start fresh")
    match.add_matcher_arguments(rec)
    _add_common(rec)

    mat = sub.add_parser("match", help="drop-in replacement of COLMAP's exhaustive_matcher on an existing database")
    mat.add_argument("--database_path", type=Path, required=True)
    mat.add_argument("--image_path", type=Path, required=True)
    mat.add_argument("--overwrite", action="store_true", help="delete existing matches and two-view geometries first")
    match.add_matcher_arguments(mat)
    _add_common(mat)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    set_verbosity(args.verbose, args.quiet)
    from . import match
    from .matchers import DEFAULT_MATCHER

    matcher = args.matcher or DEFAULT_MATCHER
    try:
        if args.command == "reconstruct":
            from .reconstruct import reconstruct
            from .report import summary_text

            result = reconstruct(
                args.scene_dir,
                image_path=args.image_path,
                output=args.output,
                matcher=matcher,
                matcher_conf=match.matcher_conf_from_args(args, matcher),
                pairs_path=args.pairs,
                feature_conf={"camera_mode": args.camera_mode, "camera_model": args.camera_model},
                overwrite=args.overwrite,
            )
            print(summary_text(result))
        elif args.command == "match":
            stats = match.match_database(args.database_path, args.image_path, args.pairs, matcher, match.matcher_conf_from_args(args, matcher), overwrite=args.overwrite)
            print(f"{stats['num_verified_pairs']}/{stats['num_pairs']} pairs verified, {stats['num_inlier_matches']} inlier matches in {args.database_path}")
    except (ValueError, FileNotFoundError, RuntimeError) as err:
        logger.error("%s", err)
        return 2
    except KeyboardInterrupt:
        logger.error("Interrupted; run the same command again to continue from where it stopped.")
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
