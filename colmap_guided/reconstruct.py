"""The whole pipeline: images → SIFT → pairs → (guided) matching → verification → mapping → model
check → report.

    python -m colmap_guided reconstruct SCENE_DIR [--matcher guided|raw|...]
        [--mapper incremental|global|hierarchical] [--output DIR]

Photos are read from SCENE_DIR/images (or --image_path) and never written to. Everything the run
makes goes to the workspace (SCENE_DIR/colmap_guided, or --output): database.db, sparse/N,
report.json, report.html. A killed run started again continues from the database.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from . import (
    cards,
    escalate,
    export,
    features,
    html_report,
    join,
    mapping,
    match,
    model_check,
    recheck,
    report,
)
from . import database as dbio
from .cli import add_pipeline_flags, conf_from_args
from .log import add_verbosity_flags, logger
from .matchers import Matcher
from .pipeline import PipelineConf
from .workspace import Workspace

ESCALATION_PAIRS = "escalation_pairs.txt"  # the pairs escalate.py chose, in the last round
JOIN_PAIRS = "join_pairs.txt"  # the pairs join.py matched, for the last two models it tried
CHECK_PAIRS = "check_pairs.txt"  # the pairs recheck.py matched
KEPT_PAIRS = escalate.KEPT_PAIRS
# Everything a run writes in its workspace: --overwrite removes these and nothing else.
WRITES = (
    "database.db",
    "database.db-wal",
    "database.db-shm",
    "database.db-journal",
    "sparse",
    "sparse.partial",
    "report.json",
    "report.json.partial",
    "report.html",
    "report.html.partial",
    ESCALATION_PAIRS,
    JOIN_PAIRS,
    CHECK_PAIRS,
    KEPT_PAIRS,
    KEPT_PAIRS + ".partial",
    "geo",  # georeference's
    cards.PANELS,
)


def resolve_paths(
    scene_dir: Path, image_path: Path | None, output: Path | None
) -> tuple[Path, Path]:
    """(photos, workspace); a workspace that would put a user's file at risk is refused here, before
    anything reads a database in it."""
    scene_dir = Path(scene_dir)
    if image_path is None:
        image_path = scene_dir / "images" if (scene_dir / "images").is_dir() else scene_dir
    image_path = Path(image_path).resolve()
    if output is None:
        # Never inside the photos' folder: SCENE_DIR/colmap_guided when photos are in
        # SCENE_DIR/images, else a sibling folder SCENE_DIR_colmap_guided.
        output = (
            scene_dir / "colmap_guided"
            if image_path != scene_dir.resolve()
            else scene_dir.parent / f"{scene_dir.name}_colmap_guided"
        )
    return image_path, Workspace.check(output, "reconstruct", keep=(image_path,))


def _registered(models: dict, which=(0,)) -> set[str]:
    """The photos of the largest model (``which``: of those models)."""
    return set().union(*(mapping.registered(models[k]) for k in which if k in models))


def _escalate(
    conf: PipelineConf,
    matcher: Matcher,
    models: dict,
    mapping_conf: dict,
    usable: list[str],
    selected: list[tuple[str, str]],
    output: Path,
    image_path: Path,
    timings: dict,
    done: set = frozenset(),
    extend: bool = False,
    cuts: list[dict] = (),
) -> tuple[dict, list[dict]]:
    """``escalate``'s rounds: the photos left out of the model (and out of every model, without
    ``other_models``) get their deferred, gated and cheaply matched pairs matched with the full
    matcher (but ``done``), then the model (of the ``usable`` photos, mapped with ``mapping_conf``)
    is extended with them; with ``extend`` (photos taken out by the check) the first round maps
    even without pairs. The photos that ``cuts`` (``join.split_models``) put away from the model
    are kept out of it. Returns the models and what each round did."""
    database_path, rounds, full = output / "database.db", [], None
    for _ in range(conf.escalation.rounds):
        registered = _registered(models)
        elsewhere = _registered(models, [k for k in models if k != 0])
        left, candidates = set(usable) - registered, selected
        # other models' photos (all without other_models, or those cut away) stay out of it
        apart = elsewhere if not conf.escalation.other_models else join.cut_away(cuts, registered)
        if apart:
            left -= apart
            candidates = [pair for pair in selected if not set(pair) & apart]
            mapping_conf = {**mapping_conf, "image_names": sorted(left | registered)}
        todo = escalate.pairs_to_escalate(
            database_path,
            left,
            candidates,
            done,
            conf.escalation.pairs_per_photo,
            escalate.read_kept(output / KEPT_PAIRS),
            elsewhere,
            conf.escalation.orphan_after,
        )
        if not todo and not extend:
            break
        logger.info("Escalation: %d pairs of %d photos left out of the model", len(todo), len(left))
        start, done, extend = time.time(), done | {key[2:] for key in todo}, False
        if todo:
            full = full or escalate.full_matcher(matcher)
            pairs_path, kept_path = output / ESCALATION_PAIRS, output / KEPT_PAIRS
            match.rematch(database_path, image_path, full, conf, todo, pairs_path, kept_path)
        timings["escalate_match"] = timings.get("escalate_match", 0) + time.time() - start
        start = time.time()
        models = mapping.run_mapping(
            database_path, image_path, output / "sparse", mapping_conf, bool(models)
        )
        timings["escalate_map"] = timings.get("escalate_map", 0) + time.time() - start
        now = _registered(models)
        rounds.append(
            {
                "photos": sorted(left),
                "pairs": len(todo),
                "registered": sorted(now - registered),
            }
        )
        logger.info("Escalation registered %d more photo(s)", len(now - registered))
        if not now - registered:  # the next round's pairs are less similar still
            break
    return models, rounds


def _check(conf, matcher, models, selected, output, image_path, timings) -> tuple[dict, set, dict]:
    """``recheck``: photos placed on cheap or thin evidence checked by the full matcher (made only
    where there is a pair to match), those it puts elsewhere taken out (the models rewritten).
    Returns the models, the pairs matched and the check's record."""
    start, database_path = time.time(), output / "database.db"
    rematch = lambda todo: match.rematch(  # noqa: E731
        database_path,
        image_path,
        escalate.full_matcher(matcher),
        conf,
        todo,
        output / CHECK_PAIRS,
        output / KEPT_PAIRS,
    )
    check_conf = {**conf.escalation.to_dict(), **conf.mapping.to_dict()}
    done, record = recheck.check_models(
        database_path, models, selected, output / KEPT_PAIRS, check_conf, rematch
    )
    if record["taken_out"]:
        models = mapping.write_models(
            output / "sparse", [rec for rec in models.values() if rec.num_reg_images() >= 2]
        )
    if record["pairs"]:
        timings["check"] = time.time() - start
    return models, done, record


def reconstruct(
    scene_dir: Path,
    image_path: Path | None = None,
    output: Path | None = None,
    matcher: str | Matcher | None = None,
    matcher_conf: dict | None = None,
    pairs_path: str | Path | None = None,
    feature_conf: dict | None = None,
    verification_conf: dict | None = None,
    mapping_conf: dict | None = None,
    overwrite: bool = False,
    match_options: dict | None = None,
    conf: PipelineConf | None = None,
) -> dict:
    """``conf``: the options of every stage (default ``PipelineConf()``); the keyword options
    given (not None) go over it: ``matcher`` (a ``matchers.PRESETS`` name or auto) and
    ``matcher_conf``, ``pairs_path`` (a pairs file or auto|exhaustive|retrieval|sequential) and
    ``match_options`` (num_neighbors, executor, ray_address): ``PairsConf``, and the sections'
    dicts ``feature_conf``, ``verification_conf``, ``mapping_conf``."""
    image_path, output = resolve_paths(scene_dir, image_path, output)
    conf = (conf or PipelineConf()).over(
        matcher,
        matcher_conf,
        feature_conf,
        {"pairs": pairs_path, **(match_options or {})},
        verification_conf,
        mapping_conf,
    )
    # decided once, here, before anything runs (a rerun continues with the database's features)
    existing = None if overwrite else features.existing_feature_type(output / "database.db")
    conf = conf.resolve(existing)
    image_names = features.list_images(image_path)
    # made now: a missing or broken --weights file fails before the extraction
    matcher = conf.matcher.build()
    features.check_matcher_features(matcher, conf.features.type)
    Workspace.claim(output, "reconstruct", keep=(image_path,), overwrite=overwrite).record(*WRITES)
    database_path = output / "database.db"
    if database_path.exists():
        with dbio.open_database(database_path) as db:
            dbio.check_image_folder(db, image_path)
    timings = {}
    photos = _extract(database_path, image_path, output, image_names, conf.features, timings)
    match_stats = match.match_pairs(
        database_path,
        image_path,
        matcher,
        conf,
        enough=conf.escalation.enough,
        strong_inliers=conf.escalation.strong_inliers,
        join_tries=conf.escalation.join_tries,
        apart=photos.panels.values(),
        orphan_after=conf.escalation.orphan_after,
        kept_path=output / KEPT_PAIRS,
    )
    timings["match"] = match_stats.pop("match_time")
    timings["verify"] = match_stats.pop("verify_time")
    models = _map(database_path, image_path, output, photos, conf, matcher, match_stats, timings)
    result = _result(scene_dir, image_path, output, photos, conf, match_stats, models, timings)
    result = cards.renamed(result, cards.colmap_names(result))
    _write_reports(output, image_path, result, models)
    return result


@dataclasses.dataclass
class Photos:
    """What extraction made of the photos: their names (collage panels in place of their cards),
    those skipped with why, and the scanned cards' layouts, panels and masked keypoints."""

    names: list[str]
    skipped: dict
    card_conf: dict
    layouts: dict
    panels: dict
    masked: dict
    prints: dict = dataclasses.field(default_factory=dict)  # repeated prints, found after matching

    @property
    def usable(self) -> list[str]:
        return [name for name in self.names if name not in self.skipped]


def _extract(database_path, image_path, output, image_names, feature_conf, timings) -> Photos:
    """Cards' layouts and collage panels, then features; at least 2 usable photos."""
    start, feature_conf = time.time(), feature_conf.to_dict()
    card_conf = cards.check_conf(feature_conf["cards"])
    layouts = cards.find_layouts(image_path, image_names, card_conf)
    image_names, panels = cards.split_collages(image_path, output, image_names, layouts)
    extraction = features.extract(database_path, image_path, image_names, feature_conf)
    masked = cards.mask_keypoints(database_path, layouts, card_conf)
    timings["extract"] = time.time() - start
    photos = Photos(image_names, extraction["skipped"], card_conf, layouts, panels, masked)
    if len(photos.usable) < 2:
        raise ValueError(
            f"Only {len(photos.usable)} usable image(s) in {image_path} ({len(photos.skipped)} "
            "skipped): a reconstruction needs at least 2 overlapping photos of the landmark; "
            "add photos and run again."
        )
    return photos


def _map(database_path, image_path, output, photos, conf, matcher, match_stats, timings) -> dict:
    """Mapping of the photos but repeated prints' copies, a weaker start where no model starts,
    escalation's rounds, then models joined; the rounds and joins go to ``match_stats``."""
    start, sparse_path = time.time(), output / "sparse"
    photos.prints = cards.repeated_prints(database_path, photos.card_conf)
    prints = photos.prints
    mapped = [name for name in photos.usable if name not in prints] if prints else None
    mapping_conf = {**conf.mapping.to_dict(), "image_names": mapped}
    models = mapping.run_mapping(database_path, image_path, sparse_path, mapping_conf)
    # recorded for the report; escalation may make a model later
    match_stats["weak_start"] = not models and match_stats["num_verified_pairs"] > 0
    if match_stats["weak_start"]:
        models = mapping.map_weak_start(database_path, image_path, sparse_path, mapping_conf)
    match_stats["splits"] = []
    if conf.escalation.cut_models:
        models, match_stats["splits"] = join.split_models(models, sparse_path)
    timings["map"] = time.time() - start
    selected = match_stats.pop("selected")
    models, done, match_stats["check"] = _check(
        conf, matcher, models, selected, output, image_path, timings
    )
    models, match_stats["escalation"] = _escalate(
        conf,
        matcher,
        models,
        mapping_conf,
        mapped or photos.usable,
        selected,
        output,
        image_path,
        timings,
        done,
        bool(match_stats["check"]["taken_out"]),
        match_stats["splits"],
    )
    start = time.time()
    if conf.escalation.cut_models:
        models, cuts = join.split_models(models, sparse_path)
        match_stats["splits"] += cuts
    models, match_stats["joins"] = join.join_models(
        database_path,
        image_path,
        sparse_path,
        models,
        matcher,
        conf,
        mapping_conf,
        match_stats.pop("descriptors"),
        output / JOIN_PAIRS,
        escalate.read_kept(output / KEPT_PAIRS),
        match_stats["splits"],
    )
    if match_stats["joins"]:
        timings["join"] = time.time() - start
    return models


def _result(scene_dir, image_path, output, photos, conf, match_stats, models, timings) -> dict:
    """report.json's content."""
    stats = report.model_statistics(models, photos.names)
    registered = set(stats["registered_images"])
    each = model_check.check_each(models)
    checked = model_check.check_models(models, each=each)
    for problem in checked["problems"]:
        logger.warning("Model check: %s", problem)
    eras = report.read_manifest(Path(scene_dir) / "manifest.json")
    database_path, sparse_path = output / "database.db", output / "sparse"
    entries = report.model_entries(models, each, eras)
    for entry in entries:  # every model is a result: its points and COLMAP text beside it
        entry["exports"] = export.export_model(models[entry["index"]], output / entry["path"])
    weak_start, prints = match_stats.pop("weak_start"), photos.prints
    result = {
        "scene": Path(scene_dir).resolve().name,
        "image_path": str(image_path),
        "database_path": str(database_path),
        "sparse_path": str(sparse_path),
        "report_path": str(output / "report.json"),
        "matcher": match_stats.pop("matcher"),
        "options": {
            "features": conf.features.to_dict(),
            "verification": match_stats.pop("verification"),
            "mapping": conf.mapping.to_dict(),
            "pairs": match_stats.pop("pairs"),
        },
        "model": stats,
        "models": entries,
        "model_check": checked,
        "weak_start": mapping.WEAK_START if weak_start else None,
        "eras": report.era_ratios(eras, stats["registered_images"], photos.names) if eras else {},
        "database": match_stats,
        "skipped_images": photos.skipped,
        **cards.card_report(
            photos.layouts, photos.panels, photos.masked, photos.prints, registered
        ),
        "manifest_path": str(Path(scene_dir).resolve() / "manifest.json") if eras else None,
        "exports": entries[0]["exports"] if entries else {},
        "timings": timings,
        **{key: stats[key] for key in report.SUMMARY_KEYS},
    }
    result["unregistered"] = report.explain_unregistered(
        database_path,
        models,
        photos.names,
        photos.skipped,
        result["options"]["verification"]["min_num_inliers"],
        set(match_stats.get("orphans", [])),
    )
    for name, why in match_stats["check"]["taken_out"].items():
        if name in result["unregistered"]:
            result["unregistered"][name]["reason"] += recheck.TAKEN_OUT.format(why=why)
    result["unregistered"].update(cards.explain_prints(prints, registered))
    if not models:
        result["no_model"] = report.explain_no_model(database_path, conf.mapping.to_dict(), prints)
    return result


def _write_reports(output: Path, image_path: Path, result: dict, models: dict) -> None:
    """report.html, then report.json (the run's last file)."""
    result["html_report_path"] = str(output / "report.html")
    try:
        html_report.write_html_report(
            output / "report.html",
            result,
            html_report.match_panels(
                {result["matcher"]["name"]: output / "database.db"}, image_path
            ),
            models.get(0),
        )
    except Exception as err:  # noqa: BLE001
        # the reconstruction is done; a failed page must not hide it
        logger.warning("Could not write the HTML report (%s); report.json is complete.", err)
        result.pop("html_report_path")
    report.write_report(output / "report.json", result)


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "reconstruct",
        help="SIFT, guided matching, verification, mapping and a report for one scene",
    )
    parser.add_argument(
        "scene_dir", type=Path, help="folder with images/ (or the photos themselves)"
    )
    parser.add_argument(
        "--image_path", type=Path, default=None, help="photos folder (default SCENE_DIR/images)"
    )
    parser.add_argument(
        "--output", type=Path, default=None, help="workspace (default SCENE_DIR/colmap_guided)"
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="remove what earlier runs wrote in the workspace (nothing else) and start fresh",
    )
    add_pipeline_flags(parser, reconstruct=True)
    add_verbosity_flags(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    result = reconstruct(
        args.scene_dir,
        image_path=args.image_path,
        output=args.output,
        overwrite=args.overwrite,
        conf=conf_from_args(args),
    )
    print(report.summary_text(result))
