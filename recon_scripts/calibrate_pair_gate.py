"""Which pairs are worth the fine matcher: the coarse network's pair-level evidence and LightGlue's
probe on each photo's best keypoints, against the fine matcher's verdict.

    python -m recon_scripts.calibrate_pair_gate --output outputs/pair_gate
        [--sources sacre_coeur_hloc ...] [--looks damaged postcard] [--max_size 512]
        [--max_images 8] [--wxbs] [--matcher guided_lightglue:...] [--probe 1024]

On development scenes of the historical proxy (half of each set printed, plus distractors) and,
with ``--wxbs``, WxBS's real appearance-change pairs, every pair of photos is matched by the fine
matcher on every keypoint (no gate, cheap pass or probe) and verified as the pipeline does; beside
it, the coarse network's evidence for the pair (``CoarseFlows.pair_score``, paper eq. 3's
image-level score: the mean over grid cells of their best match probability, the smaller
direction) and the fine matcher on only the best ``--probe`` keypoints of each photo. Prints, per
threshold, the verified pairs a gate would lose and the pairs it would skip (``guided_lightglue``'s
``min_pair_score``), and what the probe decides (``probe_inliers``, ``probe_matches``): pairs it
keeps, leaves for escalation or matches again on every keypoint, the verified pairs it would leave
and LightGlue's time against every keypoint (the cheap pass, which runs before it in the pipeline,
is left out). Development data only: these thresholds are chosen here.
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
from colmap_guided.paths import shared_data_dir
from colmap_guided.workspace import Workspace
from recon_scripts import script_parser
from recon_scripts.evaluation import matcher_specs, proxy

DEV_SOURCES = (
    "sacre_coeur_hloc",
    "lund_door_gtsfm",
    "train/dfsfm_sacre_coeur",
    "train/vggsfm_british_museum",
)


def scene_pairs(
    name: str, images_dir: Path, eras: dict, database: Path, matcher, min_inliers: int, probe: int
) -> list[dict]:
    """Every pair of the scene (``images_dir``, features in ``database``): related (neither a
    distractor), coarse evidence, verified inliers on every keypoint and on the probe's."""
    features.extract_features(database, images_dir, conf={"type": "aliked"})
    options = verify.two_view_options({"min_num_inliers": min_inliers})
    window, rows = matcher.conf["window_cells"], []
    with dbio.open_database(database) as db:
        images = {
            n: dbio.read_image_data(db, im, images_dir) for n, im in dbio.images_by_name(db).items()
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
            best = [np.arange(min(probe, len(im.keypoints))) for im in (ia, ib)]
            few = matcher.in_window(ia, ib, flows, *best, window)
            probe_s = time.perf_counter() - start
            cams = [verify.default_camera(im.width, im.height) for im in (ia, ib)]
            with colmap_quiet():
                geometry, few_geometry = (
                    verify.verify_pair(cams[0], ia.keypoints, cams[1], ib.keypoints, x, options)
                    for x in (m, few)
                )
            inliers = len(geometry.inlier_matches)
            rows.append(
                {
                    "scene": name,
                    "a": a,
                    "b": b,
                    "related": "distractor" not in (eras.get(a), eras.get(b)),
                    "score": flows.pair_score,
                    "inliers": inliers,
                    "verified": inliers >= min_inliers,
                    "fine_s": seconds,
                    "probe": len(few),
                    "probe_inliers": len(few_geometry.inlier_matches),
                    "probe_s": probe_s,
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


def probe_table(rows: list[dict], keeps, defers) -> list[str]:
    """The probe's decisions: a pair it verifies with ``keep`` inliers keeps its matches, one with
    fewer than ``defer`` matches in the window is left for escalation, the others are matched
    again on every keypoint."""
    lines = [
        "| keep at | leave below | kept | left (unrelated) | matched again | verified pairs left "
        "| fewest matches of a verified pair | LightGlue time against every keypoint |",
        "|---|---|---|---|---|---|---|---|",
    ]
    total = sum(r["fine_s"] for r in rows)
    fewest = min((r["probe"] for r in rows if r["verified"]), default=0)
    for keep, defer in itertools.product(keeps, defers):
        kept = [r for r in rows if r["probe_inliers"] >= keep]
        left = [r for r in rows if r["probe_inliers"] < keep and r["probe"] < defer]
        again = [r for r in rows if r["probe_inliers"] < keep and r["probe"] >= defer]
        cost = sum(r["probe_s"] for r in rows) + sum(r["fine_s"] for r in again)
        lines.append(
            f"| {keep} | {defer} | {len(kept)} | {len(left)} "
            f"({sum(not r['related'] for r in left)}) | {len(again)} "
            f"| {sum(r['verified'] for r in left)} / {sum(r['verified'] for r in rows)} "
            f"| {fewest} | {cost / total:.2f}x |"
        )
    return lines


def wxbs_scenes(root: Path) -> list[tuple[str, Path]]:
    """WxBS's appearance-change pairs (day/night, seasons, lighting, with viewpoint change)."""
    return [
        (f"wxbs_{pair.parent.name}_{pair.name}", pair)
        for category in ("WGABS", "WGALBS", "WLABS", "WGLBS")
        for pair in sorted((root / "wxbs_v1.1" / category).iterdir())
        if pair.is_dir()
    ]


def main(argv=None):
    parser = script_parser(__doc__)
    parser.add_argument(
        "--output", type=Path, required=True, help="proxy scenes, databases and pairs.json go here"
    )
    parser.add_argument("--sources", nargs="+", default=DEV_SOURCES)
    parser.add_argument(
        "--looks", nargs="+", default=["damaged"], choices=sorted(proxy.LOOKS), help="proxy looks"
    )
    parser.add_argument(
        "--max_size", type=int, default=1024, help="long side of the proxy photos, in pixels"
    )
    parser.add_argument(
        "--max_images", type=int, default=8, help="photos per source (distractors added)"
    )
    parser.add_argument("--wxbs", action="store_true", help="WxBS's appearance pairs too")
    parser.add_argument(
        "--matcher",
        default="guided_lightglue:min_pair_score=none,cheap_inliers=none,probe_keypoints=none",
        help="the fine matcher on every keypoint, a spec: preset[:key=value,...]",
    )
    parser.add_argument(
        "--probe", type=int, default=1024, help="keypoints per photo, the best first"
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
    scenes = []
    for key, look in itertools.product(args.sources, args.looks):
        scene_dir = proxy.build_scene(
            key, args.output, max_images=args.max_images, max_size=args.max_size, look=look
        )
        manifest = json.loads((scene_dir / "manifest.json").read_text())
        eras = {im["name"]: im["era"] for im in manifest["images"]}
        scenes.append((scene_dir.name, scene_dir / "images", eras, scene_dir / "database.db"))
    if args.wxbs:
        scenes += [
            (name, pair, {}, args.output.resolve() / "wxbs" / name / "database.db")
            for name, pair in wxbs_scenes(shared_data_dir())
        ]
    rows, workspace = [], Workspace(args.output, "proxy")
    for name, images_dir, eras, database in scenes:
        # an earlier run's, for photos drawn again
        relative = database.relative_to(args.output.resolve()).as_posix()
        if workspace.owns(relative):
            workspace.remove(relative)
        workspace.record(relative)
        database.parent.mkdir(parents=True, exist_ok=True)
        rows += scene_pairs(name, images_dir, eras, database, matcher, min_inliers, args.probe)
    workspace.record("pairs.json")[0].write_text(json.dumps(rows, indent=1) + "\n")
    print("\n".join(gate_table(rows, "score", (0.02, 0.05, 0.1, 0.15, 0.2, 0.3))) + "\n")
    print("\n".join(probe_table(rows, (60, 100, 150), (0, 10, 20, 30))) + "\n")
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
