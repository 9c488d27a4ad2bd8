"""Models joined after escalation: a landmark's two models joined, two look-alike buildings not.

    python -m recon_scripts join [sets="lund split halls"] [methods="off on uncut"] [pairs=within]

A landmark whose modern photos and prints map as two models, and two buildings of one style, each
reconstructed with the join off (``join_pairs`` 0), on (the default, 10 cross pairs) and on with
models not cut (``cut_models`` off), each in its own workspace from the same photos and pairs.

Sets: ``lund`` (lund_door_gtsfm at 512 px, 6 of its 12 photos printed grey and grainy;
reference: its COLMAP ground truth), ``split`` (the synthetic landmark, 8 views at 384 x 288, 4
of them printed; reference: the rendering's cameras), ``halls`` (two synthetic halls of one style:
one window on every facade, 12 x 8 and 9 x 7 m, 5 views each at 384 x 288, and 2 unrelated photos
of gtsfm_1dsfm_sample; no model may hold both halls). ``pairs=within``: each group's pairs only
(modern photos and prints, or each hall), as where retrieval ranks the groups apart; ``all``: every
pair, as where retrieval pairs two look-alike buildings (mapping may make one model of both, which
is cut in two); ``retrieval``: each photo's 3 most similar.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from itertools import combinations
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from colmap_guided import archival, images
from colmap_guided.mapping import load_models, registered
from colmap_guided.paths import shared_data_dir
from colmap_guided.pipeline import PipelineConf
from colmap_guided.reconstruct import reconstruct
from colmap_guided.synthetic import SceneInfo, render_scene
from recon_scripts.bench import Benchmark
from recon_scripts.evaluation.ground_truth import pose_errors

LUND_PRINTED = (0, 2, 3, 7, 8, 9)  # lund_door_gtsfm's photos printed (sorted by name)
# a method's escalation options: the join off or on, or on with models not cut
METHODS = {
    "off": {"join_pairs": 0},
    "on": {"join_pairs": 10},
    "uncut": {"join_pairs": 10, "cut_models": False},
}


@dataclasses.dataclass
class Scene:
    images: Path
    groups: list[list[str]]  # modern photos and prints, or each building (and unrelated photos)
    reference: SceneInfo | Path | None  # cameras to score the largest model against
    conf: dict  # PipelineConf options of the scene


def age(path: Path, seed: int) -> None:
    """The photo at ``path`` printed: grey, faded, grainy (``archival``'s realistic_bw)."""
    aged = archival.apply_preset(images.read_image(path), "realistic_bw", seed=seed)
    cv2.imwrite(str(path), np.ascontiguousarray(aged[:, :, ::-1]))


def resized(src: Path, dst: Path, size: int) -> None:
    photo = np.ascontiguousarray(images.read_image(src)[:, :, ::-1])
    scale = size / max(photo.shape[:2])
    cv2.imwrite(str(dst), cv2.resize(photo, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA))


def within_pairs(path: Path, groups: list[list[str]]) -> Path:
    """A pairs file of every pair inside each group and none across: what the first pass matches
    where retrieval ranks the groups apart."""
    path.write_text("".join(f"{a} {b}\n" for group in groups for a, b in combinations(group, 2)))
    return path


def split_scene(out: Path) -> Scene:
    """The synthetic landmark, 8 views; the last 4 printed. One camera: the views' EXIF."""
    scene = render_scene(out, num_images=8, width=384, height=288, seed=5)
    for i, name in enumerate(scene.names[4:]):
        age(scene.image_dir / name, i)
    groups = [scene.names[:4], scene.names[4:]]
    return Scene(scene.image_dir, groups, scene, {"features": {"camera_mode": "single"}})


def halls_scene(out: Path, data: Path) -> Scene:
    """Two halls of one style (one window, other sizes, towers and annexes), 5 views each, and 2
    unrelated photos, in one folder."""
    images = out / "images"
    images.mkdir(parents=True)
    groups = []
    for tag, seed, size in (("a", 3, (12.0, 8.0)), ("b", 4, (9.0, 7.0))):
        hall = render_scene(
            out / tag, 5, 384, 288, seed, repeated=True, style=7, conf={"hall_size": size}
        )
        groups.append([f"{tag}_{name}" for name in hall.names])
        for name in hall.names:
            shutil.copy(hall.image_dir / name, images / f"{tag}_{name}")
    groups.append([])
    for path in sorted((data / "gtsfm_1dsfm_sample" / "images").iterdir())[:2]:
        groups[-1].append(f"unrelated_{path.name}")
        resized(path, images / groups[-1][-1], 384)
    return Scene(images, groups, None, {})


def lund_scene(out: Path, data: Path) -> Scene:
    """lund_door_gtsfm at 512 px, ``LUND_PRINTED`` printed."""
    images = out / "images"
    images.mkdir(parents=True)
    groups = [[], []]
    for i, path in enumerate(sorted((data / "lund_door_gtsfm" / "images").iterdir())):
        resized(path, images / path.name, 512)
        if i in LUND_PRINTED:
            age(images / path.name, i)
        groups[i in LUND_PRINTED].append(path.name)
    return Scene(images, groups, data / "lund_door_gtsfm" / "colmap_ground_truth", {})


def run(scene: Scene, workspace: Path, pairs: str | Path, join_pairs: int, **escalation) -> dict:
    escalation = {"join_pairs": join_pairs, **escalation}
    conf = {**scene.conf, "mapping": {"num_threads": 1}, "escalation": escalation}
    if pairs == "retrieval":
        conf["pairs"] = {"pairs": "retrieval", "num_neighbors": 3}
    else:
        conf["pairs"] = {"pairs": str(pairs)}
    start = time.time()
    result = reconstruct(scene.images.parent, output=workspace, conf=PipelineConf.from_dict(conf))
    result["wall"] = time.time() - start
    return result


def models_cell(workspace: Path, groups: list[list[str]]) -> str:
    """Each model's photos by group, largest first: 4+0 | 0+4."""
    models = load_models(workspace / "sparse").values()
    names = [registered(rec) for rec in models]
    return " \\| ".join("+".join(str(len(n & set(g))) for g in groups if g) for n in names) or "–"


class JoinBenchmark(Benchmark):
    name = "join"
    default_conf = {
        "sets": ["lund", "split", "halls"],
        "methods": ["off", "on", "uncut"],  # METHODS: join off, on, on with models not cut
        # within: each group's pairs only; all: every pair; retrieval: 3 most similar each
        "pairs": "within",
    }

    def configs(self):
        pairs = self.conf["pairs"]
        return {m: {**METHODS[m], "pairs": pairs} for m in self.conf["methods"]}

    def images(self, name, work):
        return work / "scene" / "images"

    def prepare(self, name, image_path, work):
        """The scene built under WORK/<set>/scene/, and its pairs."""
        shutil.rmtree(image_path.parent, ignore_errors=True)
        builders = {"split": split_scene, "halls": halls_scene, "lund": lund_scene}
        scene = builders[name](image_path.parent, *([] if name == "split" else [shared_data_dir()]))
        pairs = self.conf["pairs"]
        if pairs in ("within", "all"):  # all: one group of every photo
            groups = scene.groups if pairs == "within" else [sum(scene.groups, [])]
            pairs = within_pairs(work / "pairs.txt", groups)
        return {"scene": scene, "pairs": pairs}

    def run_config(self, name, image_path, prepared, label, config, out):
        scene = prepared["scene"]
        options = {k: v for k, v in config.items() if k != "pairs"}
        result = run(scene, out, prepared["pairs"], **options)
        errors = (
            pose_errors(pycolmap.Reconstruction(str(out / "sparse" / "0")), scene.reference)
            if scene.reference is not None and result["num_registered"]
            else {}
        )
        placed = [e for e in errors.values() if np.isfinite(e[0])]
        pose = (
            f"{max(e[0] for e in placed):.2f}, {100 * max(e[1] for e in placed):.2f}"
            if placed
            else "–"
        )
        return {
            "photos": "+".join(str(len(g)) for g in scene.groups if g),
            "models": models_cell(out, scene.groups),
            "tries": result["database"]["joins"],
            "cuts": result["database"]["splits"],
            "pose": pose,
            "timings": result["timings"],
        }

    def progress(self, results, name, label):
        return f"{name}, join {label}: models {results[name][label]['models']}"

    def summarize(self, results):
        lines = [
            "| scene | photos (groups) | pairs | models, join off | models, join on | models, not "
            "cut | models cut: "
            "conflicts / agreements | cross pairs matched / verified | conflicts / agreements "
            "| joined: why | join s | largest model vs reference: max rotation °, centre % of "
            "extent |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for name, by_method in results.items():
            off, on, uncut = (by_method.get(m, {}) for m in ("off", "on", "uncut"))
            tries = on.get("tries", [])
            cross = "; ".join(f"{t['matched']} / {t['verified']}" for t in tries) or "–"
            conflicts = "; ".join(
                " · ".join("/".join(map(str, c)) for c in t["conflicts"] if c)
                if t.get("conflicts")
                else "–"
                for t in tries
            )
            why = "; ".join(t["why"] for t in tries) or "no two models"
            seconds = "; ".join(f"{t['time']:.1f}" for t in tries) or "–"
            photos = next(iter(by_method.values()))["photos"]
            cuts = "; ".join(f"{c['conflicts']} / {c['agreements']}" for c in on.get("cuts", []))
            lines.append(
                f"| {name} | {photos} | {self.conf['pairs']} | {off.get('models', '–')} | "
                f"{on.get('models', '–')} | {uncut.get('models', '–')} | {cuts or 'none'} "
                f"| {cross} | {conflicts} | {why} "
                f"| {seconds} | "
                f"{on.get('pose', '–')} |"
            )
        return "\n".join(lines)
