"""LightGlue on CPU in float32 and with bfloat16 transformer layers: matches kept, seconds a pair
and resident memory as pairs of new shapes go by, each precision in a fresh process.

    python -m recon_scripts.matching.lightglue_precision [--set sacre_coeur_hloc] [--pairs 150]

ALIKED (the default's 2,048 keypoints at 1,600 px) on the set's first photos; the pairs are every
two of them in order, each of its own shape (keypoints per photo differ).
"""

from __future__ import annotations

import argparse
import itertools
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor

from colmap_guided.paths import shared_data_dir


def rss_mb() -> int:
    with open(f"/proc/{os.getpid()}/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") >> 20


def sides(folder: str, photos: int) -> list:
    """ImageData of the first ``photos`` photos of ``folder``, ALIKED at the default's settings."""
    from colmap_guided.features import aliked as lf
    from colmap_guided.features import list_images
    from colmap_guided.images import image_size
    from colmap_guided.matchers.base import ImageData

    model, device = lf.load_model({**lf.default_conf, "device": "cpu"})
    paths = [os.path.join(folder, n) for n in list_images(folder)[:photos]]
    return [
        ImageData(
            os.path.basename(p),
            i,
            p,
            *lf.extract_image(model, device, p, lf.default_conf),
            *image_size(p),
        )
        for i, p in enumerate(paths, 1)
    ]


def run(bf16: bool, images: list, pairs: int) -> dict:
    """One precision in this process: the pairs' matches, s a pair, RSS after the first pair and
    the last."""
    from colmap_guided.matchers.lightglue import LightGlueMatcher

    matcher = LightGlueMatcher({"device": "cpu", "bf16": bf16})
    todo = list(itertools.islice(itertools.combinations(range(len(images)), 2), pairs))
    matches, first = [], None
    start = time.perf_counter()
    for a, b in todo:
        matches.append({tuple(m) for m in matcher.match(images[a], images[b]).tolist()})
        first = first or rss_mb()
    seconds = (time.perf_counter() - start) / len(todo)
    return {"matches": matches, "seconds": seconds, "rss_first": first, "rss_last": rss_mb()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--set", default="sacre_coeur_hloc", help="a photo set of ../shared/data")
    parser.add_argument("--pairs", type=int, default=150)
    args = parser.parse_args()
    photos = next(n for n in itertools.count(2) if n * (n - 1) // 2 >= args.pairs)
    images = sides(str(shared_data_dir() / args.set / "images"), photos)
    photos, pairs = len(images), min(args.pairs, len(images) * (len(images) - 1) // 2)
    ctx = multiprocessing.get_context("spawn")
    results = {}
    for name, bf16 in (("float32", False), ("bfloat16 layers", True)):
        # the worker exits on its own: a terminated one prints pycolmap's stack trace
        with ProcessPoolExecutor(1, mp_context=ctx) as pool:
            results[name] = pool.submit(run, bf16, images, pairs).result()
    ref = results["float32"]["matches"]
    print(f"{args.set}: {len(ref)} pairs of {photos} photos, ALIKED default settings")
    print("| precision | matches (kept of float32's) | s a pair | RSS MB after pair 1 → last |")
    print("|---|---|---|---|")
    for name, r in results.items():
        kept = sum(len(m & f) for m, f in zip(r["matches"], ref)) / max(sum(map(len, ref)), 1)
        found = sum(map(len, r["matches"]))
        print(
            f"| {name} | {found} ({kept:.1%}) | {r['seconds']:.2f} "
            f"| {r['rss_first']} → {r['rss_last']} |"
        )


if __name__ == "__main__":
    main()
