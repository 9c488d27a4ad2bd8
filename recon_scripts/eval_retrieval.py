"""Retrieval pair selection against exhaustive matching: recall of the co-visible pairs vs k.

    python -m recon_scripts.eval_retrieval [--k 3 5 10 20] [--out outputs/eval_retrieval]

The training scenes of ../shared/data/train carry COLMAP pseudo ground truth made by pycolmap's
exhaustive pipeline: a pair "verified by exhaustive matching" is one whose images share at least
``--min_shared`` 3D points of that model. Each scene alone, and all scenes pooled into one archive
(every other scene a distractor), pick top-k pairs by the GeM descriptor of ``colmap_guided.pairs``;
printed: recall of the co-visible pairs, pairs as a fraction of exhaustive, and cross-scene pairs.
Images registered end to end (retrieval vs exhaustive): run `reconstruct --pairs retrieval` on a
set.
"""

from __future__ import annotations

import json
import time
from itertools import combinations
from pathlib import Path

import colmap_guided  # noqa: F401  (zlib before pycolmap)

# isort: split
import numpy as np
import pycolmap

from colmap_guided.coarse import CoarseMatcher
from colmap_guided.features import list_images
from colmap_guided.pairs import global_descriptors, retrieval_pairs
from colmap_guided.paths import shared_data_dir
from recon_scripts import script_parser


def covisible_pairs(model_path: Path, min_shared: int) -> tuple[set[tuple[str, str]], list[str]]:
    rec = pycolmap.Reconstruction(str(model_path))
    seen: dict[tuple[int, int], int] = {}
    for point in rec.points3D.values():
        ids = sorted({el.image_id for el in point.track.elements})
        for a, b in combinations(ids, 2):
            seen[(a, b)] = seen.get((a, b), 0) + 1
    name = {i: rec.images[i].name for i in rec.images}
    pairs = {tuple(sorted((name[a], name[b]))) for (a, b), n in seen.items() if n >= min_shared}
    return pairs, sorted(name.values())


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--k", type=int, nargs="+", default=[3, 5, 10, 20])
    parser.add_argument(
        "--min_shared",
        type=int,
        default=15,
        help="3D points two images must share to count as a verified pair",
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/eval_retrieval"))
    args = parser.parse_args()
    root = shared_data_dir() / "train"
    args.out.mkdir(parents=True, exist_ok=True)
    coarse = CoarseMatcher({"mode": "raw"})
    scenes, names, desc, truth = [], [], [], set()
    start = time.time()
    for scene in sorted(p for p in root.iterdir() if (p / "colmap").is_dir()):
        pairs, _ = covisible_pairs(scene / "colmap", args.min_shared)
        files = [scene / "images" / n for n in list_images(scene / "images")]
        scene_names = [f"{scene.name}/{p.name}" for p in files]
        cache = args.out / f"{scene.name}.npy"
        if cache.is_file():
            d = np.load(cache)
        else:
            d = global_descriptors(coarse, dict(zip(scene_names, files)))
            np.save(cache, d)
        scenes.append(
            (
                scene.name,
                scene_names,
                d,
                {(f"{scene.name}/{a}", f"{scene.name}/{b}") for a, b in pairs},
            )
        )
        names += scene_names
        desc.append(d)
        truth |= scenes[-1][3]
    desc = np.concatenate(desc)
    print(f"{len(names)} images, {len(scenes)} scenes, descriptors {time.time() - start:.0f} s\n")

    def largest_component(pairs) -> int:
        parent: dict[str, str] = {}

        def find(x):
            while parent.setdefault(x, x) != x:
                parent[x] = x = parent[parent[x]]
            return x

        for a, b in pairs:
            parent[find(a)] = find(b)
        roots = [find(x) for x in list(parent)]
        return max((roots.count(r) for r in set(roots)), default=0)

    def row(label, scene_names, d, true_pairs, k):
        sel = set(retrieval_pairs(scene_names, d, k))
        n = len(scene_names)
        # largest connected per scene, summed
        truths = [t for _, sn, _, t in scenes if set(sn) <= set(scene_names)]
        cross = sum(a.split("/")[0] != b.split("/")[0] for a, b in sel)
        recall = len(sel & true_pairs) / max(len(true_pairs), 1)
        return {
            "set": label,
            "k": k,
            "images": n,
            "covisible": len(true_pairs),
            "recall": recall,
            "pairs": len(sel),
            "fraction": len(sel) / (n * (n - 1) / 2),
            "cross_scene": cross,
            "connected": sum(largest_component(sel & t) for t in truths),
            "connected_exhaustive": sum(largest_component(t) for t in truths),
        }

    rows = []
    for k in args.k:
        rows.append(row("pooled (all scenes)", names, desc, truth, k))
        per = [row(s, sn, d, t, k) for s, sn, d, t in scenes]
        rows += per
    print(
        "| set | k | images | co-visible pairs | recall | pairs / exhaustive | "
        "cross-scene pairs | images connected (exhaustive) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        if r["set"].startswith("pooled"):
            print(
                f"| {r['set']} | {r['k']} | {r['images']} | {r['covisible']} | "
                f"{r['recall']:.3f} | {r['fraction']:.3f} | {r['cross_scene']} | "
                f"{r['connected']} ({r['connected_exhaustive']}) |"
            )
    print(
        "\nPer scene (alone): recall (pairs / exhaustive) [largest connected "
        "of the co-visible pairs selected, exhaustive's] at each k:"
    )
    print("| scene | images | co-visible | " + " | ".join(f"k={k}" for k in args.k) + " |")
    print("|---|---|---|" + "---|" * len(args.k))
    for s, sn, _, t in scenes:
        rs = [r for r in rows if r["set"] == s]
        print(
            f"| {s} | {len(sn)} | {len(t)} | "
            + " | ".join(
                f"{r['recall']:.2f} ({r['fraction']:.2f}) "
                f"[{r['connected']}/{r['connected_exhaustive']}]"
                for r in rs
            )
            + " |"
        )
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
