"""PCK of the coarse matcher (raw, untrained, trained filters) on held-out pairs (paper Table 1).

    python -m recon_scripts coarse_pck [methods="raw untrained PATH.safetensors ..."]
        [labels="shipped ..."] [archival=damaged_scan] [pairs_per_scene=25] [resize_max=512]
        [impl=sparse] [output=outputs/coarse_pck/coarse_pck.json]

For every ground-truth match (p^A, p^B) — the two observations of a 3D point shared by a positive
pair (≥ 30 common points) of a held-out scene — the error is ‖m^{A→B}(p^A) − p^B‖ (and the reverse
direction), measured two ways: in pixels of the ORIGINAL images (stricter for images larger than the
network input) and, as the paper's Table 1, in pixels of the RESIZED image (the network input,
``resize_max`` long side; 16 px = one feature cell): the error vector scaled by the target image's
resize factor per axis. PCK@t is the share of errors below t = 8, 16, 32 px.

Methods: ``raw`` (raw correlation: no filter, mutual-NN-free argmax), ``untrained`` (the filter at
its random init, seed 0) and the path of each trained filter's .safetensors (named in the table by
``labels``, else by its run folder or its stem). ``archival``: a preset of colmap_guided.archival;
every method is also measured with image B degraded by it (an old photo matched to a modern one).
The sets are the held-out scenes; the pairs of each are drawn in turn from one generator (``seed``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from colmap_guided import archival
from colmap_guided.coarse.matcher import CoarseMatcher
from colmap_guided.coarse.model import CoarseNet
from colmap_guided.coarse.weights import save_filter_weights
from colmap_guided.images import read_image
from colmap_guided.train.scenes import VAL_SCENES, load_scene
from recon_scripts.bench import Benchmark

THRESHOLDS = (8, 16, 32)
BASELINES = {"raw": "raw correlation", "untrained": "untrained filter"}


def select_pairs(scenes: list[str], per_scene: int, max_points: int, seed: int = 0):
    """Up to ``per_scene`` random positive pairs per scene, with at most ``max_points`` GT matches
    each."""
    rng = np.random.default_rng(seed)
    out = []
    for name in scenes:
        scene = load_scene(name)
        idx = (
            rng.choice(len(scene.pairs), min(per_scene, len(scene.pairs)), replace=False)
            if scene.pairs
            else []
        )
        for i in sorted(idx):
            p = scene.pairs[i]
            keep = rng.choice(p.n_shared, min(max_points, p.n_shared), replace=False)
            out.append(
                (name, scene.images[p.a].path, scene.images[p.b].path, p.xy_a[keep], p.xy_b[keep])
            )
    return out


def untrained_weights(path: Path, backbone: str, resize_max: int, seed: int = 0) -> Path:
    torch.manual_seed(seed)
    net = CoarseNet({"backbone": backbone, "pretrained": False})
    save_filter_weights(net, path, resize_max, training={"note": f"untrained, torch seed {seed}"})
    return path


def evaluate(matcher: CoarseMatcher, pairs, archival_preset: str | None, desc: str) -> dict:
    """PCK of each scene of ``pairs`` at original resolution (keys ``pck8`` ...) and in resized
    pixels (``resized_pck8`` ...), and the matching seconds."""
    errors: dict[str, dict[str, list[np.ndarray]]] = {"": {}, "resized_": {}}
    t_match = 0.0
    for scene, path_a, path_b, xy_a, xy_b in tqdm(pairs, desc=desc, mininterval=10):
        fa = matcher.extract_path(path_a, str(path_a))
        key_b = str(path_b) + (f"#{archival_preset}" if archival_preset else "")
        if key_b not in matcher.cache:
            img_b = read_image(path_b)
            if archival_preset:
                img_b = archival.apply_preset(img_b, archival_preset, seed=archival_seed(path_b))
            matcher.extract(img_b, key_b)
        fb = matcher.cache[key_b]
        t = time.perf_counter()
        res = matcher.match(fa, fb)
        t_match += time.perf_counter() - t
        d_ab, d_ba = res.flow_ab(xy_a)[0] - xy_b, res.flow_ba(xy_b)[0] - xy_a
        errors[""].setdefault(scene, []).append(
            np.linalg.norm(np.concatenate([d_ab, d_ba]), axis=1)
        )
        # paper: resized pixels
        resized = np.concatenate([d_ab * fb.geometry.scale, d_ba * fa.geometry.scale])
        errors["resized_"].setdefault(scene, []).append(np.linalg.norm(resized, axis=1))
    result = {"per_scene": {}, "match_s": t_match, "pairs": len(pairs)}
    for prefix, by_scene in errors.items():
        for scene, errs in by_scene.items():
            e = np.concatenate(errs)
            result["per_scene"].setdefault(scene, {"n": int(len(e)), "pairs": len(errs)})
            result["per_scene"][scene].update(
                {f"{prefix}pck{t}": float((e < t).mean()) for t in THRESHOLDS}
            )
    return result


def totals(parts: list[dict]) -> dict:
    """``evaluate``'s results on disjoint pairs as one: PCK of all points (keys ``pck8`` ...,
    ``resized_pck8`` ...), its mean over scenes (``scene_mean_pck8`` ...) and ms per pair."""
    per_scene = {scene: v for part in parts for scene, v in part["per_scene"].items()}
    num_pairs = sum(part["pairs"] for part in parts)
    n = sum(v["n"] for v in per_scene.values())
    result = {
        "per_scene": per_scene,
        "ms_per_pair": 1000 * sum(part["match_s"] for part in parts) / max(num_pairs, 1),
        "n_points": n,
    }
    for prefix in ("", "resized_"):
        for t in THRESHOLDS:
            shares = [v[f"{prefix}pck{t}"] for v in per_scene.values()]
            # each scene's errors under t: its share times its errors, the integer it was
            under = sum(round(s * v["n"]) for s, v in zip(shares, per_scene.values()))
            result[f"{prefix}pck{t}"] = under / n if n else float("nan")
            # mean over scenes (each held-out scene weighs the same, whatever its number of points)
            result[f"{prefix}scene_mean_pck{t}"] = float(np.mean(shares))
    return result


def archival_seed(path: Path) -> int:
    import zlib

    return zlib.crc32(str(Path(path).name).encode())


def markdown(results: dict, conf: dict) -> str:
    lines = [
        f"Coarse PCK on held-out pairs ({', '.join(conf['scenes'])}; {conf['n_pairs']} pairs, "
        f"GT = shared SfM tracks, both directions); network input {conf['resize_max']} px, "
        f"{conf['impl']} filter path. 'resized': errors in pixels of the resized image (paper "
        "Table 1; 16 px = one cell); 'original': in original-resolution pixels.",
        "",
        "| method | images | resized PCK@8 | @16 | @32 | original PCK@8 | "
        "@16 | @32 | scene-mean original @16 | ms/pair |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        method, _, cond = name.partition("|")
        lines.append(
            f"| {method} | {cond or 'clean'} | "
            + " | ".join(
                f"{100 * r[f'{p}pck{t}']:.1f}" for p in ("resized_", "") for t in THRESHOLDS
            )
            + f" | {100 * r['scene_mean_pck16']:.1f} | {r['ms_per_pair']:.0f} |"
        )
    lines += [
        "",
        "Per scene PCK@8/16/32 (original pixels):",
        "",
        "| method | images | " + " | ".join(conf["scenes"]) + " |",
        "|---|---|" + "---|" * len(conf["scenes"]),
    ]
    for name, r in results.items():
        method, _, cond = name.partition("|")
        cells = []
        for s in conf["scenes"]:
            v = r["per_scene"].get(s)
            cells.append(
                "–"
                if v is None
                else f"{100 * v['pck8']:.0f}/{100 * v['pck16']:.0f}/{100 * v['pck32']:.0f}"
            )
        lines.append(f"| {method} | {cond or 'clean'} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


class CoarsePckBenchmark(Benchmark):
    name = "coarse_pck"
    default_conf = {
        "sets": list(VAL_SCENES),  # held-out scenes (the trainer's validation scenes)
        # raw, untrained, and trained filters' .safetensors
        "methods": ["raw", "untrained", "colmap_guided/weights/coarse_filter.safetensors"],
        "labels": [],  # names of the trained filters in the table, in the order of methods
        "archival": None,  # also every method with B degraded by this colmap_guided.archival preset
        "pairs_per_scene": 25,
        "max_points": 500,  # GT matches per pair
        "resize_max": 512,
        "impl": "auto",  # auto, dense or sparse
        "sparse_k": CoarseMatcher.default_conf["sparse_k"],  # sparse filter: best cells per cell
        "backbone": "efficientnet-lite0",
        "threads": 1,  # torch CPU threads (1: as the pipeline matches on CPU)
        "seed": 0,  # of the pair and point sampling
    }

    def configs(self):
        c = self.conf
        trained = [m for m in c["methods"] if m not in BASELINES]
        labels = c["labels"] or [
            Path(w).parent.name if Path(w).name == "coarse_filter.safetensors" else Path(w).stem
            for w in trained
        ]
        if len(labels) != len(trained):
            raise ValueError(f"labels {labels} do not name the trained filters {trained}")
        names = BASELINES | dict(zip(trained, labels))
        shared = {
            k: c[k]
            for k in ("archival", "pairs_per_scene", "max_points", "resize_max", "impl")
            + ("sparse_k", "backbone", "seed")
        }
        # the pairs of a scene depend on the scenes drawn before it
        return {names[m]: {"method": m, "scenes": c["sets"], **shared} for m in c["methods"]}

    def run(self) -> dict:
        c = self.conf
        if c["threads"]:
            torch.set_num_threads(c["threads"])
        self.pairs = select_pairs(c["sets"], c["pairs_per_scene"], c["max_points"], c["seed"])
        self.features = {}  # features computed once per backbone
        return super().run()

    def prepare(self, name, image_path, work):
        return {"pairs": [p for p in self.pairs if p[0] == name]}

    def run_config(self, name, image_path, prepared, label, config, out):
        method = config["method"]
        if method == "untrained":
            method = untrained_weights(
                out / "untrained.safetensors", config["backbone"], config["resize_max"]
            )
        matcher = CoarseMatcher(
            {k: config[k] for k in ("backbone", "resize_max", "impl", "sparse_k")}
            | ({"mode": "raw"} if method == "raw" else {"weights": str(method)})
        )
        matcher.cache = self.features.setdefault(matcher.features_key, {})
        conditions = [None] + ([config["archival"]] if config["archival"] else [])
        result = {
            "pck": {
                cond or "clean": evaluate(matcher, prepared["pairs"], cond, f"{name} {label}")
                for cond in conditions
            },
            "impl": matcher.impl,
        }
        if config["method"] not in BASELINES:
            result["weights"] = config["method"]
            result["training"] = matcher.weights_config.get("training", {})
        return result

    def progress(self, results, name, label):
        scores = {cond: totals([r]) for cond, r in results[name][label]["pck"].items()}
        return f"{name} {label}: PCK@8/16/32 " + ", ".join(
            f"{cond} " + " / ".join(f"{100 * r[f'pck{t}']:.1f}" for t in THRESHOLDS)
            for cond, r in scores.items()
        )

    def summarize(self, results):
        sets = list(results)
        rows = {}
        for label, result in results[sets[0]].items():
            for cond in result["pck"]:
                rows[label + (f"|{cond}" if cond != "clean" else "")] = totals(
                    [results[s][label]["pck"][cond] for s in sets]
                )
        conf = {
            "scenes": sets,
            "n_pairs": sum(next(iter(results[s].values()))["pck"]["clean"]["pairs"] for s in sets),
            "resize_max": self.conf["resize_max"],
            "impl": list(results[sets[-1]].values())[-1]["impl"],  # the last matcher's
        }
        return markdown(rows, conf).rstrip("\n")
