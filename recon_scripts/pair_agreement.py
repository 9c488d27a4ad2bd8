"""Per pair of the historical proxy: how right are the guided and the raw verified inliers, and does
their agreement tell?

    python -m recon_scripts.pair_agreement --results outputs/eval_s7_agree
        [--proxy_dir outputs/historical_proxy_s5]
        [--reference sacre_coeur_hloc=outputs/refs/sacre_coeur_hloc/sparse/0] [--json pairs.json]

For every pair of photos of a proxy scene that the reference model covers, the guided matches
(no raw side) and the raw matches (mutual NN + ratio) on the keypoints of an eval_registration run
(RESULTS/scenes/<scene>__all/ runs/seed0/guided/database.db) are verified as the pipeline does; each
side's inliers are scored against the reference: the share within 6 px of the reference epipolar
line (a proxy photo maps to its reference camera by its recorded scale and crop). The agreement of
the two sides (``verify.agreement``: the share of one side's inliers that fit the other's
fundamental matrix, both ways) is what the guided matcher's ``min_agreement`` reads; the table shows
how right each side is per agreement bucket, over the pairs where both verify.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np
import pycolmap

from colmap_guided import verify
from colmap_guided.database import open_database, read_image_data
from colmap_guided.geometry import fundamental_from_poses
from colmap_guided.log import colmap_quiet
from colmap_guided.matchers import get_matcher
from colmap_guided.matchers.raw import mutual_nn_match, normalize_descriptors
from colmap_guided.paths import REPO_ROOT

BUCKETS = [(0.0, 0.3), (0.3, 0.6), (0.6, 0.8), (0.8, 0.9), (0.9, 1.01)]


def reference_fundamental(ref: pycolmap.Reconstruction, entry_a: dict, entry_b: dict) -> np.ndarray:
    """F of the pair from the reference poses, in the proxy photos' pixels (a proxy photo is its
    source resized by ``scale``, then cropped at ``crop_offset``; COLMAP's keypoints put the image
    corner at 0, 0)."""
    images = {im.name: im for im in ref.images.values()}

    def calibration(entry: dict) -> np.ndarray:
        image = images[entry["ref_name"]]
        K = ref.cameras[image.camera_id].calibration_matrix().copy()
        K[:2] *= entry["scale"]
        K[:2, 2] -= np.asarray(entry.get("crop_offset", [0, 0]), float)
        return K

    poses = [images[entry["ref_name"]].cam_from_world() for entry in (entry_a, entry_b)]
    (R_a, t_a), (R_b, t_b) = (
        (pose.rotation.matrix(), np.asarray(pose.translation)) for pose in poses
    )
    return fundamental_from_poses(calibration(entry_a), R_a, t_a, calibration(entry_b), R_b, t_b)


def share_right(
    F: np.ndarray, kp_a: np.ndarray, kp_b: np.ndarray, inliers: np.ndarray, max_px: float = 6.0
) -> float | None:
    """Share of ``inliers`` within ``max_px`` of the reference epipolar lines, in both images."""
    if len(inliers) == 0:
        return None
    xa = np.c_[kp_a[inliers[:, 0], :2], np.ones(len(inliers))]
    xb = np.c_[kp_b[inliers[:, 1], :2], np.ones(len(inliers))]
    la, lb = xa @ F.T, xb @ F
    d = np.abs(np.sum(xb * la, 1))
    err = np.maximum(d / np.linalg.norm(la[:, :2], axis=1), d / np.linalg.norm(lb[:, :2], axis=1))
    return float(np.mean(err < max_px))


def scene_pairs(
    scene_dir: Path, database: Path, ref: pycolmap.Reconstruction, guided
) -> list[dict]:
    entries = {
        im["name"]: im for im in json.loads((scene_dir / "manifest.json").read_text())["images"]
    }
    covered = {im.name for im in ref.images.values()}
    with open_database(database) as db:
        images = {
            im.name: read_image_data(db, im, scene_dir / "images") for im in db.read_all_images()
        }
    names = sorted(
        n for n in images if entries[n]["era"] != "distractor" and entries[n]["ref_name"] in covered
    )
    options = verify.two_view_options({"min_num_inliers": 15})
    rows = []
    for name_a, name_b in itertools.combinations(names, 2):
        a, b = images[name_a], images[name_b]
        raw = (
            mutual_nn_match(
                normalize_descriptors(a.descriptors, "cpu"),
                normalize_descriptors(b.descriptors, "cpu"),
                guided.conf["ratio"],
            )
            .cpu()
            .numpy()
        )
        with colmap_quiet():
            geometries = [
                verify.verify_pair(
                    a.camera, a.keypoints, b.camera, b.keypoints, m.astype(np.uint32), options
                )
                for m in (guided.match(a, b), raw)
            ]
        g_inl, r_inl = (np.asarray(g.inlier_matches, np.int64).reshape(-1, 2) for g in geometries)
        F = reference_fundamental(ref, entries[name_a], entries[name_b])
        rows.append(
            {
                "scene": scene_dir.name,
                "a": name_a,
                "b": name_b,
                "eras": entries[name_a]["era"][0] + entries[name_b]["era"][0],
                "guided": len(g_inl),
                "raw": len(r_inl),
                "guided_right": share_right(F, a.keypoints, b.keypoints, g_inl),
                "raw_right": share_right(F, a.keypoints, b.keypoints, r_inl),
                "agreement": min(
                    verify.agreement(
                        geometries[0], a.keypoints, b.keypoints, r_inl, options.ransac.max_error
                    ),
                    verify.agreement(
                        geometries[1], a.keypoints, b.keypoints, g_inl, options.ransac.max_error
                    ),
                ),
            }
        )
    for name in images:
        guided.release(name)  # the backbone cache is by image name, and scenes share names
    return rows


def table(rows: list[dict], guided_min: int, raw_min: int) -> str:
    both = [r for r in rows if r["guided"] >= guided_min and r["raw"] >= raw_min]
    lines = [
        f"{len(rows)} pairs, {len(both)} where both sides verify "
        f"(guided >= {guided_min}, raw >= {raw_min} inliers)",
        "",
        "| agreement (min of both ways) | pairs | "
        "guided inliers right (median) | raw inliers right (median) | "
        "raw better / guided better (±5 pts) | wrong inliers guided / raw |",
        "|---|---|---|---|---|---|",
    ]
    for lo, hi in BUCKETS:
        sel = [r for r in both if lo <= r["agreement"] < hi]
        if not sel:
            continue
        g, r = np.array([s["guided_right"] for s in sel]), np.array([s["raw_right"] for s in sel])
        wrong_g = sum(s["guided"] * (1 - s["guided_right"]) for s in sel)
        wrong_r = sum(s["raw"] * (1 - s["raw_right"]) for s in sel)
        span = f"≥ {lo}" if hi > 1 else (f"< {hi}" if lo == 0 else f"{lo}–{hi}")
        lines.append(
            f"| {span} | {len(sel)} | {100 * np.median(g):.0f} % | {100 * np.median(r):.0f} % | "
            f"{np.sum(r > g + 0.05)} / {np.sum(g > r + 0.05)} | {wrong_g:.0f} / {wrong_r:.0f} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=" ".join(__doc__.split("\n\n")[0].split()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    parser.add_argument(
        "--results",
        type=Path,
        required=True,
        help="an eval_registration output with guided runs (their keypoints are used)",
    )
    parser.add_argument(
        "--proxy_dir", type=Path, default=REPO_ROOT / "outputs" / "historical_proxy_s5"
    )
    parser.add_argument(
        "--reference",
        nargs="*",
        default=[],
        help="SCENE_PREFIX=MODEL_DIR: a reference for scenes without one",
    )
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    refs = {k: v for k, _, v in (r.partition("=") for r in args.reference)}
    guided = get_matcher("guided", {"raw_matches": None, "workers": 1})
    rows = []
    for scene_dir in sorted(p for p in args.proxy_dir.iterdir() if (p / "manifest.json").is_file()):
        manifest = json.loads((scene_dir / "manifest.json").read_text())
        ref_path = next(
            (v for k, v in refs.items() if scene_dir.name in (k, f"{k}_realistic")),
            (manifest.get("reference") or {}).get("path"),
        )
        database = (
            args.results
            / "scenes"
            / f"{scene_dir.name}__all"
            / "runs"
            / "seed0"
            / "guided"
            / "database.db"
        )
        if not ref_path or not database.is_file():
            print(
                f"{scene_dir.name}: skipped (no reference or no guided run in {args.results})",
                file=sys.stderr,
            )
            continue
        rows += scene_pairs(scene_dir, database, pycolmap.Reconstruction(str(ref_path)), guided)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    print(table(rows, guided.conf["min_inliers"], guided.conf["raw_min_inliers"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
