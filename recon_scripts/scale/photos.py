"""The photo pool of the scale benchmark (training photos and rendered landmarks, 1,000 in all) and
its sets of the first N photos."""

from __future__ import annotations

import json
import random
import shutil
from itertools import zip_longest
from pathlib import Path

from colmap_guided.paths import shared_data_dir

SYNTHETIC = {"scenes": 24, "views": 24, "width": 1024, "height": 768, "seed": 1000}
POOL_SIZE = 1000


def _render(args):
    from colmap_guided.synthetic import render_scene

    out, views, seed = args
    if not (Path(out) / "ground_truth" / "images.txt").exists():
        conf = {"hall_size": hall_size(seed)}
        render_scene(out, views, SYNTHETIC["width"], SYNTHETIC["height"], seed=seed, conf=conf)
    return out


def hall_size(seed: int) -> tuple[float, float]:
    """The hall's length and width (metres) of the landmark of ``seed``: each landmark its own
    building (landmarks of one shape, only their paint apart, are twins geometry cannot tell)."""
    rng = random.Random(seed)
    return round(rng.uniform(8.0, 16.0), 1), round(rng.uniform(6.0, 10.0), 1)


def _train_scenes() -> list[dict]:
    from colmap_guided.features import list_images

    return [
        {
            "name": f"t_{p.name}",
            "kind": "train",
            "files": [str(p / "images" / n) for n in list_images(p / "images")],
        }
        for p in sorted((shared_data_dir() / "train").iterdir())
        if (p / "images").is_dir()
    ]


def _render_jobs(out: Path, left: int) -> list[tuple[str, int, int]]:
    """(folder, views, seed) of the rendered scenes that fill the pool up to ``left`` photos."""
    jobs = []
    for i in range(SYNTHETIC["scenes"]):
        views = min(SYNTHETIC["views"], left)
        if views < 2:
            break
        seed = SYNTHETIC["seed"] + i
        jobs.append((str(out / "synthetic" / f"s_{seed}"), views, seed))
        left -= views
    return jobs


def render_landmarks(out: Path, photos: int, workers: int = 2) -> list[dict]:
    """Rendered landmarks holding ``photos`` views in all (the last landmark cut, none below 2
    views), rendered once under OUT/synthetic: [{'name', 'kind', 'files': [abs paths]}]."""
    jobs = _render_jobs(out, photos)
    if jobs:
        from multiprocessing import Pool

        with Pool(min(workers, len(jobs))) as pool:
            for done in pool.imap(_render, jobs):
                print("rendered", done, flush=True)
            # workers that end by themselves: terminated, pycolmap's handler prints a stack
            pool.close()
            pool.join()
    return [
        {
            "name": Path(o).name,
            "kind": "synthetic",
            "files": [str(Path(o) / "images" / f"view_{v:03d}.jpg") for v in range(n)],
        }
        for o, n, _ in jobs
    ]


def make_pool(out: Path, workers: int = 2) -> list[dict]:
    """Scenes in pool order: [{'name', 'kind', 'files': [abs paths]}]; rendered scenes under
    OUT/synthetic."""
    if (out / "pool.json").exists():
        return json.loads((out / "pool.json").read_text())
    real = _train_scenes()
    synth = render_landmarks(out, POOL_SIZE - sum(len(s["files"]) for s in real), workers)
    random.Random(0).shuffle(real)
    random.Random(1).shuffle(synth)
    scenes = [s for pair in zip_longest(real, synth) for s in pair if s]
    (out / "pool.json").write_text(json.dumps(scenes, indent=1))
    return scenes


def photo_set(out: Path, n: int) -> Path:
    """OUT/n<N>/images: symlinks <scene>/<file> to the first ``n`` photos of the pool."""
    images = out / f"n{n}" / "images"
    if images.is_dir():
        return images
    tmp = images.with_name("images.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    left = n
    for scene in json.loads((out / "pool.json").read_text()):
        for f in scene["files"][:left]:
            (tmp / scene["name"]).mkdir(parents=True, exist_ok=True)
            (tmp / scene["name"] / Path(f).name).symlink_to(f)
        left -= min(left, len(scene["files"]))
        if not left:
            break
    if left:
        raise SystemExit(f"The pool holds fewer than {n} photos")
    tmp.rename(images)
    return images


def composition(pool: list[dict], n: int) -> str:
    """'<train> train + <rendered> rendered' of the set of the first ``n`` photos."""
    train = synth = 0
    for scene in pool:
        take = min(n - train - synth, len(scene["files"]))
        if scene["kind"] == "train":
            train += take
        else:
            synth += take
    return f"{train} train + {synth} rendered"
