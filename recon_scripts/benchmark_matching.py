"""Benchmark of the matchers on real pairs from ../shared/data (not a timed test).

For every related pair (same scene: sacre_coeur_hloc, lund_door_gtsfm, lightglue_assets, WxBS
appearance/illumination categories) it reports the COLMAP-verified inliers (pycolmap
estimate_two_view_geometry, the pipeline's options: >= 15 inliers, guided and LightGlue >= their
min_inliers) of raw, guided, guided_epipolar, guided_homography and guided_colmap (COLMAP's own
guided_matching), or of any preset on ALIKED (``--features aliked --matchers raw guided lightglue
guided_lightglue``: the learned paths' guard), whether the verified geometry agrees with the
reference correspondences where there are some (WxBS hand-labelled corrs.txt; lund_door's reference
model), and the wall time of raw vs guided (coarse extraction of both images + coarse match +
eq. 1) on the same pair. On pairs of unrelated images (different scenes) it reports the share that
verifies per matcher: guided matching must not manufacture geometry more often than raw matching.

    python -m recon_scripts.benchmark_matching [--pairs_per_set 3] [--unrelated 24]
        [--json out.json]
    python -m recon_scripts.benchmark_matching --sweep   # guided options grid on the same pairs
    python -m recon_scripts.benchmark_matching --features aliked
        --matchers raw guided lightglue guided_lightglue

Markdown tables go to stdout, everything to --json. Features are the pipeline's own
(``features.extract_features``, its default options), extracted into a COLMAP database in
--cache_dir and read back through ``colmap_guided.database``, so reruns only pay for matching.
"""

from __future__ import annotations

import itertools
import json
import time
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np
import pycolmap
import torch

from colmap_guided import database as dbio
from colmap_guided import features, verify
from colmap_guided.log import logger
from colmap_guided.matchers import get_matcher, resolve_auto
from colmap_guided.matchers.base import ImageData
from colmap_guided.matchers.guided import GuidedMatcher
from colmap_guided.paths import shared_data_dir
from recon_scripts import script_parser
from recon_scripts.evaluation import matcher_specs

BASELINES = ["raw", "guided", "guided_epipolar", "guided_homography", "guided_colmap"]
WXBS_RELATED = ["WGABS", "WGALBS", "WGLBS", "WLABS"]  # appearance / illumination changes


# ------------------------------------------------------------------------------------------------
# Features and pairs
# ------------------------------------------------------------------------------------------------


def image_name(path: Path) -> str:
    """A photo's image name in the benchmark's databases (its path below the data folder)."""
    return path.relative_to(shared_data_dir()).as_posix()


def extract(pairs: list[dict], kind: str, cache_dir: Path) -> Path:
    """The pipeline's ``kind`` features (``features.extract_features``, its default options) of
    every image of ``pairs``, in the COLMAP database ``cache_dir/<kind>.db`` (a rerun extracts only
    the images it lacks); returns its path."""
    names = sorted({image_name(pair[k]) for pair in pairs for k in ("a", "b")})
    database = cache_dir / f"{kind}.db"
    cache_dir.mkdir(parents=True, exist_ok=True)
    stats = features.extract_features(database, shared_data_dir(), names, {"type": kind})
    if stats["skipped"]:
        raise ValueError(f"The pipeline skips benchmark images: {stats['skipped']}")
    return database


def read_pair(database: Path, pair: dict) -> tuple[ImageData, ImageData]:
    """The two images of ``pair`` as the database holds them, new objects (no matcher cache carried
    over from another pair)."""
    with dbio.open_database(database) as db:
        a, b = (
            dbio.read_image_data(db, dbio.read_image(db, image_name(pair[k])), shared_data_dir())
            for k in ("a", "b")
        )
    # no database camera: matchers and verify_matches use COLMAP's default camera of the image size
    return replace(a, camera=None), replace(b, camera=None)


def wxbs_corrs(pair_dir: Path) -> np.ndarray:
    return np.loadtxt(pair_dir / "corrs.txt").reshape(-1, 4)


def lund_door_corrs(name_a: str, name_b: str) -> np.ndarray:
    """Reference correspondences of two lund_door images: 2D observations of shared 3D points."""
    rec = pycolmap.Reconstruction(shared_data_dir() / "lund_door_gtsfm" / "colmap_ground_truth")
    by_name = {im.name: im for im in rec.images.values()}
    obs = []
    for name in (name_a, name_b):
        im = by_name[name]
        obs.append({p.point3D_id: p.xy for p in im.points2D if p.has_point3D()})
    common = sorted(set(obs[0]) & set(obs[1]))
    return np.array([[*obs[0][i], *obs[1][i]] for i in common], np.float64).reshape(-1, 4)


def related_pairs(per_set: int) -> list[dict]:
    """Same-scene pairs: consecutive images of each set, plus WxBS A/L pairs with reference
    corrs."""
    data = shared_data_dir()
    pairs = []
    for name in ("sacre_coeur_hloc", "lund_door_gtsfm"):
        images = sorted((data / name / "images").iterdir())
        for a, b in list(itertools.pairwise(images))[:per_set]:
            corrs = lund_door_corrs(a.name, b.name) if name == "lund_door_gtsfm" else None
            pairs.append({"set": name, "a": a, "b": b, "corrs": corrs})
    lg = data / "lightglue_assets" / "images"
    for a, b in (("DSC_0410.JPG", "DSC_0411.JPG"), ("sacre_coeur1.jpg", "sacre_coeur2.jpg")):
        pairs.append({"set": "lightglue_assets", "a": lg / a, "b": lg / b, "corrs": None})
    for category in WXBS_RELATED:
        for pair_dir in sorted((data / "wxbs_v1.1" / category).iterdir())[:per_set]:
            # .png or .jpg, not .txt
            a, b = (next(pair_dir.glob(f"{stem}.*[!t]")) for stem in ("01", "02"))
            pairs.append({"set": f"wxbs/{category}", "a": a, "b": b, "corrs": wxbs_corrs(pair_dir)})
    return pairs


def unrelated_pairs(count: int, seed: int = 0) -> list[dict]:
    """Pairs of photos of different places (scenes chosen so no two show the same landmark)."""
    data = shared_data_dir()
    groups = {
        "sacre_coeur": sorted((data / "sacre_coeur_hloc" / "images").iterdir()),
        "lund_door": sorted((data / "lund_door_gtsfm" / "images").iterdir()),
        "lund_street": sorted((data / "opensfm_lund" / "images").iterdir()),
        "alamo": sorted((data / "gtsfm_1dsfm_sample" / "images").iterdir()),
        "dsc_building": sorted((data / "lightglue_assets" / "images").glob("DSC_*")),
    }
    for landmark in (
        "london_bridge",
        "piazza_san_marco",
        "st_pauls_cathedral",
        "united_states_capitol",
    ):
        groups[landmark] = sorted(
            (data / "phototourism_superglue" / "images").glob(f"{landmark}_*")
        )
    rng = np.random.default_rng(seed)
    combos = list(itertools.combinations(sorted(groups), 2))
    rng.shuffle(combos)
    pairs = []
    for k, (ga, gb) in enumerate(itertools.islice(itertools.cycle(combos), count)):
        a = groups[ga][rng.integers(len(groups[ga]))]
        b = groups[gb][rng.integers(len(groups[gb]))]
        pairs.append({"set": f"{ga}|{gb}", "a": a, "b": b, "corrs": None})
    return pairs


# ------------------------------------------------------------------------------------------------
# Verification
# ------------------------------------------------------------------------------------------------


def verify_matches(
    a: ImageData, b: ImageData, matches: np.ndarray, matcher
) -> pycolmap.TwoViewGeometry:
    """COLMAP's two-view verification with the pipeline's options for ``matcher`` (raw: >= 15
    inliers, guided: its min_inliers)."""
    options = verify.two_view_options(matcher.verification_conf)
    return verify.verify_pair(
        verify.default_camera(a.width, a.height),
        a.keypoints,
        verify.default_camera(b.width, b.height),
        b.keypoints,
        matches,
        options,
    )


def reference_error(geometry: pycolmap.TwoViewGeometry, corrs: np.ndarray | None) -> float | None:
    """Median error (px) of the reference correspondences under the verified geometry: symmetric
    epipolar distance for F (or E), symmetric transfer error for a planar / panoramic H."""
    if corrs is None or len(geometry.inlier_matches) == 0:
        return None
    xa = np.concatenate([corrs[:, :2], np.ones((len(corrs), 1))], 1)
    xb = np.concatenate([corrs[:, 2:], np.ones((len(corrs), 1))], 1)
    F = np.asarray(geometry.F)
    if np.any(F):
        lb, la = xa @ F.T, xb @ F
        alg = np.abs((xb * lb).sum(1))
        d = 0.5 * (
            alg / np.linalg.norm(lb[:, :2], axis=1) + alg / np.linalg.norm(la[:, :2], axis=1)
        )
        return float(np.median(d))
    H = np.asarray(geometry.H)
    if not np.any(H):
        return None
    pb, pa = xa @ H.T, xb @ np.linalg.inv(H).T
    d = 0.5 * (
        np.linalg.norm(pb[:, :2] / pb[:, 2:] - corrs[:, 2:], axis=1)
        + np.linalg.norm(pa[:, :2] / pa[:, 2:] - corrs[:, :2], axis=1)
    )
    return float(np.median(d))


# ------------------------------------------------------------------------------------------------
# Runs
# ------------------------------------------------------------------------------------------------


def best_time(fn, repeat: int):
    """Result of ``fn()`` and its fastest wall time over ``repeat`` runs
    (robust on a shared CPU)."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return out, min(times)


def extract_coarse(matcher: GuidedMatcher, a: ImageData, b: ImageData) -> None:
    """Coarse features of both images from their files (the caches emptied first: the matcher's and
    the images')."""
    for image in (a, b):
        matcher.release(image.name)
        image.extra.clear()
        matcher.prepare(image)


def run_pair(pair: dict, matchers: dict, database: Path, max_ref_err: float, repeat: int) -> dict:
    a, b = read_pair(database, pair)
    row = {
        "set": pair["set"],
        "a": str(pair["a"].relative_to(shared_data_dir())),
        "b": str(pair["b"].relative_to(shared_data_dir())),
        "num_keypoints": [len(a.keypoints), len(b.keypoints)],
    }
    for name, matcher in matchers.items():
        timing = {}
        if isinstance(matcher, GuidedMatcher):
            _, timing["coarse_extract_s"] = best_time(
                partial(extract_coarse, matcher, a, b), repeat
            )
            flows, timing["coarse_match_s"] = best_time(partial(matcher.coarse_flows, a, b), repeat)
            matches, timing["eq1_s"] = best_time(partial(matcher.match_flows, a, b, flows), repeat)
            matcher.release(a.name), matcher.release(b.name)
            timing["total_s"] = (
                timing["coarse_extract_s"] + timing["coarse_match_s"] + timing["eq1_s"]
            )
        else:
            matches, timing["total_s"] = best_time(partial(matcher.match, a, b), repeat)
        geometry = verify_matches(a, b, matches, matcher)
        err = reference_error(geometry, pair["corrs"])
        row[name] = {
            "matches": len(matches),
            "inliers": len(geometry.inlier_matches),
            "config": pycolmap.TwoViewGeometryConfiguration(geometry.config).name,
            "ref_err_px": err,
            "correct": None if pair["corrs"] is None or err is None else err < max_ref_err,
            **timing,
        }
    return row


def sweep(
    pairs: list[dict],
    unrelated: list[dict],
    guided: GuidedMatcher,
    database: Path,
    max_ref_err: float,
) -> list[dict]:
    """Verified inliers (related) and verified share (unrelated) over a grid of guided options."""
    grid = {
        "ratio": [None, 0.8, 0.9, 0.95],
        "max_fb_cells": [None, 2.0],
        "window_cells": [1.0, 2.0],
    }
    combos = [dict(zip(grid, values)) for values in itertools.product(*grid.values())]
    raw = get_matcher("raw", {"device": str(guided.device)})
    results = {
        json.dumps(c): {
            "related_inliers": [],
            "related_correct": [],
            "related_wrong": [],
            "unrelated_inliers": [],
        }
        for c in ["raw", *combos]
    }
    for kind, plist in (("related", pairs), ("unrelated", unrelated)):
        for pair in plist:
            a, b = read_pair(database, pair)
            flows = guided.coarse_flows(a, b)
            for combo in ["raw", *combos]:
                matches = (
                    raw.match(a, b) if combo == "raw" else guided.match_flows(a, b, flows, **combo)
                )
                geometry = verify_matches(a, b, matches, raw if combo == "raw" else guided)
                r = results[json.dumps(combo)]
                r[f"{kind}_inliers"].append(len(geometry.inlier_matches))
                if kind == "related" and pair["corrs"] is not None:
                    err = reference_error(geometry, pair["corrs"])
                    r["related_correct"].append(err is not None and err < max_ref_err)
                    r["related_wrong"].append(
                        len(geometry.inlier_matches) > 0 and not r["related_correct"][-1]
                    )
            guided.release(a.name), guided.release(b.name)
            logger.info("sweep %s %s done", kind, pair["set"])
    return [{"conf": json.loads(k), **v} for k, v in results.items()]


def sweep_markdown(results: list[dict]) -> str:
    """One line per option set: related pairs verified / correct, inliers vs raw, unrelated
    verified."""
    raw = next(r for r in results if r["conf"] == "raw")
    keys = [k for k in results[1]["conf"]]
    out = [
        "| matcher | "
        + " | ".join(keys)
        + " | related verified | correct / wrong (with reference) | "
        "median inliers / raw | unrelated verified |",
        "|---|" + "---|" * (len(keys) + 4),
    ]
    for r in results:
        c = r["conf"]
        conf = (
            "raw | " + " | ".join("–" for _ in keys)
            if c == "raw"
            else "guided | " + " | ".join(str(c[k]) for k in keys)
        )
        ratios = [g / x for g, x in zip(r["related_inliers"], raw["related_inliers"]) if x > 0]
        out.append(
            f"| {conf} | {sum(n > 0 for n in r['related_inliers'])}/{len(r['related_inliers'])}"
            f" | {sum(r['related_correct'])} / {sum(r['related_wrong'])} of "
            f"{len(r['related_correct'])} | {np.median(ratios) if ratios else float('nan'):.2f}"
            f" | {sum(n > 0 for n in r['unrelated_inliers'])}/{len(r['unrelated_inliers'])} |"
        )
    return "\n".join(out)


def markdown(rows: list[dict], unrelated_rows: list[dict], names: list[str]) -> str:
    out = [
        "| set | pair | "
        + " | ".join(f"{n} inliers" for n in names)
        + " | raw s | guided s | guided/raw time |",
        "|---|---|" + "---|" * (len(names) + 3),
    ]
    for r in rows:
        cells = []
        for n in names:
            c = r[n]
            mark = "" if c["correct"] is None else (" ✓" if c["correct"] else " ✗")
            cells.append(f"{c['inliers']}{mark}")
        pair = (
            f"{Path(r['a']).name}–{Path(r['b']).name}"
            if not r["set"].startswith("wxbs")
            else Path(r["a"]).parent.name
        )
        g = r.get("guided")
        t = (
            f"{r['raw']['total_s']:.2f} | {g['total_s']:.2f} | "
            f"{g['total_s'] / r['raw']['total_s']:.1f}×"
            if g and "raw" in r
            else "– | – | –"
        )
        out.append(f"| {r['set']} | {pair} | " + " | ".join(cells) + f" | {t} |")
    if "guided" in names and "raw" in names:
        med = {
            k: np.median([r["guided"][k] for r in rows])
            for k in ("coarse_extract_s", "coarse_match_s", "eq1_s", "total_s")
        }
        raw_med = np.median([r["raw"]["total_s"] for r in rows])
        out.append("")
        out.append(
            f"Median per pair: raw {raw_med:.2f} s; guided {med['total_s']:.2f} s = coarse "
            f"features of both images {med['coarse_extract_s']:.2f} + coarse match "
            f"{med['coarse_match_s']:.2f} + eq. 1 {med['eq1_s']:.2f} (median guided/raw time ratio "
            f"{np.median([r['guided']['total_s'] / r['raw']['total_s'] for r in rows]):.2f})."
        )
    out.append("")
    out.append(
        "Unrelated pairs (different scenes) passing verification (each matcher's minimum inliers):"
    )
    out.append("")
    out.append("| matcher | verified / pairs | max inliers |")
    out.append("|---|---|---|")
    for n in names:
        verified = sum(r[n]["inliers"] > 0 for r in unrelated_rows)
        most = max((r[n]["inliers"] for r in unrelated_rows), default=0)
        out.append(f"| {n} | {verified}/{len(unrelated_rows)} | {most} |")
    return "\n".join(out)


def _parser():
    """The command line."""
    parser = script_parser(__doc__)
    parser.add_argument("--pairs_per_set", type=int, default=3)
    parser.add_argument("--unrelated", type=int, default=24, help="number of unrelated-image pairs")
    parser.add_argument(
        "--matchers",
        nargs="+",
        default=BASELINES,
        help="presets of colmap_guided.matchers.PRESETS "
        "(lightglue, guided_lightglue with --features aliked)",
    )
    parser.add_argument(
        "--features",
        default="sift",
        choices=sorted(features.FEATURE_TYPES),
        help="aliked / xfeat: the pipeline's learned "
        "features (ALIKED: with its raw / guided defaults)",
    )
    parser.add_argument(
        "--guided_conf",
        type=json.loads,
        default={},
        help="JSON overriding the guided matcher's options",
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--max_ref_err",
        type=float,
        default=5.0,
        help="px: a verified geometry is correct below this median reference error",
    )
    parser.add_argument(
        "--cache_dir",
        type=Path,
        default=Path("/tmp/colmap_guided_bench_features"),
        help="the COLMAP databases of the extracted features, one per feature type",
    )
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--sweep",
        action="store_true",
        help="grid over ratio / forward-backward / window for the guided matcher",
    )
    parser.add_argument(
        "--repeat", type=int, default=3, help="timings: fastest of this many runs (related pairs)"
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch CPU threads (1: stable timings on a shared machine)",
    )
    return parser


def build_matchers(args) -> dict:
    """The ``--matchers`` by name, each checked against the ``--features``."""
    # a preset, optionally with name:key=value options
    specs = {n: matcher_specs.parse_spec(n) for n in args.matchers}
    matchers = {
        n: get_matcher(
            sp.name,
            resolve_auto(
                sp.name,
                args.features,
                {"device": args.device, **sp.conf, **(args.guided_conf if n == "guided" else {})},
            ).matcher_conf,
        )
        for n, sp in specs.items()
    }
    for matcher in matchers.values():
        features.check_matcher_features(matcher, args.features)
    return matchers


def run_pairs(pairs: list[dict], matchers: dict, database: Path, args, related: bool) -> list:
    """``run_pair`` on every pair, logging its inliers; related pairs timed ``--repeat`` times."""
    rows, repeat = [], args.repeat if related else 1
    for pair in pairs:
        rows.append(run_pair(pair, matchers, database, args.max_ref_err, repeat))
        label = f"{pair['set']} {pair['a'].name}" if related else f"unrelated {pair['set']}"
        logger.info("%s: %s", label, {n: rows[-1][n]["inliers"] for n in matchers})
    return rows


def main(argv=None) -> None:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.sweep and args.features != "sift":
        parser.error("--sweep runs on SIFT only")
    torch.set_grad_enabled(False)
    torch.set_num_threads(args.threads)

    pairs = related_pairs(args.pairs_per_set)
    unrelated = unrelated_pairs(args.unrelated)
    database = extract(pairs + unrelated, args.features, args.cache_dir)
    matchers = build_matchers(args)
    result = {
        "features": args.features,
        "matchers": {n: m.describe() for n, m in matchers.items()},
        "device": args.device,
        "torch_threads": torch.get_num_threads(),
    }
    if args.sweep:
        guided = matchers.get("guided") or get_matcher(
            "guided", {"device": args.device, **args.guided_conf}
        )
        result["sweep"] = sweep(pairs, unrelated, guided, database, args.max_ref_err)
        print(sweep_markdown(result["sweep"]))
    else:
        result["related"] = run_pairs(pairs, matchers, database, args, True)
        result["unrelated"] = run_pairs(unrelated, matchers, database, args, False)
        print(markdown(result["related"], result["unrelated"], list(matchers)))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=str))


if __name__ == "__main__":
    main()
