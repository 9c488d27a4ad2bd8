"""PCK of the coarse matcher on held-out SfM pairs (paper Table 1 protocol), Markdown + JSON.

For every ground-truth match (p^A, p^B) — the two observations of a 3D point shared by a positive
pair (≥ 30 common points) of a held-out scene — the error is ‖m^{A→B}(p^A) − p^B‖ (and the reverse
direction), measured two ways: in pixels of the ORIGINAL images (stricter for images larger than the
network input) and, as the paper's Table 1, in pixels of the RESIZED image (the network input,
``--resize_max`` long side; 16 px = one feature cell): the error vector scaled by the target image's
resize factor per axis. PCK@t is the share of errors below t = 8, 16, 32 px.

Methods: raw correlation (no filter, mutual-NN-free argmax), the untrained filter (random init,
seed 0), and every trained filter given with --weights. Optionally --archival PRESET also measures
every method with image B degraded by that archival preset (an old photo matched to a modern one).

    python -m recon_scripts.eval_coarse_pck \
        --weights outputs/train_epipolar_lite0/coarse_filter.safetensors \
        --out outputs/coarse_pck [--pairs_per_scene 25] [--resize_max 512] [--impl sparse] \
        [--archival damaged_scan]
"""

from __future__ import annotations

import json
import tempfile
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
from colmap_guided.log import logger, set_verbosity
from colmap_guided.train.scenes import VAL_SCENES, load_scene
from recon_scripts import script_parser

THRESHOLDS = (8, 16, 32)


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
    """PCK at original resolution (keys ``pck8`` ...) and in resized pixels
    (``resized_pck8`` ...)."""
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
    result = {"per_scene": {}, "ms_per_pair": 1000 * t_match / max(len(pairs), 1)}
    for prefix, by_scene in errors.items():
        for scene, errs in by_scene.items():
            e = np.concatenate(errs)
            result["per_scene"].setdefault(scene, {"n": int(len(e)), "pairs": len(errs)})
            result["per_scene"][scene].update(
                {f"{prefix}pck{t}": float((e < t).mean()) for t in THRESHOLDS}
            )
        every = (
            np.concatenate([np.concatenate(v) for v in by_scene.values()])
            if by_scene
            else np.zeros(0)
        )
        result.update(
            {
                f"{prefix}pck{t}": float((every < t).mean()) if len(every) else float("nan")
                for t in THRESHOLDS
            }
        )
        # mean over scenes (each held-out scene weighs the same, whatever its number of points)
        result.update(
            {
                f"{prefix}scene_mean_pck{t}": float(
                    np.mean([v[f"{prefix}pck{t}"] for v in result["per_scene"].values()])
                )
                for t in THRESHOLDS
            }
        )
        result["n_points"] = int(len(every))
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


def _parser():
    """The command line."""
    p = script_parser(__doc__)
    p.add_argument(
        "--weights", nargs="*", type=Path, default=[], help="trained filter .safetensors files"
    )
    p.add_argument("--labels", nargs="*", default=None, help="names of the --weights in the table")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--scenes", nargs="+", default=VAL_SCENES)
    p.add_argument("--pairs_per_scene", type=int, default=25)
    p.add_argument("--max_points", type=int, default=500, help="GT matches per pair")
    p.add_argument("--resize_max", type=int, default=512)
    p.add_argument("--impl", choices=["auto", "dense", "sparse"], default="auto")
    p.add_argument(
        "--sparse_k",
        type=int,
        default=CoarseMatcher.default_conf["sparse_k"],
        help="sparse filter: best cells kept per cell (product default)",
    )
    p.add_argument("--backbone", default="efficientnet-lite0")
    p.add_argument(
        "--archival",
        default=None,
        help=f"also evaluate with B degraded by a preset of {sorted(archival.PRESETS)}",
    )
    p.add_argument(
        "--no_baselines", action="store_true", help="skip raw correlation and the untrained filter"
    )
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch CPU threads (1: as the pipeline matches on CPU)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--verbose", action="store_true")
    return p


def weight_labels(args) -> list[str]:
    """The table names of the ``--weights``: ``--labels``, else each file's run folder or stem."""
    return args.labels or [
        w.parent.name if w.name == "coarse_filter.safetensors" else w.stem for w in args.weights
    ]


def methods_to_run(args, tmp: Path) -> list[tuple[str, dict]]:
    """(label, matcher options) of the baselines (the untrained filter saved in ``tmp``) and of
    each trained filter."""
    methods: list[tuple[str, dict]] = []
    if not args.no_baselines:
        untrained = untrained_weights(tmp / "untrained.safetensors", args.backbone, args.resize_max)
        methods.append(("raw correlation", {"mode": "raw"}))
        methods.append(("untrained filter", {"weights": str(untrained)}))
    return methods + [
        (label, {"weights": str(w)}) for label, w in zip(weight_labels(args), args.weights)
    ]


def evaluate_methods(methods: list[tuple[str, dict]], pairs, args) -> tuple[dict, str]:
    """Each method's PCK, clean and with ``--archival``; and the last matcher's filter path."""
    common = {
        "backbone": args.backbone,
        "resize_max": args.resize_max,
        "impl": args.impl,
        "sparse_k": args.sparse_k,
    }
    weights = dict(zip(weight_labels(args), args.weights))
    conditions = [None] + ([args.archival] if args.archival else [])
    results, shared_cache = {}, {}
    for label, conf in methods:
        matcher = CoarseMatcher({**common, **conf})
        # features computed once per backbone
        matcher.cache = shared_cache.setdefault(matcher.features_key, {})
        for cond in conditions:
            name = label + (f"|{cond}" if cond else "")
            r = results[name] = evaluate(matcher, pairs, cond, name)
            logger.info(
                "%-32s PCK@8/16/32 = %.1f / %.1f / %.1f %%",
                name,
                100 * r["pck8"],
                100 * r["pck16"],
                100 * r["pck32"],
            )
        if label not in ("raw correlation", "untrained filter"):
            results[label]["weights"] = str(weights[label])
            results[label]["training"] = matcher.weights_config.get("training", {})
    return results, matcher.impl


def write_results(out: Path, results: dict, conf: dict) -> None:
    """OUT/coarse_pck.json and OUT/coarse_pck.md; the Markdown printed."""
    (out / "coarse_pck.json").write_text(json.dumps({"conf": conf, "results": results}, indent=1))
    md = markdown(results, conf)
    (out / "coarse_pck.md").write_text(md)
    print(md)


def main(argv=None):
    args = _parser().parse_args(argv)
    set_verbosity(args.verbose)
    if args.threads:
        torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    pairs = select_pairs(args.scenes, args.pairs_per_scene, args.max_points, args.seed)
    logger.info("%d held-out pairs from %s.", len(pairs), ", ".join(args.scenes))
    with tempfile.TemporaryDirectory() as tmp:
        results, impl = evaluate_methods(methods_to_run(args, Path(tmp)), pairs, args)
        conf = {
            "scenes": args.scenes,
            "n_pairs": len(pairs),
            "resize_max": args.resize_max,
            "impl": impl,
            "pairs_per_scene": args.pairs_per_scene,
            "max_points": args.max_points,
            "seed": args.seed,
            "archival": args.archival,
        }
        write_results(args.out, results, conf)


if __name__ == "__main__":
    main()
