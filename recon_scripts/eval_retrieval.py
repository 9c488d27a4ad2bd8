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
from recon_scripts.evaluation.tables import markdown_table


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


def _parser():
    """The command line."""
    parser = script_parser(__doc__)
    parser.add_argument("--k", type=int, nargs="+", default=[3, 5, 10, 20])
    parser.add_argument(
        "--min_shared",
        type=int,
        default=15,
        help="3D points two images must share to count as a verified pair",
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/eval_retrieval"))
    return parser


def scene_descriptors(
    coarse: CoarseMatcher, scene: Path, out: Path
) -> tuple[list[str], np.ndarray]:
    """The scene's image names (``scene/photo``) and GeM descriptors, cached in OUT/<scene>.npy."""
    files = [scene / "images" / n for n in list_images(scene / "images")]
    scene_names = [f"{scene.name}/{p.name}" for p in files]
    cache = out / f"{scene.name}.npy"
    if cache.is_file():
        return scene_names, np.load(cache)
    d = global_descriptors(coarse, dict(zip(scene_names, files)))
    np.save(cache, d)
    return scene_names, d


def load_scenes(coarse: CoarseMatcher, root: Path, min_shared: int, out: Path) -> list[tuple]:
    """(name, image names, descriptors, co-visible pairs) of each scene of ``root`` with a model."""
    scenes = []
    for scene in sorted(p for p in root.iterdir() if (p / "colmap").is_dir()):
        pairs, _ = covisible_pairs(scene / "colmap", min_shared)
        scene_names, d = scene_descriptors(coarse, scene, out)
        truth = {(f"{scene.name}/{a}", f"{scene.name}/{b}") for a, b in pairs}
        scenes.append((scene.name, scene_names, d, truth))
    return scenes


def largest_component(pairs) -> int:
    """Images in the largest connected component of the graph of ``pairs``."""
    parent: dict[str, str] = {}

    def find(x):
        while parent.setdefault(x, x) != x:
            parent[x] = x = parent[parent[x]]
        return x

    for a, b in pairs:
        parent[find(a)] = find(b)
    roots = [find(x) for x in list(parent)]
    return max((roots.count(r) for r in set(roots)), default=0)


def retrieval_row(scenes, label, scene_names, d, true_pairs, k) -> dict:
    """Recall, pairs and connectivity of the top-``k`` retrieval pairs of one set of images."""
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


def pooled_table(rows: list[dict]) -> str:
    """The pooled archive's row at each k."""
    headers = ["set", "k", "images", "co-visible pairs", "recall", "pairs / exhaustive"]
    headers += ["cross-scene pairs", "images connected (exhaustive)"]
    return markdown_table(
        headers,
        [
            [
                r["set"],
                r["k"],
                r["images"],
                r["covisible"],
                f"{r['recall']:.3f}",
                f"{r['fraction']:.3f}",
                r["cross_scene"],
                f"{r['connected']} ({r['connected_exhaustive']})",
            ]
            for r in rows
            if r["set"].startswith("pooled")
        ],
    )


def scene_table(rows: list[dict], scenes: list[tuple], ks: list[int]) -> str:
    """One row per scene alone, one cell per k."""
    return markdown_table(
        ["scene", "images", "co-visible"] + [f"k={k}" for k in ks],
        [
            [s, len(sn), len(t)]
            + [
                f"{r['recall']:.2f} ({r['fraction']:.2f}) "
                f"[{r['connected']}/{r['connected_exhaustive']}]"
                for r in rows
                if r["set"] == s
            ]
            for s, sn, _, t in scenes
        ],
    )


def main() -> None:
    args = _parser().parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    coarse = CoarseMatcher({"mode": "raw"})
    start = time.time()
    scenes = load_scenes(coarse, shared_data_dir() / "train", args.min_shared, args.out)
    names = [n for _, sn, _, _ in scenes for n in sn]
    desc = np.concatenate([d for _, _, d, _ in scenes])
    truth = set().union(*(t for _, _, _, t in scenes))
    print(f"{len(names)} images, {len(scenes)} scenes, descriptors {time.time() - start:.0f} s\n")
    rows = []
    for k in args.k:
        rows.append(retrieval_row(scenes, "pooled (all scenes)", names, desc, truth, k))
        rows += [retrieval_row(scenes, s, sn, d, t, k) for s, sn, d, t in scenes]
    print(pooled_table(rows))
    print(
        "\nPer scene (alone): recall (pairs / exhaustive) [largest connected "
        "of the co-visible pairs selected, exhaustive's] at each k:"
    )
    print(scene_table(rows, scenes, args.k))
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
