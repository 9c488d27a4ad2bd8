"""Verified inliers of matchers on real pairs of photos, and the share of unrelated pairs verifying.

    python -m recon_scripts matching [methods="raw guided"] [pairs_per_set=3] [unrelated=24]
    python -m recon_scripts matching sweep=true   # guided options grid on the same pairs
    python -m recon_scripts matching features=aliked methods="raw guided lightglue guided_lightglue"

Sets are groups of pairs: consecutive photos of a folder of ../shared/data (sacre_coeur_hloc,
lund_door_gtsfm with its reference model's correspondences), lightglue_assets' two pairs,
wxbs/CATEGORY (WxBS appearance / illumination pairs, hand-labelled corrs.txt) and ``unrelated``
(pairs of photos of different scenes). Methods are matcher specs ``name[:key=value,...]`` on the
``features`` (ALIKED: ``raw guided lightglue guided_lightglue``, the learned paths' guard);
``guided_conf`` goes over the ``guided`` method's options. Reported: the COLMAP-verified inliers
(pycolmap estimate_two_view_geometry, the pipeline's options: >= 15 inliers, guided and LightGlue
>= their min_inliers), whether the verified geometry agrees with the reference correspondences
(median error < max_ref_err px) where a pair has some, and the wall time of raw vs guided (coarse
extraction of both images + coarse match + eq. 1, fastest of ``repeat`` runs) on the same pair. On
unrelated pairs: the share that verifies per matcher (guided matching must not manufacture
geometry more often than raw matching). ``sweep=true``: raw and the guided matcher over a grid of
its options (ratio, forward-backward, window) on the same coarse flows, instead of the methods.

Features are the pipeline's own (``features.extract_features``, its default options), extracted
into a COLMAP database per feature type in ``cache_dir`` and read back through
``colmap_guided.database``, so reruns only pay for matching.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np
import pycolmap
import torch

from colmap_guided import database as dbio
from colmap_guided import features, verify
from colmap_guided.matchers import get_matcher, resolve_auto
from colmap_guided.matchers.base import ImageData
from colmap_guided.matchers.guided import GuidedMatcher
from colmap_guided.paths import shared_data_dir
from recon_scripts.bench import Benchmark
from recon_scripts.evaluation import matcher_specs

BASELINES = ["raw", "guided", "guided_epipolar", "guided_homography", "guided_colmap"]
WXBS_RELATED = ["WGABS", "WGALBS", "WGLBS", "WLABS"]  # appearance / illumination changes
UNRELATED = "unrelated"  # the set of pairs of photos of different scenes
# the sweep's grid over the guided matcher's options
SWEEP_GRID = {
    "ratio": [None, 0.8, 0.9, 0.95],
    "max_fb_cells": [None, 2.0],
    "window_cells": [1.0, 2.0],
}


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
    # no database camera: matchers and verify_images take COLMAP's default camera of the image size
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


def set_pairs(name: str, per_set: int, unrelated: int) -> list[dict]:
    """The pairs of one set: ``unrelated`` (that many pairs of photos of different scenes),
    lightglue_assets' two pairs, the first ``per_set`` pairs of a WxBS category (``wxbs/WGABS``,
    with their reference corrs), or the first ``per_set`` consecutive photos of a folder of the data
    (lund_door_gtsfm with its reference model's correspondences)."""
    data = shared_data_dir()
    if name == UNRELATED:
        return unrelated_pairs(unrelated)
    if name == "lightglue_assets":
        lg = data / name / "images"
        return [
            {"set": name, "a": lg / a, "b": lg / b, "corrs": None}
            for a, b in (("DSC_0410.JPG", "DSC_0411.JPG"), ("sacre_coeur1.jpg", "sacre_coeur2.jpg"))
        ]
    pairs = []
    if name.startswith("wxbs/"):
        for pair_dir in sorted((data / "wxbs_v1.1" / name[len("wxbs/") :]).iterdir())[:per_set]:
            # .png or .jpg, not .txt
            a, b = (next(pair_dir.glob(f"{stem}.*[!t]")) for stem in ("01", "02"))
            pairs.append({"set": name, "a": a, "b": b, "corrs": wxbs_corrs(pair_dir)})
        return pairs
    if not (data / name / "images").is_dir():
        raise ValueError(f"set {name!r}: neither {UNRELATED}, wxbs/CATEGORY nor a folder of photos")
    images = sorted((data / name / "images").iterdir())
    for a, b in list(itertools.pairwise(images))[:per_set]:
        corrs = lund_door_corrs(a.name, b.name) if name == "lund_door_gtsfm" else None
        pairs.append({"set": name, "a": a, "b": b, "corrs": corrs})
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


def pair_row(pair: dict, a: ImageData, b: ImageData, matches, matcher, max_ref_err: float) -> dict:
    """The pair, and the verified geometry of ``matches`` against its reference correspondences."""
    geometry = verify.verify_images(a, b, matches, matcher.verification_conf)
    err = reference_error(geometry, pair["corrs"])
    return {
        "set": pair["set"],
        "a": image_name(pair["a"]),
        "b": image_name(pair["b"]),
        "num_keypoints": [len(a.keypoints), len(b.keypoints)],
        "reference": pair["corrs"] is not None,
        "matches": len(matches),
        "inliers": len(geometry.inlier_matches),
        "config": pycolmap.TwoViewGeometryConfiguration(geometry.config).name,
        "ref_err_px": err,
        "correct": None if pair["corrs"] is None or err is None else err < max_ref_err,
    }


def run_pair(pair: dict, matcher, database: Path, max_ref_err: float, repeat: int) -> dict:
    """``pair_row`` of the matcher's matches and their time (fastest of ``repeat`` runs)."""
    a, b = read_pair(database, pair)
    timing = {}
    if isinstance(matcher, GuidedMatcher):
        _, timing["coarse_extract_s"] = best_time(partial(extract_coarse, matcher, a, b), repeat)
        flows, timing["coarse_match_s"] = best_time(partial(matcher.coarse_flows, a, b), repeat)
        matches, timing["eq1_s"] = best_time(partial(matcher.match_flows, a, b, flows), repeat)
        matcher.release(a.name), matcher.release(b.name)
        timing["total_s"] = timing["coarse_extract_s"] + timing["coarse_match_s"] + timing["eq1_s"]
    else:
        matches, timing["total_s"] = best_time(partial(matcher.match, a, b), repeat)
    return {**pair_row(pair, a, b, matches, matcher, max_ref_err), **timing}


def sweep_pair(
    pair: dict, guided: GuidedMatcher, database: Path, max_ref_err: float, flows: dict, combo
) -> dict:
    """``pair_row`` of the guided matcher's eq. 1 with ``combo`` over its options, on the pair's
    coarse flows (computed once, kept in ``flows``)."""
    a, b = read_pair(database, pair)
    key = (image_name(pair["a"]), image_name(pair["b"]))
    if key not in flows:
        flows[key] = guided.coarse_flows(a, b)
        guided.release(a.name), guided.release(b.name)
    matches = guided.match_flows(a, b, flows[key], **combo)
    return pair_row(pair, a, b, matches, guided, max_ref_err)


def sweep_markdown(sweeps: list[tuple]) -> str:
    """One line per option set (conf, related rows, unrelated rows): related pairs verified /
    correct, inliers vs raw, unrelated verified."""
    results = [
        {
            "conf": conf,
            "related_inliers": [r["inliers"] for r in related],
            "related_correct": [bool(r["correct"]) for r in related if r["reference"]],
            "related_wrong": [
                r["inliers"] > 0 and not r["correct"] for r in related if r["reference"]
            ],
            "unrelated_inliers": [r["inliers"] for r in unrelated],
        }
        for conf, related, unrelated in sweeps
    ]
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


class MatchingBenchmark(Benchmark):
    name = "matching"
    default_conf = {
        "sets": [
            "sacre_coeur_hloc",
            "lund_door_gtsfm",
            "lightglue_assets",
            *(f"wxbs/{category}" for category in WXBS_RELATED),
            UNRELATED,
        ],
        "methods": BASELINES,  # presets of colmap_guided.matchers.PRESETS[:key=value,...]
        "features": "sift",  # aliked / xfeat: the pipeline's learned features
        "pairs_per_set": 3,
        "unrelated": 24,  # number of unrelated-image pairs
        "guided_conf": {},  # over the guided method's options
        "device": "cpu",
        "max_ref_err": 5.0,  # px: a verified geometry is correct below this median reference error
        "cache_dir": "/tmp/colmap_guided_bench_features",  # the feature databases, one per type
        "sweep": False,  # grid over ratio / forward-backward / window for the guided matcher
        "repeat": 3,  # timings: fastest of this many runs (related pairs)
        "threads": 1,  # torch CPU threads (1: stable timings on a shared machine)
    }

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        if self.conf["sweep"] and self.conf["features"] != "sift":
            raise ValueError("sweep runs on SIFT only")
        if self.conf["features"] not in features.FEATURE_TYPES:
            raise ValueError(f"features: one of {sorted(features.FEATURE_TYPES)}")
        self.matchers = {}

    def configs(self):
        c = self.conf
        shared = {k: c[k] for k in ("features", "device", "max_ref_err", "pairs_per_set")}
        shared.update(unrelated=c["unrelated"], threads=c["threads"])
        shared["repeat"] = 1 if c["sweep"] else c["repeat"]  # the sweep reports no timings
        if not c["sweep"]:
            runs = {method: (method, None) for method in c["methods"]}
        else:
            combos = [dict(zip(SWEEP_GRID, v)) for v in itertools.product(*SWEEP_GRID.values())]
            runs = {"raw": ("raw", None)}
            runs.update(
                {", ".join(f"{k}={v}" for k, v in x.items()): ("guided", x) for x in combos}
            )
        return {
            label: {
                **shared,
                "method": method,
                "guided_conf": c["guided_conf"] if method == "guided" else {},
                "sweep": combo,
            }
            for label, (method, combo) in runs.items()
        }

    def matcher(self, method: str):
        """The matcher of a method spec on the features (checked against them), built once."""
        if method not in self.matchers:
            c, spec = self.conf, matcher_specs.parse_spec(method)
            conf = {"device": c["device"], **spec.conf}
            conf.update(c["guided_conf"] if method == "guided" else {})
            matcher = get_matcher(
                spec.name, resolve_auto(spec.name, c["features"], conf).matcher_conf
            )
            features.check_matcher_features(matcher, c["features"])
            self.matchers[method] = matcher
        return self.matchers[method]

    def images(self, name, work):
        return shared_data_dir()

    def prepare(self, name, image_path, work):
        torch.set_num_threads(self.conf["threads"])
        for config in self.configs().values():
            self.matcher(config["method"])
        pairs = set_pairs(name, self.conf["pairs_per_set"], self.conf["unrelated"])
        database = extract(pairs, self.conf["features"], Path(self.conf["cache_dir"]))
        return {"pairs": pairs, "database": database, "flows": {}}

    def run_config(self, name, image_path, prepared, label, config, out):
        matcher = self.matcher(config["method"])
        repeat = 1 if name == UNRELATED else config["repeat"]
        args = (matcher, prepared["database"], config["max_ref_err"])
        with torch.no_grad():
            if config["sweep"] is None:
                rows = [run_pair(pair, *args, repeat) for pair in prepared["pairs"]]
            else:
                flows, combo = prepared["flows"], config["sweep"]
                rows = [sweep_pair(pair, *args, flows, combo) for pair in prepared["pairs"]]
        return {
            "matcher": matcher.describe(),
            "torch_threads": torch.get_num_threads(),
            "pairs": rows,
        }

    def progress(self, results, name, label):
        inliers = [r["inliers"] for r in results[name][label]["pairs"]]
        return f"{name} {label}: verified inliers {inliers}"

    def summarize(self, results):
        def rows(label: str, related: bool) -> list[dict]:
            return [
                row
                for name, runs in results.items()
                if (name != UNRELATED) == related
                for row in runs[label]["pairs"]
            ]

        configs = self.configs()
        if self.conf["sweep"]:
            return sweep_markdown(
                [
                    (c["sweep"] or "raw", rows(label, True), rows(label, False))
                    for label, c in configs.items()
                ]
            )

        def by_pair(related: bool) -> list[dict]:
            return [
                {
                    "set": cells[0]["set"],
                    "a": cells[0]["a"],
                    "b": cells[0]["b"],
                    **dict(zip(configs, cells)),
                }
                for cells in zip(*(rows(label, related) for label in configs))
            ]

        return markdown(by_pair(True), by_pair(False), list(configs))
