"""Stage 6: the report — registered ratio per scene (LTLL-style, paper Fig. 5a), model statistics,
timings.

``report.json`` holds what a script compares; the summary printed on stdout is what a person reads.
An image manifest (``SCENE_DIR/manifest.json``, the datasets/ltll_manifest.json schema for one
scene: ``{"images": [{"name": ..., "era": "historical"|"modern"}, ...]}``) adds the ratio per era.
"""

from __future__ import annotations

import json
from pathlib import Path

import pycolmap

# model_statistics' figures that report.json also gives at its top level
SUMMARY_KEYS = (
    "num_images",
    "num_registered",
    "registered_ratio",
    "num_points3D",
    "mean_track_length",
    "mean_reprojection_error",
)


def model_statistics(models: dict[int, pycolmap.Reconstruction], image_names: list[str]) -> dict:
    """Statistics of the largest model; images registered in another model count as not
    registered."""
    largest = max(models.values(), key=lambda rec: rec.num_reg_images(), default=None)
    registered = sorted(largest.images[i].name for i in largest.reg_image_ids()) if largest else []
    num_images = len(image_names)
    return {
        "num_images": num_images,
        "num_registered": len(registered),
        "registered_ratio": len(registered) / num_images if num_images else 0.0,
        "num_models": len(models),
        "num_registered_all_models": sum(rec.num_reg_images() for rec in models.values()),
        "num_points3D": largest.num_points3D() if largest else 0,
        "mean_track_length": largest.compute_mean_track_length()
        if largest and largest.num_points3D()
        else 0.0,
        "mean_reprojection_error": largest.compute_mean_reprojection_error()
        if largest and largest.num_points3D()
        else 0.0,
        "registered_images": registered,
        "unregistered_images": sorted(set(image_names) - set(registered)),
    }


def model_entries(
    models: dict[int, pycolmap.Reconstruction], problems: dict[int, list[str]], eras: dict[str, str]
) -> list[dict]:
    """Every model, largest first: a building, or a part of one. Its folder, photos, points, model
    check (``problems``: ``model_check.check_each``) and photos per era."""
    out = []
    for index, rec in sorted(models.items()):
        names = sorted(rec.images[i].name for i in rec.reg_image_ids())
        entry = {
            "index": index,
            "path": f"sparse/{index}",
            "num_registered": len(names),
            "num_points3D": rec.num_points3D(),
            "passes_check": not problems[index],
            "problems": problems[index],
            "images": names,
        }
        if eras:
            entry["eras"] = {
                e: sum(eras.get(n) == e for n in names) for e in sorted(set(eras.values()))
            }
        out.append(entry)
    return out


def read_manifest(path: Path) -> dict[str, str]:
    """name -> era from a one-scene manifest; {} when there is none."""
    path = Path(path)
    if not path.is_file():
        return {}
    data = json.loads(path.read_text(encoding="utf-8"))
    return {entry["name"]: entry.get("era", "modern") for entry in data.get("images", [])}


def era_ratios(eras: dict[str, str], registered: list[str], image_names: list[str]) -> dict:
    """Registered ratio for historical images only and for all images (paper Fig. 5a)."""
    registered = set(registered)
    out = {}
    for era in sorted(set(eras.values())):
        names = [n for n in image_names if eras.get(n) == era]
        if names:
            out[era] = {
                "num_images": len(names),
                "num_registered": sum(n in registered for n in names),
                "registered_ratio": sum(n in registered for n in names) / len(names),
            }
    return out


MIN_KEYPOINTS = (
    100  # fewer SIFT keypoints than this: too little detail to match (blank, blurred, tiny scan)
)
SUGGEST = {
    "reading": "Check that the file opens in an image viewer; "
    "convert it to JPEG or scan it again, and run again.",
    "features": "Use a sharper, larger or better exposed scan of this photo.",
    "matching": "Check that it shows the landmark; if it does, add photos taken between its "
    "viewpoint (and date) and the others', so that each step shares details with the next.",
    "mapping": "Add photos taken between this one and {best}, from nearby "
    "viewpoints, so that more of its details are also seen in photos of the model.",
}


ORPHAN = (
    " Its other pairs were not matched: a photo whose first pairs all fail is taken for a photo "
    "of something else (--orphan_after none matches them all)."
)


def explain_unregistered(
    database_path: Path,
    models: dict[int, pycolmap.Reconstruction],
    image_names: list[str],
    skipped: dict[str, str],
    min_num_inliers: int = 15,
    orphans: set[str] = frozenset(),
) -> dict[str, dict]:
    """Why each photo in no model dropped out, in plain words: {name: {stage, reason, suggestion,
    evidence}}. A photo in a smaller model is a result (that model's), not listed here.

    Stages, in pipeline order: ``reading`` (skipped: the file could not be used), ``features``
    (fewer than MIN_KEYPOINTS keypoints and no verified pair), ``matching`` (no pair passed two-view
    verification; ``orphans``: its other pairs left unmatched) and ``mapping`` (verified pairs,
    yet the mapper could not place it). Evidence:
    verified pairs (two_view_geometries with inliers), the best one and its inliers, how many of the
    verified partners are in a model, and the best unverified candidate.
    """
    registered = {rec.images[i].name for rec in models.values() for i in rec.reg_image_ids()}
    todo = [name for name in image_names if name not in registered]
    out = {name: _unreadable(skipped[name]) for name in todo if name in skipped}
    if len(out) == len(todo):
        return out
    verified, candidates, keypoints = _pair_evidence(
        database_path, [name for name in todo if name not in out]
    )
    for name in todo:
        if name in out:
            continue
        pairs = verified.get(name, [])
        best_inliers, best = pairs[0] if pairs else (0, None)
        entry = {
            "verified_pairs": len(pairs),
            "best_pair": best,
            "best_inliers": best_inliers,
            "num_keypoints": keypoints[name],
        }
        if not pairs and keypoints[name] < MIN_KEYPOINTS:
            stage, reason = "features", _features_reason(keypoints[name])
        elif not pairs:
            tried = candidates.get(name, [])
            stage, reason = "matching", _matching_reason(tried, min_num_inliers)
            if name in orphans:
                reason += ORPHAN
            entry.update(
                best_candidate=tried[0][1] if tried else None,
                best_candidate_matches=tried[0][0] if tried else 0,
            )
        else:
            stage, reason = "mapping", _mapping_reason(pairs, registered)
        entry.update(stage=stage, reason=reason, suggestion=SUGGEST[stage].format(best=best))
        out[name] = entry
    return {name: out[name] for name in todo}


def _unreadable(skip_reason: str) -> dict:
    """The ``reading`` entry of a skipped photo, from its "reason; hint" text."""
    reason, _, hint = skip_reason.partition("; ")
    return {
        "stage": "reading",
        "reason": f"The file could not be used: {reason}.",
        "suggestion": (hint[:1].upper() + hint[1:] + ".") if hint else SUGGEST["reading"],
    }


def _pair_evidence(database_path: Path, names: list[str]) -> tuple[dict, dict, dict]:
    """Verified partners, tentative partners (strongest first) and keypoint counts of ``names``."""
    from . import database as dbio

    with dbio.open_database(database_path) as db:
        by_id = dbio.image_names(db)
        ids = {n: i for i, n in by_id.items()}
        verified = _partners(by_id, dbio.pair_inlier_counts(db), positive_only=True)
        candidates = _partners(by_id, dbio.pair_match_counts(db))
        keypoints = {n: dbio.num_keypoints(db, ids[n]) if n in ids else 0 for n in names}
    return verified, candidates, keypoints


def _partners(
    by_id: dict[int, str], counts: dict[tuple[int, int], int], positive_only: bool = False
) -> dict[str, list[tuple[int, str]]]:
    """{name: [(count, partner), ...]} from pair counts, largest count first, then by name."""
    table: dict[str, list[tuple[int, str]]] = {}
    for (id_a, id_b), count in counts.items():
        if count <= 0 and positive_only:
            continue
        a, b = by_id[id_a], by_id[id_b]
        table.setdefault(a, []).append((count, b))
        table.setdefault(b, []).append((count, a))
    return {name: sorted(pairs, key=lambda t: (-t[0], t[1])) for name, pairs in table.items()}


def _features_reason(num_keypoints: int) -> str:
    """Why a photo with too few keypoints matched nothing."""
    found = f"Only {num_keypoints}" if num_keypoints else "No"
    return (
        f"{found} distinctive points were found in the photo (a blank, blurred, "
        "very dark or very small image): too few to match it with the others."
    )


def _matching_reason(tried: list[tuple[int, str]], min_num_inliers: int) -> str:
    """Why none of the pairs ``tried`` (strongest first) passed two-view verification."""
    if not tried:
        return (
            "It was matched with no other photo: the pairs list leaves it out, or its pairs "
            "were left unmatched (the coarse network saw no overlap, or LightGlue found almost "
            "no match on their best keypoints) and escalation did not reach them (--rounds, "
            "--pairs_per_photo)."
        )
    num_matches, best = tried[0]
    if num_matches >= min_num_inliers:
        return (
            f"None of the {len(tried)} photos it was compared with shares enough "
            f"details with it. The best, {best}, had {num_matches} tentative "
            f"matches, but fewer than {min_num_inliers} of them fit one consistent "
            "pair of camera positions (the others are chance look-alikes)."
        )
    count = (
        f"only {num_matches} tentative match{'es' if num_matches != 1 else ''}"
        if num_matches
        else "no tentative match"
    )
    return (
        f"None of the {len(tried)} photos it was compared with shares enough "
        f"details with it: the best, {best}, had {count}, and at least "
        f"{min_num_inliers} must fit one consistent pair of camera positions."
    )


def _mapping_reason(pairs: list[tuple[int, str]], registered: set[str]) -> str:
    """Why a photo with verified pairs (strongest first) was still not placed by the mapper."""
    count, best = pairs[0]
    linked = sum(partner in registered for _, partner in pairs)
    return (
        f"It matched {len(pairs)} photo(s), {linked} of them in a model; "
        f"the best, {best}, with {count} matches that agree with "
        "one geometry. Still, the mapper could not fix its position from "
        "them: too few of those matches fall on points of the 3D model"
        + (" (none of the photos it matched is in a model)." if not linked else ".")
    )


def explain_no_model(database_path: Path, mapping_conf: dict, left_out=()) -> dict:
    """When mapping made no model: which photos are linked to which (verified pairs, strongest
    first) and why no model could start, in plain words. ``left_out``: photos not mapped
    (repeated prints)."""
    from . import database as dbio

    with dbio.open_database(database_path) as db:
        names = dbio.image_names(db)
        counts = dbio.pair_inlier_counts(db)
    pairs = sorted(
        (
            (n, names[a], names[b])
            for (a, b), n in counts.items()
            if n >= mapping_conf["min_num_matches"]
            and names[a] not in left_out
            and names[b] not in left_out
        ),
        reverse=True,
    )
    group = {name: {name} for _, a, b in pairs for name in (a, b)}
    for _, a, b in pairs:
        if group[a] is not group[b]:
            merged = group[a] | group[b]
            for name in merged:
                group[name] = merged
    largest = max((len(g) for g in group.values()), default=0)
    need, start = mapping_conf["min_model_size"], mapping_conf["init_min_num_inliers"]
    if not pairs:
        why = (
            f"No two photos share {mapping_conf['min_num_matches']} verified matches"
            + (" (apart from repeated prints of one picture, mapped once)" if left_out else "")
            + ": nothing links them. Try --camera_mode single if the photos come from one "
            "camera, or add photos taken between the existing ones."
        )
    elif largest < need:
        why = (
            f"The largest group of linked photos holds {largest}; a model needs at least {need} "
            "(mapping's min_model_size). Add a photo of the same view, or lower min_model_size."
        )
    elif pairs[0][0] < start:
        why = (
            f"A model starts from a pair with at least {start} verified matches "
            f"(init_min_num_inliers); the strongest, {pairs[0][1]} ~ {pairs[0][2]}, has "
            f"{pairs[0][0]}."
        )
    else:
        why = (
            "Linked pairs exist, but mapping could not start a model it trusts from any of them: "
            "their photos were taken from nearly the same place (too little parallax to place "
            "points in depth), or the model failed the model check."
        )
    return {
        "why": why,
        "linked": [{"photos": [a, b], "verified_matches": n} for n, a, b in pairs[:50]],
    }


def write_report(path: Path, report: dict) -> None:
    tmp = Path(path).with_suffix(".json.partial")
    tmp.write_text(json.dumps(report, indent=2, default=str), encoding="utf-8")
    tmp.replace(path)


def summary_text(report: dict) -> str:
    s = report["model"]
    lines = [
        f"Scene: {report['scene']}",
        f"Registered {s['num_registered']}/{s['num_images']} images "
        f"({100 * s['registered_ratio']:.0f} %) in the largest of {s['num_models']} model(s)",
        f"3D points: {s['num_points3D']}, mean track length {s['mean_track_length']:.2f}, "
        f"mean reprojection error {s['mean_reprojection_error']:.2f} px",
    ]
    problems = (report.get("model_check") or {}).get("problems", [])
    if problems:
        lines.append(
            f"WARNING: the model check found {len(problems)} problem(s), e.g. {problems[0]} "
            "(all in report.json, model_check)"
        )
    for era, r in report.get("eras", {}).items():
        lines.append(
            f"  {era}: {r['num_registered']}/{r['num_images']} "
            f"registered ({100 * r['registered_ratio']:.0f} %)"
        )
    others = (report.get("models") or [])[1:]
    if others:
        shown = ", ".join(f"{m['path']} ({m['num_registered']})" for m in others[:10])
        lines.append(
            f"{len(others)} other model(s), photos in each: {shown}"
            + (" ..." if len(others) > 10 else "")
        )
    cuts = (report.get("database") or {}).get("splits") or []
    if cuts:
        lines.append(f"Models cut in two (two places that look alike): {len(cuts)} (report.html)")
    tries = (report.get("database") or {}).get("joins") or []
    if tries:
        joined = sum(t["joined"] for t in tries)
        lines.append(f"Joining models: {len(tries)} tried, {joined} joined (report.html)")
    skipped = report.get("skipped_images") or {}
    why = report.get("unregistered") or {}
    unregistered = [name for name in why if name not in skipped]
    if unregistered:
        shown = ", ".join(f"{name} ({why[name]['stage']})" for name in unregistered[:10]) + (
            " ..." if len(unregistered) > 10 else ""
        )
        lines.append(f"In no model (stage where it dropped out): {shown}")
    if skipped:
        reasons = skipped if isinstance(skipped, dict) else dict.fromkeys(skipped, "unreadable")
        lines.append(f"Skipped {len(reasons)} image(s):")
        lines.extend(f"  {name}: {reason}" for name, reason in list(reasons.items())[:10])
        if len(reasons) > 10:
            lines.append(f"  ... and {len(reasons) - 10} more (report.json, skipped_images)")
    times = ", ".join(f"{k} {v:.1f} s" for k, v in report["timings"].items())
    lines.append(f"Time: {times}")
    if s["num_models"]:
        lines.append(f"Model: {report['sparse_path']}/0   Report: {report['report_path']}")
    else:
        db = report.get("database") or {}
        verified = (
            f" ({db['num_verified_pairs']} of {db['num_pairs']} photo pairs verified)"
            if "num_pairs" in db
            else ""
        )
        why = (report.get("no_model") or {}).get("why") or (
            "mapping found no starting pair it could trust. Try --camera_mode single if the "
            "photos come from one camera, or add photos taken between the existing ones."
        )
        lines.append(f"No model was made{verified}: {why[:1].lower() + why[1:]}")
        lines.append(f"Report: {report['report_path']}")
    if (report.get("exports") or {}).get("ply"):
        lines.append(f"Points for MeshLab/CloudCompare: {report['exports']['ply']}")
    if report.get("html_report_path"):
        lines.append(f"Open in a browser: {report['html_report_path']}")
    return "\n".join(lines)
