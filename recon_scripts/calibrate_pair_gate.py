"""Which pairs are worth the fine matcher: the coarse network's pair-level evidence against the fine
matcher's verdict.

    python -m recon_scripts.calibrate_pair_gate --output outputs/pair_gate
        [--sources sacre_coeur_hloc ...]
        [--max_images 8] [--matcher guided_lightglue]

On development scenes of the historical proxy (half of each set a damaged print, plus distractors),
every pair of photos is matched by the fine matcher and verified as the pipeline does; beside it,
the coarse network's evidence for the pair (``CoarseFlows.pair_score``, paper eq. 3's image-level
score: the mean over grid cells of their best match probability, the smaller direction) and the
fine matcher's matches on only its best ``--budget`` keypoints of each photo. Prints, per threshold,
the verified pairs a gate would lose and the pairs it would skip (``guided_lightglue``'s
``min_pair_score``), and what the budget gives the pairs it would keep per fallback threshold (a
pair with fewer matches in the window is matched again on every keypoint). Development split only:
the gate's threshold is chosen here.
"""

from __future__ import annotations

import itertools
import json
import time
from pathlib import Path

import numpy as np

from colmap_guided import database as dbio
from colmap_guided import features, verify
from colmap_guided.log import colmap_quiet, set_verbosity
from colmap_guided.matchers import get_matcher
from colmap_guided.workspace import Workspace
from recon_scripts import script_parser
from recon_scripts.evaluation import matcher_specs, proxy

DEV_SOURCES = (
    "sacre_coeur_hloc",
    "lund_door_gtsfm",
    "train/dfsfm_sacre_coeur",
    "train/vggsfm_british_museum",
)


def scene_pairs(scene_dir: Path, matcher, min_inliers: int, budget: int) -> list[dict]:
    """Every pair of the scene: related (neither a distractor), coarse evidence, verified
    inliers."""
    eras = {
        im["name"]: im["era"]
        for im in json.loads((scene_dir / "manifest.json").read_text())["images"]
    }
    database = scene_dir / "database.db"
    features.extract_features(database, scene_dir / "images", conf={"type": "aliked"})
    options = verify.two_view_options({"min_num_inliers": min_inliers})
    rows = []
    with dbio.open_database(database) as db:
        images = {
            n: dbio.read_image_data(db, im, scene_dir / "images")
            for n, im in dbio.images_by_name(db).items()
        }
        for image in images.values():
            matcher.prepare(image)
        for a, b in itertools.combinations(sorted(images), 2):
            ia, ib = images[a], images[b]
            flows = matcher.coarse_flows(ia, ib)
            start = time.perf_counter()
            m = matcher.match_flows(ia, ib, flows)
            seconds = time.perf_counter() - start
            start = time.perf_counter()
            best = [np.arange(min(budget, len(im.keypoints))) for im in (ia, ib)]
            few = matcher.in_window(ia, ib, flows, *best, matcher.conf["window_cells"])
            budget_s = time.perf_counter() - start
            cams = [verify.default_camera(im.width, im.height) for im in (ia, ib)]
            with colmap_quiet():
                geometry, few_geometry = (
                    verify.verify_pair(cams[0], ia.keypoints, cams[1], ib.keypoints, x, options)
                    for x in (m, few)
                )
            inliers, few_inliers = len(geometry.inlier_matches), len(few_geometry.inlier_matches)
            agree = (
                verify.agreement(
                    geometry,
                    ia.keypoints,
                    ib.keypoints,
                    few_geometry.inlier_matches,
                    options.ransac.max_error,
                )
                if inliers >= min_inliers
                else 0.0
            )
            rows.append(
                {
                    "scene": scene_dir.name,
                    "a": a,
                    "b": b,
                    "related": "distractor" not in (eras[a], eras[b]),
                    "score": flows.pair_score,
                    "inliers": inliers,
                    "verified": inliers >= min_inliers,
                    "fine_s": seconds,
                    "budget": len(few),
                    "budget_inliers": few_inliers,
                    "budget_agreement": agree,
                    "budget_s": budget_s,
                }
            )
    for name in images:  # scenes of one landmark share file names
        matcher.release(name)
    return rows


def gate_table(rows: list[dict], key: str, thresholds) -> list[str]:
    verified = [r for r in rows if r["verified"]]
    lines = [
        f"| {key} below | verified pairs lost | related pairs skipped | "
        "unrelated skipped | fine time skipped |",
        "|---|---|---|---|---|",
    ]
    total = sum(r["fine_s"] for r in rows)
    for t in thresholds:
        gated = [r for r in rows if r[key] < t]
        lost = [r for r in gated if r["verified"]]
        lines.append(
            f"| {t:g} | {len(lost)} / {len(verified)} "
            f"(max {max((r['inliers'] for r in lost), default=0)} inliers) "
            f"| {sum(r['related'] for r in gated)} / {sum(r['related'] for r in rows)} "
            f"| {sum(not r['related'] for r in gated)} / {sum(not r['related'] for r in rows)} "
            f"| {sum(r['fine_s'] for r in gated) / total:.0%} |"
        )
    return lines


def budget_table(rows: list[dict], thresholds, min_inliers: int) -> list[str]:
    """Pairs whose matches on the budget reach each threshold keep them; the others are matched
    again on every keypoint."""
    lines = [
        "| fallback below | pairs kept at the budget (unrelated) | verified on every keypoint "
        "among them | inliers, budget / every keypoint, min · median | budget inliers on every "
        "keypoint's geometry, min | verified by the budget only "
        "| fine time against every keypoint |",
        "|---|---|---|---|---|---|---|",
    ]
    total = sum(r["fine_s"] for r in rows)
    for t in thresholds:
        kept = [r for r in rows if r["budget"] >= t]
        both = [r for r in kept if r["verified"]]
        share = [r["budget_inliers"] / r["inliers"] for r in both]
        cost = sum(r["budget_s"] for r in rows) + sum(r["fine_s"] for r in rows if r["budget"] < t)
        lines.append(
            f"| {t} | {len(kept)} ({sum(not r['related'] for r in kept)}) | {len(both)} "
            f"| {min(share, default=0):.2f} · {np.median(share) if share else 0:.2f} "
            f"| {min((r['budget_agreement'] for r in both), default=0):.2f} "
            f"| {sum(not r['verified'] and r['budget_inliers'] >= min_inliers for r in kept)} "
            f"| {cost / total:.2f}x |"
        )
    return lines


def main(argv=None):
    parser = script_parser(__doc__)
    parser.add_argument(
        "--output", type=Path, required=True, help="proxy scenes, databases and pairs.json go here"
    )
    parser.add_argument("--sources", nargs="+", default=DEV_SOURCES)
    parser.add_argument(
        "--max_images", type=int, default=8, help="photos per source (distractors added)"
    )
    parser.add_argument(
        "--matcher",
        default="guided_lightglue:min_pair_score=none",
        help="the fine matcher, a spec: preset[:key=value,...]",
    )
    parser.add_argument(
        "--budget", type=int, default=1024, help="keypoints per photo, the best first"
    )
    args = parser.parse_args(argv)
    set_verbosity(quiet=True)
    leaked = set(args.sources) & set(proxy.SPLITS["test"])
    if leaked:
        parser.error(
            f"{sorted(leaked)} belong to the test split: "
            "the gate is chosen on development scenes only"
        )
    spec = matcher_specs.parse_spec(args.matcher)
    matcher = get_matcher(spec.name, spec.conf)
    min_inliers = matcher.verification_conf["min_num_inliers"]
    rows = []
    for key in args.sources:
        scene_dir = proxy.build_scene(key, args.output, max_images=args.max_images)
        workspace = Workspace(args.output, "proxy")
        # an earlier run's, for photos drawn again
        if workspace.owns(f"{scene_dir.name}/database.db"):
            workspace.remove(f"{scene_dir.name}/database.db")
        workspace.record(f"{scene_dir.name}/database.db")
        rows += scene_pairs(scene_dir, matcher, min_inliers, args.budget)
    workspace.record("pairs.json")[0].write_text(json.dumps(rows, indent=1) + "\n")
    print("\n".join(gate_table(rows, "score", (0.02, 0.05, 0.1, 0.15, 0.2, 0.3))) + "\n")
    thresholds = (60, 100, 150, 200, 300, 400, 600)
    print("\n".join(budget_table(rows, thresholds, min_inliers)) + "\n")
    for label, pick in (
        ("verified", lambda r: r["verified"]),
        ("not verified", lambda r: not r["verified"]),
    ):
        values = np.array([r["score"] for r in rows if pick(r)])
        if len(values):
            print(
                f"{label} pairs ({len(values)}): score min "
                f"{values.min():.3f}, 5% {np.percentile(values, 5):.3f}, "
                f"median {np.median(values):.3f}, max {values.max():.3f}"
            )


if __name__ == "__main__":
    main()
