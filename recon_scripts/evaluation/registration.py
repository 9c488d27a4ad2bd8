"""Registration benchmark (paper Fig. 5a): registered ratio per scene, checked against a reference
model.

Methods
- ``pycolmap``: pycolmap's default pipeline, untouched (extract_features + match_exhaustive +
  incremental_mapping with default options);
- any matcher spec of the registry (``raw``, ``guided``, ``guided:ratio=0.9``...): ``reconstruct``.

A registered image counts as *correct* only when its pose agrees with the reference model (where the
scene has one): the est->ref world rotation is the consensus of R_ref_i^T R_est_i over the
registered images (the candidate agreeing with most others within ``max_rotation_deg``), an image is
wrong when its rotation error exceeds ``max_rotation_deg`` (5°) or, with >= 3 images, its camera
centre is farther than ``max_center_frac`` (10 %) of the scene depth (median depth of the
reference's 3D points in its cameras; the spread of the reference centres when it has no points)
from its reference after a robust similarity fit. Images without a reference pose are 'unverified'.
Distractors (era 'distractor') must never register; each one registered is a failure.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
from functools import partial
from itertools import combinations
from pathlib import Path

import numpy as np
import pycolmap

from colmap_guided.features import CAMERA_MODES
from colmap_guided.log import logger
from colmap_guided.matchers import AUTO, resolve_auto
from colmap_guided.workspace import Workspace

from . import matcher_specs
from .metrics import rotation_angle

MAX_ROTATION_DEG = 5.0
MAX_CENTER_FRAC = 0.1


# ---------------------------------------------------------------------------- reference check
def _chordal_mean(Rs: list[np.ndarray]) -> np.ndarray:
    U, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def compare_poses(
    est: dict[str, tuple[np.ndarray, np.ndarray]],
    ref: dict[str, tuple[np.ndarray, np.ndarray]],
    max_rotation_deg: float = MAX_ROTATION_DEG,
    max_center_frac: float = MAX_CENTER_FRAC,
    scale: float | None = None,
) -> dict[str, dict]:
    """Per image of ``est`` (name -> (R, t) cam_from_world) that ``ref`` also has: rotation error
    (deg), centre error (fraction of ``scale``, the scene depth in reference units; default the
    median spread of the reference centres; None with < 3 images) and 'ok'."""
    names = sorted(set(est) & set(ref))
    if len(names) < 2:
        return {n: {"rotation_error": None, "center_error": None, "ok": None} for n in names}
    Qs = {n: ref[n][0].T @ est[n][0] for n in names}  # x_ref = Q x_est (rotation part)
    support = {
        n: [m for m in names if rotation_angle(Qs[n].T @ Qs[m]) < max_rotation_deg] for n in names
    }
    best = max(names, key=lambda n: (len(support[n]), -names.index(n)))
    Q = _chordal_mean([Qs[m] for m in support[best]])
    rot_err = {n: rotation_angle((ref[n][0] @ Q).T @ est[n][0]) for n in names}

    c_est = {n: -est[n][0].T @ est[n][1] for n in names}
    c_ref = {n: -ref[n][0].T @ ref[n][1] for n in names}
    center_err = {n: None for n in names}
    inl = [n for n in names if rot_err[n] < max_rotation_deg]
    if len(inl) >= 3:
        ref_pts = np.array([c_ref[n] for n in names])
        spread = (
            scale
            if scale
            else float(np.median(np.linalg.norm(ref_pts - np.median(ref_pts, 0), axis=1))) or 1.0
        )
        tol = max_center_frac * spread
        best_fit, best_count = None, -1
        for i, j in combinations(inl, 2):  # similarity (Q fixed) from two centres, scored on all
            d_est = Q @ (c_est[i] - c_est[j])
            den = float(d_est @ d_est)
            if den < 1e-12:
                continue
            s = float((c_ref[i] - c_ref[j]) @ d_est) / den
            if s <= 0:
                continue
            t = c_ref[i] - s * Q @ c_est[i]
            count = sum(np.linalg.norm(s * Q @ c_est[n] + t - c_ref[n]) < tol for n in inl)
            if count > best_count:
                best_fit, best_count = (s, t), count
        if best_fit is not None:
            s, t = best_fit
            fit = [n for n in inl if np.linalg.norm(s * Q @ c_est[n] + t - c_ref[n]) < tol]
            if len(fit) >= 2:  # least-squares refinement of s, t on the inliers
                A = np.array([Q @ c_est[n] for n in fit])
                B = np.array([c_ref[n] for n in fit])
                Ac, Bc = A - A.mean(0), B - B.mean(0)
                s = float(np.sum(Ac * Bc) / max(np.sum(Ac * Ac), 1e-12))
                t = B.mean(0) - s * A.mean(0)
            center_err = {
                n: float(np.linalg.norm(s * Q @ c_est[n] + t - c_ref[n]) / spread) for n in names
            }
    out = {}
    for n in names:
        ok = rot_err[n] < max_rotation_deg and (
            center_err[n] is None or center_err[n] < max_center_frac
        )
        out[n] = {"rotation_error": rot_err[n], "center_error": center_err[n], "ok": bool(ok)}
    return out


def model_poses(
    rec: pycolmap.Reconstruction, names: set | None = None
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for image in rec.images.values():
        if image.has_pose and (names is None or image.name in names):
            pose = image.cam_from_world()
            out[image.name] = (pose.rotation.matrix(), np.asarray(pose.translation, float))
    return out


def scene_depth(rec: pycolmap.Reconstruction, names) -> float | None:
    """Median over the given images of the median depth of their 3D points (the model's units)."""
    depths = []
    by_name = {im.name: im for im in rec.images.values()}
    for name in names:
        image = by_name.get(name)
        if image is None or not image.has_pose:
            continue
        ids = [p.point3D_id for p in image.points2D if p.has_point3D()]
        if not ids:
            continue
        pose = image.cam_from_world()
        xyz = np.array([rec.points3D[i].xyz for i in ids[:: max(1, len(ids) // 500)]])
        z = (xyz @ pose.rotation.matrix().T + pose.translation)[:, 2]
        depths.append(float(np.median(z)))
    return float(np.median(depths)) if depths else None


def largest_model(models: dict) -> pycolmap.Reconstruction | None:
    return max(models.values(), key=lambda rec: rec.num_reg_images(), default=None)


def photos(images: list[dict]) -> list[dict]:
    """The photos of a scene's manifest entries: a collage card's panels in place of the card."""
    return [p for im in images for p in im.get("panels", [im])]


def estimated_poses(
    largest: pycolmap.Reconstruction | None, images: list[dict], same_picture: dict | None = None
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{photo: pose} of a run: a panel under its own name (the pipeline cuts it into its
    workspace, whose path prefixes the model's name), a print grouped with a registered print of
    the same picture at that print's pose."""
    est = model_poses(largest) if largest is not None else {}
    panels = {p["name"] for im in images for p in im.get("panels", [])}
    est = {(Path(n).name if Path(n).name in panels else n): pose for n, pose in est.items()}
    for copy, first in (same_picture or {}).items():
        if copy not in est and first in est:
            est[copy] = est[first]
    return est


def score_registration(
    largest: pycolmap.Reconstruction | None,
    images: list[dict],
    reference: pycolmap.Reconstruction | None,
    same_picture: dict | None = None,
    **tol,
) -> dict:
    """Counts for one run: images = the scene's manifest entries (name, era, optional ref_name,
    a collage card's panels); ``same_picture``: {print: the print of its picture that the run
    mapped}. A collage card registered whole holds no one view: it counts off the pose."""
    est = estimated_poses(largest, images, same_picture)
    registered = set(est)
    targets = [im for im in photos(images) if im["era"] != "distractor"]
    distractors = [im for im in images if im["era"] == "distractor"]
    whole_cards = sorted(im["name"] for im in images if "panels" in im and im["name"] in est)
    out = {
        "num_images": len(targets),
        "num_registered": sum(im["name"] in registered for im in targets),
        "num_distractors": len(distractors),
        "distractors_registered": sorted(
            im["name"] for im in distractors if im["name"] in registered
        ),
    }
    for era in sorted({im["era"] for im in targets}):
        sub = [im for im in targets if im["era"] == era]
        out[f"{era}_registered"] = f"{sum(im['name'] in registered for im in sub)}/{len(sub)}"
    out["registered_ratio"] = (
        out["num_registered"] / out["num_images"] if out["num_images"] else 0.0
    )
    out["correct"] = out["wrong"] = out["unverified"] = None
    if reference is not None and largest is not None:
        ref_poses_by_name = model_poses(reference)
        to_ref = {im["name"]: im.get("ref_name", im["name"]) for im in targets}
        pairs = {
            n: (est[n], ref_poses_by_name[r])
            for n, r in to_ref.items()
            if n in est and r in ref_poses_by_name
        }
        depth = scene_depth(reference, [to_ref[n] for n in pairs])
        checks = compare_poses(
            {n: p[0] for n, p in pairs.items()},
            {n: p[1] for n, p in pairs.items()},
            scale=depth,
            **tol,
        )
        reg_targets = [im["name"] for im in targets if im["name"] in registered]
        out["correct"] = sum(1 for n in reg_targets if checks.get(n, {}).get("ok"))
        out["wrong"] = sorted(
            [n for n in reg_targets if checks.get(n, {}).get("ok") is False] + whole_cards
        )
        out["unverified"] = sorted(n for n in reg_targets if checks.get(n, {}).get("ok") is None)
        out["correct_ratio"] = out["correct"] / out["num_images"] if out["num_images"] else 0.0
        out["pose_checks"] = checks
    elif reference is None:
        out["correct_ratio"] = None
    else:
        out["correct"], out["wrong"], out["unverified"], out["correct_ratio"] = 0, [], [], 0.0
    return out


# ----------------------------------------------------------------------------------------- runs
def method_slug(method: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.=-]+", "_", method).strip("_")


def _fresh_workspace(workspace: Path, database: Path | None, image_dir: Path) -> Path:
    """``workspace`` without what an earlier run wrote (with a copy of ``database`` when given);
    returns its database path."""
    from colmap_guided.reconstruct import WRITES

    workspace = Workspace.claim(workspace, "reconstruct", overwrite=True)
    workspace.record(*WRITES, "eval.json")
    if database is not None:
        shutil.copyfile(database, workspace.path / "database.db")
        _take_panels(Path(database).parent, workspace.path, Path(image_dir))
    return workspace.path / "database.db"


def _take_panels(source: Path, workspace: Path, image_dir: Path) -> None:
    """The collage panels of a database copied from the run in ``source``: named after the
    workspace they were cut into, they are copied into ``workspace`` and renamed, so that the run
    matches its own panels, not those and its own again."""
    from colmap_guided import database as dbio
    from colmap_guided.cards import PANELS

    theirs = (source / PANELS).resolve()
    if not theirs.is_dir():
        return
    shutil.copytree(theirs, workspace / PANELS, dirs_exist_ok=True)
    with dbio.open_database(workspace / "database.db") as db:
        for name, image in dbio.images_by_name(db).items():
            if (image_dir / name).resolve().parent == theirs:
                own = os.path.relpath(workspace / PANELS / Path(name).name, image_dir)
                image.name = Path(own).as_posix()
                db.update_image(image)


# pycolmap's default pipeline, and its database mapped by this project's mapping stage (what the
# mapper alone gives)
PYCOLMAP_METHODS = ("pycolmap", "pycolmap_mapping")


def run_pycolmap_default(
    image_dir: Path,
    workspace: Path,
    camera_mode: str = "auto",
    seed: int | None = None,
    database: Path | None = None,
    threads: int | None = None,
    own_mapping: bool = False,
) -> tuple[dict, dict]:
    """pycolmap's default pipeline with default options (``seed``: only the mapper's random seed,
    and
    ``threads``: the mapper's threads, 1 = runs repeat exactly; ``database``: a finished database of
    this pipeline to map again, extraction and matching skipped; ``own_mapping``: the database
    mapped by ``mapping.run_mapping`` with its defaults instead); returns (models, timings)."""
    db = _fresh_workspace(workspace, database, image_dir)
    (Path(workspace) / "sparse").mkdir()
    timings = {}
    if database is None:
        start = time.time()
        pycolmap.extract_features(db, image_dir, camera_mode=CAMERA_MODES[camera_mode])
        timings["extract"] = time.time() - start
        start = time.time()
        pycolmap.match_exhaustive(db)
        timings["match"] = time.time() - start
    start = time.time()
    if own_mapping:
        from colmap_guided.mapping import run_mapping

        conf = {
            **({"random_seed": seed} if seed is not None else {}),
            **({"num_threads": threads} if threads is not None else {}),
        }
        models = run_mapping(db, image_dir, Path(workspace) / "sparse", conf)
    else:
        options = pycolmap.IncrementalPipelineOptions()
        if seed is not None:
            options.random_seed = seed
        if threads is not None:
            options.num_threads = threads
        models = pycolmap.incremental_mapping(db, image_dir, workspace / "sparse", options=options)
    timings["map"] = time.time() - start
    return dict(models), timings


def split_stage_options(method: str) -> tuple[str, dict, dict, dict]:
    """A method spec's feature-stage options (keys of ``features.default_conf``, e.g.
    ``guided:type=aliked``, or of its nested options, ``aliked.max_num_keypoints=1024``), mapping
    options (keys of ``mapping.default_conf``, e.g. ``guided:mapper=global``) and escalation
    options (keys of ``escalate.default_conf``, e.g. ``guided_lightglue:enough=None``) apart from
    its matcher spec: (matcher spec, feature conf, mapping conf, escalation conf)."""
    from colmap_guided.escalate import default_conf as escalation_defaults
    from colmap_guided.features import default_conf as feature_defaults
    from colmap_guided.mapping import default_conf as mapping_defaults

    if method in PYCOLMAP_METHODS:
        return method, {}, {}, {}
    spec = matcher_specs.parse_spec(method)
    stages = [{}, {}, {}]
    taken = set()
    for key, value in spec.conf.items():
        head, dot, sub = key.partition(".")  # a nested option: aliked.max_num_keypoints=1024
        for conf, defaults in zip(
            stages, (feature_defaults, mapping_defaults, escalation_defaults)
        ):
            if not dot and key in defaults:
                conf[key] = value
            elif dot and isinstance(defaults.get(head), dict):
                conf.setdefault(head, {})[sub] = value
            else:
                continue
            taken.add(key)
    feature, mapping, escalation = stages
    rest = ",".join(
        item
        for item in method.partition(":")[2].split(",")
        if item and item.partition("=")[0].strip() not in taken
    )
    return spec.name + (f":{rest}" if rest else ""), feature, mapping, escalation


def database_key(method: str) -> tuple[str, str]:
    """What a method's database depends on: (features key, features + matching key). Mapping options
    do not change the database, so ``guided`` and ``guided:mapper=global`` share one;
    ``raw:type=aliked`` and ``guided:type=aliked`` share their keypoints."""
    if method in PYCOLMAP_METHODS:  # one database, mapped two ways
        return "pycolmap", "pycolmap|pycolmap"
    matcher, feature, _, escalation = split_stage_options(method)
    # the features it extracts: 'guided' and 'guided:type=sift' share them
    feature = {
        **feature,
        "type": resolve_auto(
            matcher_specs.parse_spec(matcher).name, feature.get("type", AUTO), log=False
        ).feature_type,
    }
    features = json.dumps(feature, sort_keys=True)
    # escalation decides which pairs are matched: part of the database
    return features, f"{matcher}|{features}|{json.dumps(escalation, sort_keys=True)}"


def run_method(
    scene_dir: Path,
    method: str,
    workspace: Path,
    extra_conf: dict | None = None,
    seed: int | None = None,
    feature_conf: dict | None = None,
    database: Path | None = None,
    features_only: bool = False,
    threads: int | None = None,
) -> tuple[pycolmap.Reconstruction | None, dict]:
    """One reconstruction of a laid-out scene (``seed``: the mapper's random seed, None = each
    method's default; ``threads``: the mapper's threads, None = each method's default, 1 = a rerun
    gives the same model; ``database``: a finished database of this method, or of another mapper, so
    only mapping runs (the database does not depend on the mapper); with ``features_only`` its
    matches are cleared first, so only the keypoints of a method with the same feature options are
    reused); returns (largest model, summary)."""
    scene_dir = Path(scene_dir)
    image_dir = scene_dir / "images"
    start = time.time()
    if method in PYCOLMAP_METHODS:
        models, timings = run_pycolmap_default(
            image_dir,
            workspace,
            seed=seed,
            database=database,
            threads=threads,
            own_mapping=method == "pycolmap_mapping",
        )
        largest = largest_model(models)
        info = {"timings": timings, "num_models": len(models)}
    else:
        from colmap_guided.database import clear_matches, open_database
        from colmap_guided.mapping import load_models
        from colmap_guided.pipeline import PipelineConf
        from colmap_guided.reconstruct import reconstruct

        method, own_features, own_mapping, escalation = split_stage_options(method)
        feature_conf = {**(feature_conf or {}), **own_features} or None
        (spec,) = matcher_specs.parse_specs([method], extra_conf)
        mapping_conf = {
            **({"random_seed": seed} if seed is not None else {}),
            **({"num_threads": threads} if threads is not None else {}),
            **own_mapping,
        } or None
        # reconstruct resumes from the copied database
        db = _fresh_workspace(workspace, database, image_dir)
        if database is not None and features_only:
            with open_database(db) as opened:
                clear_matches(opened)
        result = reconstruct(
            scene_dir,
            conf=PipelineConf.from_dict({"escalation": escalation}),
            output=workspace,
            matcher=spec.name,
            matcher_conf=spec.conf,
            feature_conf=feature_conf,
            mapping_conf=mapping_conf,
        )
        models = load_models(Path(result["sparse_path"]))
        largest = largest_model(models)
        info = {
            "timings": result["timings"],
            "num_models": result["model"]["num_models"],
            "matcher": result["matcher"],
            "same_picture": {
                copy: found["same_picture_as"]
                for copy, found in result.get("repeated_prints", {}).items()
            },
        }
    info["num_points3D"] = largest.num_points3D() if largest is not None else 0
    info["wall_time"] = time.time() - start
    return largest, info


def _reusable(
    runs_dirs: list[Path], methods: list[str], method: str
) -> tuple[Path | None, bool, dict]:
    """A finished database to start ``method`` from: (path, features only, the source's timings).
    First one of the same features and matcher (map only), then one of the same features
    (match and map), in ``runs_dirs`` in order; (None, False, {}) when there is none."""
    features, full = database_key(method)
    for want_full in (True, False):
        for runs_dir in runs_dirs:
            for other in methods:
                if other == method and runs_dir == runs_dirs[0]:
                    continue
                key = database_key(other)
                if (key[1] if want_full else key[0]) != (full if want_full else features):
                    continue
                if other in PYCOLMAP_METHODS and not want_full:
                    continue
                ws = Path(runs_dir) / method_slug(other)
                if (ws / "database.db").is_file() and (ws / "eval.json").is_file():
                    timings = json.loads((ws / "eval.json").read_text()).get("timings", {})
                    return ws / "database.db", not want_full, timings
    return None, False, {}


def seed_runs_dir(scene_dir: Path, seed: int | None) -> Path:
    return Path(scene_dir) / "runs" / (f"seed{seed}" if seed is not None else "")


def _set_aside(workspace: Path) -> Path:
    """Move a finished run to WORKSPACE.remap, so its database outlives the emptied workspace."""
    previous = workspace.with_name(workspace.name + ".remap")
    shutil.rmtree(previous, ignore_errors=True)
    workspace.rename(previous)
    return previous


def _own_database(previous: Path) -> tuple[Path, bool, dict]:
    """A set-aside run's database to map again, as ``_reusable`` gives one: all of it reused."""
    timings = json.loads((previous / "eval.json").read_text()).get("timings", {})
    return previous / "database.db", False, timings


def _count_reused(info: dict, reuse: Path, source_timings: dict, features_only: bool) -> None:
    """Add the reused stages' times to the run's, as if it had run them (not the mapping)."""
    reused = {
        k: v
        for k, v in source_timings.items()
        if not k.endswith("map") and (k == "extract" or not features_only)
    }
    info["timings"] = {
        **info["timings"],
        **{k: v + info["timings"].get(k, 0.0) for k, v in reused.items()},
    }
    info["wall_time"] += sum(reused.values())
    info["reused"] = {"database": str(reuse), "stages": sorted(reused)}


def _load_scene(
    scene_dir: Path, seed: int | None
) -> tuple[dict, list, pycolmap.Reconstruction | None]:
    """The scene's record to fill (no methods yet), its manifest images and reference model."""
    one = json.loads((scene_dir / "manifest.json").read_text(encoding="utf-8"))
    images = one["images"]
    ref_path = (one.get("reference") or {}).get("path")
    reference = pycolmap.Reconstruction(ref_path) if ref_path and Path(ref_path).is_dir() else None
    out = {
        "scene": one.get("scene", scene_dir.name),
        "subset": one.get("subset", "all"),
        "scene_dir": str(scene_dir),
        "reference": ref_path,
        "seed": seed,
        "eras": era_counts(images),
        "methods": {},
    }
    return out, images, reference


def evaluate_scene(
    scene_dir: Path,
    methods: list[str],
    runs_dir: Path | None = None,
    extra_conf: dict | None = None,
    resume: bool = False,
    seed: int | None = None,
    feature_conf: dict | None = None,
    databases_from: Path | None = None,
    remap: bool = False,
    threads: int | None = None,
    reuse_from: list[str] | None = None,
    **tol,
) -> dict:
    """Run every method on one laid-out scene (SCENE/images + SCENE/manifest.json) and score it
    (``seed``: the mappers' random seed; runs go to SCENE/runs/seed<seed>/ then; ``threads``: the
    mappers' threads, 1 = every run repeats exactly; ``databases_from``: the runs folder of another
    seed whose finished databases are mapped again; ``remap``: a finished run maps its own database
    again, after a change of the mapping stage or of ``threads``; pycolmap's runs too;
    ``reuse_from``: the methods whose finished databases a run may start from, default
    ``methods``)."""
    scene_dir = Path(scene_dir)
    out, images, reference = _load_scene(scene_dir, seed)
    runs_dir = Path(runs_dir) if runs_dir else seed_runs_dir(scene_dir, seed)
    sources = [runs_dir] + ([Path(databases_from)] if databases_from else [])
    run = partial(
        run_method, extra_conf=extra_conf, seed=seed, feature_conf=feature_conf, threads=threads
    )
    for method in methods:
        workspace = runs_dir / method_slug(method)
        done = workspace / "eval.json"
        own = remap and done.is_file() and (workspace / "database.db").is_file()
        if resume and done.is_file() and not own:
            out["methods"][method] = json.loads(done.read_text())
            continue
        logger.info("%s [%s]: %s", out["scene"], out["subset"], method)
        previous = _set_aside(workspace) if own else None  # the workspace is emptied before the run
        try:
            reuse, features_only, source_timings = (
                _own_database(previous)
                if own
                else _reusable(sources, reuse_from or methods, method)
            )
            largest, info = run(
                scene_dir, method, workspace, database=reuse, features_only=features_only
            )
        except Exception as err:  # one failing method must not lose the others' results
            logger.error("%s [%s] %s failed: %r", out["scene"], out["subset"], method, err)
            out["methods"][method] = {"error": repr(err)}
            continue
        if reuse is not None:
            _count_reused(info, reuse, source_timings, features_only)
        if own:
            shutil.rmtree(previous)
            info["reused"]["database"] = "the same run's, mapped again (remap)"
        score = score_registration(largest, images, reference, info.get("same_picture"), **tol)
        record = {**score, **info}
        workspace.mkdir(parents=True, exist_ok=True)
        done.write_text(json.dumps(record, indent=1, default=str), encoding="utf-8")
        out["methods"][method] = record
    return out


def era_counts(images: list[dict]) -> dict:
    out = {}
    for im in photos(images):
        out[im["era"]] = out.get(im["era"], 0) + 1
    return out


# ------------------------------------------------------------------------------------- reporting
def _cell(rec: dict | None) -> str:
    if not rec:
        return "–"
    if "error" in rec:
        return "failed"
    return f"{rec['num_registered']}/{rec['num_images']} ({100 * rec['registered_ratio']:.0f} %)"


def _check_cell(rec: dict | None) -> str:
    if not rec or "error" in rec:
        return "–"
    d = (
        f"{len(rec['distractors_registered'])}/{rec['num_distractors']}"
        if rec.get("num_distractors")
        else "–"
    )
    if rec.get("correct") is None:
        return f"no ref · distr. {d}"
    return f"{rec['correct']} ok · {len(rec['wrong'])} wrong · distr. {d}"


def markdown_tables(results: list[dict], methods: list[str]) -> str:
    from .tables import markdown_table

    head = ["scene", "subset", "images h/m/d"]
    rows, rows2 = [], []
    for r in results:
        counts = r.get("eras", {})
        n = f"{counts.get('historical', 0)}/{counts.get('modern', 0)}/{counts.get('distractor', 0)}"
        rows.append([r["scene"], r["subset"], n] + [_cell(r["methods"].get(m)) for m in methods])
        rows2.append(
            [r["scene"], r["subset"]] + [_check_cell(r["methods"].get(m)) for m in methods]
        )
    text = "Registered images (largest model; distractors not counted):\n\n" + markdown_table(
        head + methods, rows
    )
    means = []
    for subset in sorted({r["subset"] for r in results}):
        vals = []
        for m in methods:
            ratios = [
                r["methods"][m]["registered_ratio"]
                for r in results
                if r["subset"] == subset and "registered_ratio" in r["methods"].get(m, {})
            ]
            vals.append(f"{100 * np.mean(ratios):.0f} %" if ratios else "–")
        means.append([subset] + vals)
    text += "\n\nMean registered ratio per subset (paper Fig. 5a):\n\n" + markdown_table(
        ["subset"] + methods, means
    )
    text += (
        "\n\nAgreement with the reference model (rotation < 5°, centre < "
        "10 % of the scene depth) and distractors registered (must be 0):\n\n"
        + markdown_table(["scene", "subset"] + methods, rows2)
    )
    return text


def plot_registration(results: list[dict], methods: list[str], path: Path) -> None:
    from . import tables

    subsets = [s for s in ("historical", "modern", "all") if any(r["subset"] == s for r in results)]
    fig, axes = tables.figure(max(1, len(subsets)), 6.5, 4.2)
    for ax, subset in zip(axes, subsets):
        rs = [r for r in results if r["subset"] == subset]
        series = {
            m: [100 * r["methods"].get(m, {}).get("registered_ratio", float("nan")) for r in rs]
            for m in methods
        }
        tables.grouped_bars(
            None,
            [r["scene"] for r in rs],
            series,
            "registered images (%)",
            f"Registered ratio — {subset} images",
            (0, 105),
            ax=ax,
        )
    tables.save_figure(fig, path)


def report_markdown(title: str, methods: list[str], results: list[dict]) -> str:
    """The registration tables under a title with the machine and date."""
    from . import tables

    note = tables.machine_note()
    return (
        f"### {title}: registration ({note['date']}, "
        f"{note['torch_device']}, {note['cpu_count']} CPUs)\n\n" + markdown_tables(results, methods)
    )
