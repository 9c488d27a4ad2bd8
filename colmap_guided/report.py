"""Stage 6: the report — registered ratio per scene (LTLL-style, paper Fig. 5a), model statistics, timings.

``report.json`` holds what a script compares; the summary printed on stdout is what a person reads.
An image manifest (``SCENE_DIR/manifest.json``, the datasets/ltll_manifest.json schema for one scene:
``{"images": [{"name": ..., "era": "historical"|"modern"}, ...]}``) adds the ratio per era.
"""

from __future__ import annotations

import json
from pathlib import Path

import pycolmap


def model_statistics(models: dict[int, pycolmap.Reconstruction], image_names: list[str]) -> dict:
    """Statistics of the largest model; images registered in another model count as not registered."""
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
        "mean_track_length": largest.compute_mean_track_length() if largest and largest.num_points3D() else 0.0,
        "mean_reprojection_error": largest.compute_mean_reprojection_error() if largest and largest.num_points3D() else 0.0,
        "registered_images": registered,
        "unregistered_images": sorted(set(image_names) - set(registered)),
    }


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
            out[era] = {"num_images": len(names), "num_registered": sum(n in registered for n in names), "registered_ratio": sum(n in registered for n in names) / len(names)}
    return out


def write_report(path: Path, report: dict) -> None:
    tmp = Path(path).with_suffix(".json.partial")
    tmp.write_text(json.dumps(report, indent=2, default=str), encoding="utf-8")
    tmp.replace(path)


def summary_text(report: dict) -> str:
    s = report["model"]
    lines = [
        f"Scene: {report['scene']}",
        f"Registered {s['num_registered']}/{s['num_images']} images ({100 * s['registered_ratio']:.0f} %) in the largest of {s['num_models']} model(s)",
        f"3D points: {s['num_points3D']}, mean track length {s['mean_track_length']:.2f}, mean reprojection error {s['mean_reprojection_error']:.2f} px",
    ]
    problems = (report.get("model_check") or {}).get("problems", [])
    if problems:
        lines.append(f"WARNING: the model check found {len(problems)} problem(s), e.g. {problems[0]} (all in report.json, model_check)")
    for era, r in report.get("eras", {}).items():
        lines.append(f"  {era}: {r['num_registered']}/{r['num_images']} registered ({100 * r['registered_ratio']:.0f} %)")
    skipped = report.get("skipped_images") or {}
    unregistered = [name for name in s["unregistered_images"] if name not in skipped]
    if unregistered:
        shown = ", ".join(unregistered[:10]) + (" ..." if len(unregistered) > 10 else "")
        lines.append(f"Not registered: {shown}")
    if skipped:
        reasons = skipped if isinstance(skipped, dict) else dict.fromkeys(skipped, "unreadable")
        lines.append(f"Skipped {len(reasons)} image(s):")
        lines.extend(f"  {name}: {reason}" for name, reason in list(reasons.items())[:10])
        if len(reasons) > 10:
            lines.append(f"  ... and {len(reasons) - 10} more (report.json, skipped_images)")
    times = ", ".join(f"{k} {v:.1f} s" for k, v in report["timings"].items())
    lines.append(f"Time: {times}")
    lines.append(f"Model: {report['sparse_path']}/0   Report: {report['report_path']}")
    if report.get("html_report_path"):
        lines.append(f"Open in a browser: {report['html_report_path']}")
    return "\n".join(lines)
