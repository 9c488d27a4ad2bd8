"""Lay a multi-scene manifest out as scene folders and reconstruct each (historical-only and all
images).

    # LTLL (not downloadable here): scan a local copy, then run
    python -m recon_scripts.run_manifest --manifest datasets/ltll_manifest.json --root /data/LTLL
        --scan
    # the photo sets of ../shared/data (all modern), offline
    python -m recon_scripts.run_manifest --manifest datasets/shared_manifest.json
        --scenes sacre_coeur_hloc --subsets all
    # regenerate datasets/shared_manifest.json from ../shared/data
    python -m recon_scripts.run_manifest --write_shared_manifest datasets/shared_manifest.json

--scan lists ROOT/SCENE/{historical|old|...,modern|new|...}/... (or
ROOT/{historical,modern}/SCENE/...) and writes the filled manifest to --scanned_manifest (the
repository's manifest is not overwritten). Each scene and subset becomes
OUTPUT/<scene>__<subset>/images (symlinks; --copy to copy) + manifest.json; the source is never
modified. --methods: 'pycolmap' (pycolmap's default pipeline) and/or matcher specs of the registry
(raw, guided, guided:ratio=0.9, ...), each run with `reconstruct`. Prints the per-scene table,
writes OUTPUT/results.json, results.md and registered.png.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from colmap_guided.features import list_images
from colmap_guided.log import logger, set_verbosity
from colmap_guided.paths import REPO_ROOT, shared_data_dir
from colmap_guided.workspace import Workspace
from recon_scripts.evaluation import manifest as mf
from recon_scripts.evaluation import registration


def shared_manifest(data_dir: Path | None = None) -> dict:
    """The manifest of ../shared/data: every multi-view set, all era=modern
    (no real historical set)."""
    data_dir = Path(data_dir) if data_dir else shared_data_dir()
    skip = {
        "wxbs_v1.1": "two-view pairs, not a scene",
        "lightglue_assets": "two unrelated pairs, not a scene",
    }
    scenes = []
    keys = [d.name for d in sorted(data_dir.iterdir()) if d.is_dir() and d.name != "train"]
    keys += (
        [f"train/{d.name}" for d in sorted((data_dir / "train").iterdir()) if d.is_dir()]
        if (data_dir / "train").is_dir()
        else []
    )
    for key in keys:
        if key in skip or not (data_dir / key / "images").is_dir():
            continue
        ref = next(
            (sub for sub in ("colmap_ground_truth", "colmap") if (data_dir / key / sub).is_dir()),
            None,
        )
        scenes.append(
            {
                "name": key.split("/")[-1],
                "path": key,
                "image_dir": "images",
                "reference": {
                    "type": "colmap",
                    "path": ref,
                    "kind": "reference" if ref == "colmap_ground_truth" else "pseudo_gt",
                }
                if ref
                else None,
                "images": [
                    {"name": n, "era": "modern"} for n in list_images(data_dir / key / "images")
                ],
            }
        )
    return {
        "name": "shared_data",
        "description": "The real photo sets of ../shared/data described with the LTLL manifest "
        "schema. All photos are modern (no real historical multi-view set is available offline); "
        "for historical images use the proxy of recon_scripts/make_historical_proxy.py (its "
        "OUTPUT/proxy_manifest.json has the same schema). Skipped: "
        + "; ".join(f"{k} ({v})" for k, v in skip.items())
        + ".",
        "source": "../shared/data/README.md and each set's "
        "_source.json (provenance, licences: research/test use only)",
        "root": "$COLMAP_GUIDED_DATA",
        "reference_paths": "relative to the scene's path; 'colmap_ground_truth' "
        "is a reference model, 'colmap' the train scenes' pseudo ground truth",
        "scenes": scenes,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=" ".join(__doc__.split("\n\n")[0].split()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    parser.add_argument(
        "--manifest", type=Path, default=REPO_ROOT / "datasets" / "ltll_manifest.json"
    )
    mf.add_manifest_flags(
        parser,
        output=REPO_ROOT / "outputs" / "run_manifest",
        methods=["raw"],
        methods_help="'pycolmap' and/or matcher specs (raw, guided, ...)",
    )
    parser.add_argument(
        "--scanned_manifest",
        type=Path,
        default=None,
        help="where --scan writes the filled manifest (default OUTPUT/manifest_scanned.json)",
    )
    parser.add_argument(
        "--write_shared_manifest",
        type=Path,
        default=None,
        help="write the ../shared/data manifest here and exit",
    )
    parser.add_argument(
        "--layout_only", action="store_true", help="lay the scenes out, do not reconstruct"
    )
    parser.add_argument(
        "--copy", action="store_true", help="copy the photos instead of symlinking them"
    )
    args = parser.parse_args(argv)
    set_verbosity(False, args.quiet)
    try:  # refused before any work: a folder of the user's files, or one holding the photos
        Workspace.claim(args.output, "evaluation").record(*registration.REPORT_FILES)
    except ValueError as err:
        logger.error("%s", err)
        return 2

    if args.write_shared_manifest:
        mf.save_manifest(args.write_shared_manifest, shared_manifest())
        print(f"Wrote {args.write_shared_manifest}")
        return 0
    data = mf.load_manifest(args.manifest, args.root)
    if args.scan:
        if data["_root"] is None:
            parser.error("--scan needs --root (the local copy)")
        data["scenes"] = mf.scan_root(data["_root"])
        data["root"] = str(Path(data["_root"]).resolve())
        out = args.scanned_manifest or args.output / "manifest_scanned.json"
        mf.save_manifest(out, data)
        print(f"Scanned {len(data['scenes'])} scenes -> {out}")
    scenes = mf.select_scenes(data, args.scenes, args.max_scenes)
    if not scenes:
        logger.error(
            "The manifest %s lists no scene with images: pass --root and --scan for a local copy.",
            args.manifest,
        )
        return 2
    results = []
    for scene in scenes:
        for subset in args.subsets:
            scene_dir = mf.layout_scene(data, scene, subset, args.output, copy=args.copy)
            if scene_dir is None:
                logger.info("%s: fewer than 2 %s images, skipped.", scene["name"], subset)
                continue
            if args.layout_only:
                print(scene_dir)
                continue
            results.append(
                registration.evaluate_scene(
                    scene_dir,
                    args.methods,
                    extra_conf={"device": args.device, "weights": args.weights},
                    resume=args.resume,
                )
            )
    if args.layout_only or not results:
        return 0
    text = registration.write_report(
        args.output, data.get("name", "manifest"), args.manifest, args.methods, results
    )
    print(text)
    print(f"\nResults in {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
