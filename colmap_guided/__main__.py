"""Command line: `python -m colmap_guided {reconstruct,localize,georeference,match,export,import,
report} ...`."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from .conf import add_conf_flags, at_most_zero, conf_from_flags, none_or
from .log import logger, set_verbosity

if TYPE_CHECKING:
    from .pipeline import PipelineConf

# PipelineConf's options given as reconstruct's and match's flags, help from their comments:
# option -> flag (some flags keep the shorter name they had)
FEATURE_FLAGS = {
    "camera_mode": "camera_mode",
    "camera_model": "camera_model",
    "stretch_contrast_below": "stretch_contrast_below",
    "smooth_noise_above": "smooth_noise_above",
    "type": "features",
}
ALIKED_FLAGS = {"weights": "aliked_weights"}
MAPPING_FLAGS = {"mapper": "mapper", "random_seed": "seed", "num_threads": "threads"}
# of the matcher's conf (the guided matcher's comments); not given: the chosen matcher's own
MATCHER_FLAGS = ["ratio", "weights", "device"]
LOCALIZE_MATCHER_FLAGS = ["weights", "device"]  # localize keeps the matcher's ratio


def _add_pipeline_flags(parser: argparse.ArgumentParser, reconstruct: bool) -> None:
    """reconstruct's (all) or match's (matcher and pairs) options of ``pipeline.PipelineConf``."""
    from . import escalate, features, mapping, pipeline
    from .executor import EXECUTORS
    from .features import aliked
    from .matchers import AUTO

    if reconstruct:
        group = parser.add_argument_group("feature options")
        add_conf_flags(
            group,
            features,
            FEATURE_FLAGS,
            types=dict.fromkeys(
                ["stretch_contrast_below", "smooth_noise_above"],
                none_or(float, old_off=lambda text: text == "off"),
            ),
            choices={
                "camera_mode": sorted(features.CAMERA_MODES),
                "type": [*sorted(features.FEATURE_TYPES), AUTO],
            },
            what="feature",
            flags=FEATURE_FLAGS,
            defaults={"type": pipeline.FeatureConf().type},
        )
        add_conf_flags(group, aliked, ALIKED_FLAGS, types={"weights": str}, flags=ALIKED_FLAGS)
        group = parser.add_argument_group("mapping options")
        add_conf_flags(
            group,
            mapping,
            MAPPING_FLAGS,
            types={"random_seed": none_or(int, old_off=lambda text: int(text) < 0)},
            choices={"mapper": mapping.MAPPERS},
            flags=MAPPING_FLAGS,
        )
        group = parser.add_argument_group("escalation options (where the learned matcher runs)")
        add_conf_flags(group, escalate, types={"enough": none_or(int)})
    group = _add_matcher_flags(parser, MATCHER_FLAGS)
    add_conf_flags(
        group,
        pipeline,
        [f.name for f in dataclasses.fields(pipeline.PairsConf)],
        types={"ray_address": str},
        choices={"executor": EXECUTORS},
        what="pairs",
    )


def _add_matcher_flags(parser: argparse.ArgumentParser, keys: list[str]):
    """--matcher and the matcher options ``keys`` (not given: the chosen matcher's own), in a
    "matching options" group, which it returns."""
    from . import pipeline
    from .matchers import AUTO, PRESETS
    from .matchers.guided import GuidedMatcher

    group = parser.add_argument_group("matching options")
    add_conf_flags(group, pipeline, ["matcher"], choices={"matcher": [*sorted(PRESETS), AUTO]})
    add_conf_flags(
        group,
        GuidedMatcher,
        keys,
        types={"ratio": none_or(float, old_off=at_most_zero), "weights": str},
        what="matcher",
        defaults=dict.fromkeys(keys, argparse.SUPPRESS),
    )
    return group


def _add_localize_flags(parser: argparse.ArgumentParser) -> None:
    """localize's options: its retrieval's k and, as reconstruct's, the matcher (auto: the one
    reconstruct picks for the workspace database's features), its weights and device."""
    from . import localize

    add_conf_flags(parser, localize, ["num_images"])
    _add_matcher_flags(parser, LOCALIZE_MATCHER_FLAGS)


def conf_from_args(args: argparse.Namespace) -> PipelineConf:
    """The ``PipelineConf`` of reconstruct's or match's flags, without the matcher options
    (``matcher_conf_from_args``: checked against the matcher once it is chosen)."""
    from . import escalate, features, mapping, pipeline
    from .features import aliked

    pairs = [f.name for f in dataclasses.fields(pipeline.PairsConf)]
    conf = {"matcher": {"name": args.matcher}, "pairs": conf_from_flags(args, pipeline, pairs)}
    if args.command == "reconstruct":
        given = conf_from_flags(args, aliked, ALIKED_FLAGS, flags=ALIKED_FLAGS)
        conf["features"] = {
            **conf_from_flags(args, features, FEATURE_FLAGS, "feature", FEATURE_FLAGS),
            "aliked": {k: v for k, v in given.items() if v is not None},
        }
        conf["mapping"] = conf_from_flags(args, mapping, MAPPING_FLAGS, "mapping", MAPPING_FLAGS)
        conf["escalation"] = conf_from_flags(args, escalate, list(escalate.default_conf))
    return pipeline.PipelineConf.from_dict(conf)


def matcher_conf_from_args(args: argparse.Namespace, matcher: str) -> dict:
    """The matcher options given as flags; one that ``matcher`` (a preset) does not take is a
    one-line ValueError naming a matcher that takes it."""
    from .matchers import PRESETS, preset
    from .matchers.guided import GuidedMatcher

    given = conf_from_flags(args, GuidedMatcher, MATCHER_FLAGS, "matcher")
    unknown = sorted(set(given) - set(preset(matcher)[0].default_conf))
    if unknown:
        users = sorted(name for name in PRESETS if unknown[0] in preset(name)[0].default_conf)
        raise ValueError(
            f"--{unknown[0]} does not apply to the {matcher} matcher; pass "
            f"--matcher {users[0] if users else '...'} (or another that takes it)"
        )
    return given


def _matcher_conf(args, matcher: str) -> dict:
    """``matcher_conf_from_args``; an option the matcher does not take is a usage error (exit
    status 1) before anything runs."""
    try:
        return matcher_conf_from_args(args, matcher)
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
    from .html_report import rewrite_report

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
        "--overwrite",
        action="store_true",
        help="remove what earlier runs wrote in the workspace (nothing else) and start fresh",
    )
    _add_pipeline_flags(rec, reconstruct=True)
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
    _add_localize_flags(loc)
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
    _add_pipeline_flags(mat, reconstruct=False)
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

    geo = sub.add_parser(
        "georeference",
        help="place the model on the Earth from a few photos' map positions or GPS EXIF: "
        "each photo's camera as KML PhotoOverlays and GeoJSON",
    )
    geo.add_argument(
        "workspace", type=Path, help="the --output folder of a reconstruct run (holds sparse/0)"
    )
    geo.add_argument(
        "--control",
        type=Path,
        default=None,
        help="CSV with the header name,latitude,longitude[,altitude]: where a few photos were "
        "taken (WGS84 degrees, metres above sea level); added to the photos' GPS EXIF",
    )
    geo.add_argument(
        "--image_path",
        type=Path,
        default=None,
        help="the photos' folder, if moved since reconstruct (only read)",
    )
    _add_common(geo)

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
    rep.add_argument(
        "--num_pairs",
        type=int,
        default=inspect.signature(rewrite_report).parameters["num_pairs"].default,
        help="pairs drawn: those with the most inliers (default: %(default)s)",
    )
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
            from .pipeline import MatcherConf
            from .reconstruct import reconstruct, resolve_paths
            from .report import summary_text

            conf = conf_from_args(args)
            output = resolve_paths(args.scene_dir, args.image_path, args.output)[1]
            # e.g. a missing --aliked_weights: the one line
            feature_conf = features.check_conf(conf.features.to_dict())
            # decided here, where --ratio/--device/--weights are checked against the matcher
            existing = (
                None if args.overwrite else features.existing_feature_type(output / "database.db")
            )
            chosen, feature_type, _ = resolve_auto(conf.matcher.name, feature_conf, None, existing)
            conf = dataclasses.replace(
                conf,
                features=conf.features.over({"type": feature_type}),
                matcher=MatcherConf(chosen, _matcher_conf(args, chosen)),
            )
            result = reconstruct(
                args.scene_dir,
                image_path=args.image_path,
                output=args.output,
                overwrite=args.overwrite,
                conf=conf,
            )
            print(summary_text(result))
        elif args.command == "localize":
            from . import localize
            from .matchers.guided import GuidedMatcher

            given = conf_from_flags(args, GuidedMatcher, LOCALIZE_MATCHER_FLAGS, "matcher")
            matcher_conf = {k: v for k, v in given.items() if v is not None}
            conf = conf_from_flags(args, localize, ["num_images"])
            out = localize.localize(
                args.workspace, args.photos, args.matcher, matcher_conf, conf, add=args.add
            )
            print(localize.summary_text(out))
        elif args.command == "georeference":
            from .georeference import georeference, summary_text

            print(summary_text(georeference(args.workspace, args.control, args.image_path)))
        elif args.command == "match":
            from . import database, features, match
            from .matchers import AUTO, resolve_auto
            from .pipeline import MatcherConf

            conf = conf_from_args(args)
            with database.open_database(args.database_path) as db:
                feature_type = features.database_feature_type(db)
            matcher, _, options = resolve_auto(conf.matcher.name, AUTO, None, feature_type)
            options = {**options, **_matcher_conf(args, matcher)}
            stats = match.match_database(
                args.database_path,
                args.image_path,
                overwrite=args.overwrite,
                conf=dataclasses.replace(conf, matcher=MatcherConf(matcher, options)),
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
