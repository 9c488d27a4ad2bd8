"""Two-view protocols: relative pose AUC on pairs with reference cameras (paper Table 2) and WxBS.

Pose protocol (SuperGlue/OANet YFCC): for each sampled pair, SIFT keypoints (pycolmap, as the
pipeline extracts them, into a cached COLMAP database), matches of each matcher variant, essential
matrix by RANSAC with threshold 1 px / mean focal on the reference intrinsics, pose error vs the
reference relative pose, AUC at 5/10/20 degrees over all pairs. Pairs are sampled deterministically
among covisible pairs (>= ``min_covisible`` shared 3D points of the scene's COLMAP model), spread
over bins of reference relative rotation so that easy and hard pairs are both present.

WxBS protocol: fundamental matrix (or homography) by MAGSAC++ from the matches, score = share of the
hand-labelled correspondences within 3/5/10 px (symmetric epipolar distance / transfer error).
"""

from __future__ import annotations

import dataclasses
import time
import zlib
from itertools import combinations
from pathlib import Path

import numpy as np

from colmap_guided import database as dbio
from colmap_guided import features, paths
from colmap_guided.geometry import essential_from_pose
from colmap_guided.log import logger
from colmap_guided.matchers.base import ImageData, scoped_torch_threads
from colmap_guided.paths import shared_data_dir

from . import matcher_specs, metrics
from .reference import TWO_VIEW_SCENES, RefScene, load_reference

ROTATION_BINS = (0.0, 15.0, 30.0, 60.0, 180.0)
DEFAULT_CACHE = paths.cache_dir("evaluation")


# ------------------------------------------------------------------------------------------ pairs
def sample_pairs(
    ref: RefScene, max_pairs: int | None, seed: int = 0, min_covisible: int = 50, bins=ROTATION_BINS
) -> list[dict]:
    """Deterministic sample of covisible pairs with reference poses, round-robin over rotation
    bins."""
    names = sorted(ref.views)
    candidates = []
    for a, b in combinations(names, 2):
        if not ref.comparable(a, b):
            continue
        shared = ref.covisibility(a, b)
        if shared < min_covisible:
            continue
        R, _ = ref.relative_pose(a, b)
        candidates.append(
            {
                "scene": ref.key,
                "a": a,
                "b": b,
                "covisible": shared,
                "rotation": metrics.rotation_angle(R),
            }
        )
    rng = np.random.default_rng(seed + zlib.crc32(ref.key.encode()))
    order = rng.permutation(len(candidates))
    buckets = [
        [candidates[i] for i in order if lo <= candidates[i]["rotation"] < hi]
        for lo, hi in zip(bins[:-1], bins[1:])
    ]
    chosen = []
    limit = len(candidates) if max_pairs is None else min(max_pairs, len(candidates))
    depth = 0
    while len(chosen) < limit:
        for bucket in buckets:
            if depth < len(bucket) and len(chosen) < limit:
                chosen.append(bucket[depth])
        depth += 1
    return chosen


# --------------------------------------------------------------------------------------- features
def sift_features(
    image_dir: Path,
    names: list[str],
    cache_dir: Path,
    max_num_features: int = 2000,
    max_image_size: int = 3200,
) -> dict[str, ImageData]:
    """SIFT of ``names`` (paths relative to ``image_dir``) with pycolmap, as the pipeline extracts
    them.

    Cached in ``cache_dir/database.db`` (one camera per image; the cameras are not used: the
    protocol uses the reference intrinsics). Returns name -> ImageData (keypoints in COLMAP pixel
    convention).
    """
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    database_path = cache_dir / "database.db"
    conf = {
        "camera_mode": "per_image",
        "max_num_features": max_num_features,
        "max_image_size": max_image_size,
    }
    features.extract_features(database_path, image_dir, sorted(set(names)), conf)
    out = {}
    with dbio.open_database(database_path) as db:
        images = dbio.images_with_keypoints(db)
        for name in sorted(set(names)):
            if name in images:
                out[name] = dbio.read_image_data(db, images[name], image_dir)
    return out


def _as_specs(specs, extra_conf: dict | None = None) -> list:
    """Spec strings (checked against the registry) or MatcherSpec objects, as a list."""
    specs = list(specs or [])
    texts = [s for s in specs if isinstance(s, str)]
    return (
        [s for s in specs if not isinstance(s, str)] + matcher_specs.parse_specs(texts, extra_conf)
        if texts
        else specs
    )


def _fresh(image: ImageData) -> ImageData:
    """The same image with an empty per-matcher cache (matchers never share their caches)."""
    return dataclasses.replace(image, extra={})


def _flow_options(spec) -> tuple[str, ...]:
    """Options the spec's matcher applies after its guidance (``Matcher.flow_options``): variants
    differing only in these share one ``coarse_flows`` per pair."""
    return matcher_specs.matcher_class(spec.name).flow_options


def _group_key(spec) -> str:
    import json

    return spec.name + json.dumps(
        {k: v for k, v in sorted(spec.conf.items()) if k not in _flow_options(spec)}, default=str
    )


def run_specs(
    specs, pairs: list[tuple[str, str]], images: dict[str, ImageData]
) -> dict[str, tuple[list[np.ndarray], list[float]]]:
    """Matches and per-pair times of several variants. A variant's time is what it would cost alone
    (coarse match + eq. 1 for grouped guided variants). A variant that cannot run raises: a
    benchmark table never loses a row silently."""
    groups: dict[str, list] = {}
    for spec in specs:
        groups.setdefault(_group_key(spec), []).append(spec)
    out = {}
    for group in groups.values():
        first = group[0]
        flow_options = _flow_options(first)
        shared = len(group) > 1  # variants of one matcher differing only in its flow_options
        base = dataclasses.replace(
            first, conf={k: v for k, v in first.conf.items() if k not in flow_options}
        )
        matcher = matcher_specs.build(base if shared else first)
        local: dict[str, ImageData] = {}
        res = {spec.label: ([], []) for spec in group}
        with scoped_torch_threads(matcher.torch_threads):  # as match_database
            for a, b in pairs:
                for n in (a, b):
                    if n not in local:
                        local[n] = _fresh(images[n])
                if shared:
                    start = time.time()
                    flows = matcher.coarse_flows(local[a], local[b])
                    t_flow = time.time() - start
                    for spec in group:
                        start = time.time()
                        m = matcher.match_flows(
                            local[a],
                            local[b],
                            flows,
                            **{k: spec.conf[k] for k in flow_options if k in spec.conf},
                        )
                        res[spec.label][0].append(np.asarray(m, np.int64).reshape(-1, 2))
                        res[spec.label][1].append(t_flow + time.time() - start)
                else:
                    start = time.time()
                    m = matcher.match(local[a], local[b])
                    res[first.label][0].append(np.asarray(m, np.int64).reshape(-1, 2))
                    res[first.label][1].append(time.time() - start)
        for n in local:
            matcher.release(n)
        out.update(res)
    return out


# ------------------------------------------------------------------------------------- pose AUC
def evaluate_pose_pair(
    ref: RefScene,
    a: ImageData,
    b: ImageData,
    matches: np.ndarray,
    threshold_px: float = 1.0,
    estimator: str = "cv2",
    precision_px: float = 3.0,
) -> dict:
    va, vb = ref.views[a.name], ref.views[b.name]
    p1 = a.keypoints[matches[:, 0], :2] if len(matches) else np.zeros((0, 2))
    p2 = b.keypoints[matches[:, 1], :2] if len(matches) else np.zeros((0, 2))
    R_gt, t_gt = ref.relative_pose(a.name, b.name)
    est = metrics.estimate_relative_pose(
        p1, p2, va.camera, vb.camera, threshold_px=threshold_px, estimator=estimator
    )
    err = metrics.relative_pose_error(
        est["R"] if est else None, est["t"] if est else None, R_gt, t_gt
    )
    precision = float("nan")
    if len(matches):
        k1, k2 = metrics.normalize_points(va.camera, p1), metrics.normalize_points(vb.camera, p2)
        e_px = metrics.symmetric_epipolar_distance(
            k1, k2, essential_from_pose(R_gt, t_gt)
        ) * metrics.mean_focal(va.camera, vb.camera)
        precision = float(np.mean(e_px < precision_px))
    return {
        "num_matches": int(len(matches)),
        "num_inliers": int(est["num_inliers"]) if est else 0,
        "precision": precision,
        "err_R": err["R"],
        "err_t": err["t"],
        "err_pose": err["pose"],
    }


def summarize_pose(records: list[dict], thresholds=metrics.AUC_THRESHOLDS) -> dict:
    errors = [r["err_pose"] for r in records]
    prec = [r["precision"] for r in records if not np.isnan(r["precision"])]
    return {
        "num_pairs": len(records),
        "auc": [100.0 * v for v in metrics.pose_auc(errors, thresholds)],
        "acc": [100.0 * v for v in metrics.pose_accuracy(errors, thresholds)],
        "mean_matches": float(np.mean([r["num_matches"] for r in records])) if records else 0.0,
        "mean_inliers": float(np.mean([r["num_inliers"] for r in records])) if records else 0.0,
        "precision": 100.0 * float(np.mean(prec)) if prec else float("nan"),
        "time_per_pair": float(np.mean([r["time"] for r in records])) if records else 0.0,
    }


def _pose_inputs(
    scenes, max_pairs, seed, min_covisible, max_num_features, reference_source, cache_dir, data_dir
) -> tuple[dict, list[dict], dict]:
    """Each scene's reference, its sampled pairs with features of both images, and the features."""
    refs, all_pairs, images = {}, [], {}
    for key in scenes:
        ref = load_reference(key, reference_source, data_dir)
        refs[key] = ref
        pairs = sample_pairs(ref, max_pairs, seed, min_covisible)
        logger.info("%s: %d pairs sampled (%s cameras)", key, len(pairs), ref.source)
        names = sorted({p["a"] for p in pairs} | {p["b"] for p in pairs})
        feats = sift_features(
            ref.image_dir,
            names,
            Path(cache_dir) / f"sift{max_num_features}" / key.replace("/", "__"),
            max_num_features,
        )
        images[key] = feats
        all_pairs += [p for p in pairs if p["a"] in feats and p["b"] in feats]
    return refs, all_pairs, images


def _pose_record(ref: RefScene, images, pair, matches, time_s, threshold_px, estimator) -> dict:
    """One variant's record of one pair: the pair, its time and ``evaluate_pose_pair``'s errors."""
    a, b = images[pair["a"]], images[pair["b"]]
    r = evaluate_pose_pair(ref, a, b, matches, threshold_px, estimator)
    return {"scene": pair["scene"], "a": pair["a"], "b": pair["b"], "time": time_s, **r}


def _pose_result(spec, records: list[dict], scenes) -> dict:
    """One variant's summary, per scene and overall, with its per-pair records (logged)."""
    result = {
        "matcher": spec.name,
        "conf": spec.conf,
        "summary": summarize_pose(records),
        "per_scene": {
            key: summarize_pose([r for r in records if r["scene"] == key]) for key in scenes
        },
        "pairs": records,
    }
    s = result["summary"]
    logger.info(
        "%-28s AUC@5/10/20 %.1f / %.1f / %.1f  (%d pairs)", spec.label, *s["auc"], s["num_pairs"]
    )
    return result


def merge_pose_results(parts: list[dict]) -> dict:
    """Results of ``run_pose_benchmark`` on disjoint scenes (e.g. one scene and one variant each)
    as one run on all their scenes: each variant's records in the order of the parts."""
    scenes = list(dict.fromkeys(key for part in parts for key in part["config"]["scenes"]))
    pairs, records, specs = {}, {}, {}
    for part in parts:
        for p in part["pairs"]:
            pairs.setdefault((p["scene"], p["a"], p["b"]), p)
        for label, r in part["results"].items():
            specs.setdefault(label, matcher_specs.MatcherSpec(r["matcher"], r["conf"], label))
            records.setdefault(label, []).extend(r["pairs"])
    config = {
        **parts[0]["config"],
        "scenes": scenes,
        "reference_source": {
            key: source
            for part in parts
            for key, source in part["config"]["reference_source"].items()
        },
    }
    results = {label: _pose_result(spec, records[label], scenes) for label, spec in specs.items()}
    return {"config": config, "pairs": list(pairs.values()), "results": results}


def run_pose_benchmark(
    scenes=TWO_VIEW_SCENES,
    specs=matcher_specs.DEFAULT_TWO_VIEW_SPECS,
    max_pairs: int | None = 10,
    seed: int = 0,
    min_covisible: int = 50,
    max_num_features: int = 2000,
    threshold_px: float = 1.0,
    estimator: str = "cv2",
    reference_source: str = "auto",
    cache_dir: Path = DEFAULT_CACHE,
    extra_conf: dict | None = None,
    data_dir: Path | None = None,
) -> dict:
    """The Table 2 protocol on the given scenes; returns {'config', 'pairs', 'results': label ->
    ...}."""
    specs = _as_specs(specs, extra_conf)
    refs, all_pairs, images = _pose_inputs(
        scenes,
        max_pairs,
        seed,
        min_covisible,
        max_num_features,
        reference_source,
        cache_dir,
        data_dir,
    )
    by_scene = {key: [p for p in all_pairs if p["scene"] == key] for key in scenes}
    per_key = {
        key: run_specs(specs, [(p["a"], p["b"]) for p in by_scene[key]], images[key])
        for key in scenes
    }
    results = {}
    for spec in specs:
        records = [
            _pose_record(refs[key], images[key], p, m, t, threshold_px, estimator)
            for key in scenes
            for p, m, t in zip(by_scene[key], *per_key[key][spec.label])
        ]
        results[spec.label] = _pose_result(spec, records, scenes)
    config = {
        "scenes": list(scenes),
        "max_pairs": max_pairs,
        "seed": seed,
        "min_covisible": min_covisible,
        "max_num_features": max_num_features,
        "ransac": f"{estimator} essential matrix, {threshold_px} px / mean focal",
        "reference_source": {k: r.source for k, r in refs.items()},
        "thresholds_deg": list(metrics.AUC_THRESHOLDS),
    }
    return {"config": config, "pairs": all_pairs, "results": results}


# ------------------------------------------------------------------------------------------- WxBS
def list_wxbs_pairs(root: Path | None = None, categories=None) -> list[dict]:
    """WxBS pairs: <category>/<pair>/{01,02}.(png|jpg) + corrs.txt, sorted by category and name."""
    root = Path(root) if root else shared_data_dir() / "wxbs_v1.1"
    pairs = []
    for corrs in sorted(root.glob("*/*/corrs.txt")):
        folder = corrs.parent
        ims = []
        for stem in ("01", "02"):
            found = [
                p
                for p in sorted(folder.glob(stem + ".*"))
                if p.suffix.lower() in features.IMAGE_EXTENSIONS
            ]
            if found:
                ims.append(found[0].relative_to(root).as_posix())
        if len(ims) != 2:
            continue
        category = folder.parent.name
        if categories and category not in categories:
            continue
        pairs.append(
            {
                "category": category,
                "pair": f"{category}/{folder.name}",
                "a": ims[0],
                "b": ims[1],
                "corrs": corrs,
            }
        )
    return pairs


def run_wxbs_benchmark(
    specs=matcher_specs.DEFAULT_TWO_VIEW_SPECS,
    root: Path | None = None,
    max_pairs: int | None = None,
    categories=None,
    geometry: str = "F",
    threshold_px: float = 1.0,
    max_num_features: int = 2000,
    cache_dir: Path = DEFAULT_CACHE,
    extra_conf: dict | None = None,
) -> dict:
    root = Path(root) if root else shared_data_dir() / "wxbs_v1.1"
    specs = _as_specs(specs, extra_conf)
    pairs = list_wxbs_pairs(root, categories)
    if max_pairs is not None:
        # Deterministic spread over categories: round-robin.
        by_cat = {}
        for p in pairs:
            by_cat.setdefault(p["category"], []).append(p)
        chosen, depth = [], 0
        while len(chosen) < min(max_pairs, len(pairs)):
            for cat in sorted(by_cat):
                if depth < len(by_cat[cat]) and len(chosen) < max_pairs:
                    chosen.append(by_cat[cat][depth])
            depth += 1
        pairs = chosen
    names = sorted({p["a"] for p in pairs} | {p["b"] for p in pairs})
    images = sift_features(
        root, names, Path(cache_dir) / f"sift{max_num_features}" / "wxbs", max_num_features
    )
    pairs = [p for p in pairs if p["a"] in images and p["b"] in images]
    matched = run_specs(specs, [(p["a"], p["b"]) for p in pairs], images)
    results = {}
    for spec in specs:
        matches, times = matched[spec.label]
        records = []
        for p, m, t in zip(pairs, matches, times):
            a, b = images[p["a"]], images[p["b"]]
            p1 = a.keypoints[m[:, 0], :2] if len(m) else np.zeros((0, 2))
            p2 = b.keypoints[m[:, 1], :2] if len(m) else np.zeros((0, 2))
            est = metrics.estimate_geometry(p1, p2, geometry, threshold_px)
            corrs = wxbs_corrs_colmap(p["corrs"])
            errs = metrics.geometry_errors(corrs, est["M"] if est else None, geometry)
            records.append(
                {
                    "pair": p["pair"],
                    "category": p["category"],
                    "num_matches": int(len(m)),
                    "num_inliers": est["num_inliers"] if est else 0,
                    "share": [100.0 * v for v in metrics.share_within(errs)],
                    "median_error": float(np.median(errs)) if len(errs) else float("inf"),
                    "time": t,
                }
            )
        results[spec.label] = {
            "matcher": spec.name,
            "conf": spec.conf,
            "summary": summarize_wxbs(records),
            "per_category": {
                c: summarize_wxbs([r for r in records if r["category"] == c])
                for c in sorted({r["category"] for r in records})
            },
            "pairs": records,
        }
        s = results[spec.label]["summary"]
        logger.info("%-28s WxBS share @3/5/10 px %.1f / %.1f / %.1f", spec.label, *s["share"])
    config = {
        "root": str(root),
        "geometry": geometry,
        "ransac": f"OpenCV USAC_MAGSAC {threshold_px} px",
        "thresholds_px": list(metrics.WXBS_THRESHOLDS),
        "max_num_features": max_num_features,
        "num_pairs": len(pairs),
    }
    return {
        "config": config,
        "pairs": [{k: v for k, v in p.items() if k != "corrs"} for p in pairs],
        "results": results,
    }


def wxbs_corrs_colmap(path: Path) -> np.ndarray:
    """corrs.txt (x1 y1 x2 y2) -> COLMAP pixel convention.

    The labels are assumed to put pixel centres at integers (the matplotlib/OpenCV convention of the
    labelling tool's display); COLMAP's centres are at +0.5. The shift is negligible at 3 px anyway.
    """
    corrs = np.loadtxt(path, dtype=np.float64, ndmin=2).reshape(-1, 4)
    return corrs + 0.5


def summarize_wxbs(records: list[dict]) -> dict:
    if not records:
        return {
            "num_pairs": 0,
            "share": [0.0 for _ in metrics.WXBS_THRESHOLDS],
            "mean_matches": 0.0,
            "mean_inliers": 0.0,
            "time_per_pair": 0.0,
        }
    return {
        "num_pairs": len(records),
        "share": [
            float(np.mean([r["share"][i] for r in records]))
            for i in range(len(metrics.WXBS_THRESHOLDS))
        ],
        "solved_5px": 100.0 * float(np.mean([r["share"][1] >= 50.0 for r in records])),
        "mean_matches": float(np.mean([r["num_matches"] for r in records])),
        "mean_inliers": float(np.mean([r["num_inliers"] for r in records])),
        "time_per_pair": float(np.mean([r["time"] for r in records])),
    }
