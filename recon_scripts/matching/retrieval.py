"""Retrieval pair selection against exhaustive matching: recall of the co-visible pairs vs k.

    python -m recon_scripts retrieval [k="3 5 10 20"] [min_shared=15]
        [sets="train/strecha_castle train/pmvs_hall pooled"]

The training scenes of ../shared/data/train carry COLMAP pseudo ground truth made by pycolmap's
exhaustive pipeline: a pair "verified by exhaustive matching" is one whose images share at least
``min_shared`` 3D points of that model. Sets: ``train/SCENE`` (a scene alone), ``train`` (every
training scene with a model) and ``pooled`` (the scenes of the sets, or every training scene
without one, pooled into one archive: every other scene a distractor). Each picks top-k pairs by
the GeM descriptor of ``colmap_guided.pairs`` (descriptors kept in WORK/<scene>/descriptors.npy);
printed: recall of the co-visible pairs, pairs as a fraction of exhaustive, and cross-scene pairs.
Images registered end to end (retrieval vs exhaustive): the ``pairs`` preset, or `reconstruct
--pairs retrieval` on a set.
"""

from __future__ import annotations

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
from recon_scripts.bench import Benchmark
from recon_scripts.evaluation.tables import markdown_table

POOLED = "pooled"  # the set of the scenes pooled into one archive
POOLED_LABEL = "pooled (all scenes)"


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


def training_scenes() -> list[str]:
    """``train/SCENE`` of every training scene with a model."""
    root = shared_data_dir() / "train"
    scenes = sorted(p for p in root.iterdir() if (p / "colmap").is_dir()) if root.is_dir() else []
    return [f"train/{p.name}" for p in scenes]


def scene_descriptors(
    coarse: CoarseMatcher, scene: Path, cache: Path
) -> tuple[list[str], np.ndarray]:
    """The scene's image names (``scene/photo``) and GeM descriptors, cached in ``cache``."""
    files = [scene / "images" / n for n in list_images(scene / "images")]
    scene_names = [f"{scene.name}/{p.name}" for p in files]
    if cache.is_file():
        return scene_names, np.load(cache)
    d = global_descriptors(coarse, dict(zip(scene_names, files)))
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.save(cache, d)
    return scene_names, d


def load_scene(coarse: CoarseMatcher, scene: Path, min_shared: int, cache: Path) -> tuple:
    """(name, image names, descriptors, co-visible pairs) of a scene with a model."""
    pairs, _ = covisible_pairs(scene / "colmap", min_shared)
    scene_names, d = scene_descriptors(coarse, scene, cache)
    truth = {(f"{scene.name}/{a}", f"{scene.name}/{b}") for a, b in pairs}
    return scene.name, scene_names, d, truth


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


def scene_table(scenes: list[list[dict]], ks: list[int]) -> str:
    """One row per scene alone (its rows at each k), one cell per k."""
    return markdown_table(
        ["scene", "images", "co-visible"] + [f"k={k}" for k in ks],
        [
            [rows[0]["set"], rows[0]["images"], rows[0]["covisible"]]
            + [
                f"{r['recall']:.2f} ({r['fraction']:.2f}) "
                f"[{r['connected']}/{r['connected_exhaustive']}]"
                for r in rows
            ]
            for rows in scenes
        ],
    )


class RetrievalBenchmark(Benchmark):
    name = "retrieval"
    default_conf = {
        "sets": ["train", POOLED],  # train: every training scene with a model
        "k": [3, 5, 10, 20],
        "min_shared": 15,  # 3D points two images must share to count as a verified pair
    }

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        sets = self.conf["sets"]
        self.conf["sets"] = [s for x in sets for s in (training_scenes() if x == "train" else [x])]
        self.coarse = None

    def pooled(self) -> list[str]:
        """The scenes of the pooled archive: those of the sets, or every training scene."""
        return [s for s in self.conf["sets"] if s != POOLED] or training_scenes()

    def configs(self):
        c = self.conf
        return {
            f"k={k}": {"k": k, "min_shared": c["min_shared"], "pooled": self.pooled()}
            for k in c["k"]
        }

    def scene(self, name: str, work: Path) -> tuple:
        """``load_scene`` of ``train/SCENE``, its descriptors kept in its folder of WORK."""
        self.coarse = self.coarse or CoarseMatcher({"mode": "raw"})
        cache = work / self.folder(name) / "descriptors.npy"
        return load_scene(self.coarse, shared_data_dir() / name, self.conf["min_shared"], cache)

    def prepare(self, name, image_path, work):
        if name != POOLED:
            scenes = [self.scene(name, work.parent)]
            label = scenes[0][0]
        else:
            scenes = [self.scene(s, work.parent) for s in self.pooled()]
            label = POOLED_LABEL
        return {
            "scenes": scenes,
            "label": label,
            "names": [n for _, sn, _, _ in scenes for n in sn],
            "descriptors": np.concatenate([d for _, _, d, _ in scenes]),
            "truth": set().union(*(t for _, _, _, t in scenes)),
        }

    def run_config(self, name, image_path, prepared, label, config, out):
        p = prepared
        return retrieval_row(
            p["scenes"], p["label"], p["names"], p["descriptors"], p["truth"], config["k"]
        )

    def progress(self, results, name, label):
        r = results[name][label]
        return f"{r['set']} k={r['k']}: recall {r['recall']:.3f}, {r['pairs']} pairs"

    def summarize(self, results):
        rows = [r for runs in results.values() for r in runs.values()]
        scenes = [list(runs.values()) for name, runs in results.items() if name != POOLED]
        return (
            pooled_table(rows)
            + "\n\nPer scene (alone): recall (pairs / exhaustive) [largest connected "
            "of the co-visible pairs selected, exhaustive's] at each k:\n"
            + scene_table(scenes, self.conf["k"])
        )
