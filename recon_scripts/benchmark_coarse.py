"""Speed of the coarse network's neighbourhood-consensus filter, and pycolmap's exhaustive
SIFT matching of real pairs measured in the same run as the reference.

    python -m recon_scripts.benchmark_coarse [--grids 25 32] [--sift-images 10] [--workers 1 2]
        [--repeats 3]

Prints a Markdown table of ms per pair at square grids (25x25 and 32x32 by default) for
- naive: the paper's/NCNet's 4D convolution as a loop of conv3d (``conv4d_naive``, the tests'
  reference too),
- dense: ``NeighConsensus.forward`` (batched conv3d, both image orders in one 2-group pass),
- sparse k, radius: ``CoarseNet.match_sparse`` (filter on ``sparse_support``; correlation, mutual
  steps and argmax included), and raw mode (correlation + argmax, no filter),
with ratios vs naive; on CUDA (if present) dense, single and batched, in float32/float16/bfloat16.
Features are real (two photos of the Sacre Coeur resized square to the grid), so sparse supports
have realistic sizes. Filter weights: the default trained file if present, else random (the speed
does not depend on the values). Then the backbone per image, and the CPU target on one database of
--sift-images photos of --sift-set (pycolmap SIFT): pycolmap's exhaustive matching + verification vs
the guided match stage with 1 and 2 pair workers, same run, and the guided parts
(backbone, coarse, eq. 1) timed serially.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from colmap_guided.coarse import DEFAULT_WEIGHTS, CoarseMatcher, CoarseNet, save_filter_weights
from colmap_guided.coarse.matcher import PRECISIONS
from colmap_guided.coarse.model import correlation, soft_mutual_nn
from colmap_guided.images import read_image
from colmap_guided.paths import shared_data_dir
from recon_scripts import script_parser


def conv4d_naive(x, weight, bias=None, groups=1):
    """The paper's/NCNet's 4D convolution as a Python loop of 3D convolutions, one per output
    I-slice and kernel I-offset: the reference of this benchmark and of tests/test_coarse_conv4d."""
    n, _, ni, nj, nk, nl = x.shape
    ki = weight.shape[2]
    out = x.new_zeros(n, weight.shape[0], ni, nj, nk, nl)
    for i in range(ni):
        for a in range(ki):
            src = i + a - ki // 2
            if 0 <= src < ni:
                out[:, :, i] += torch.nn.functional.conv3d(
                    x[:, :, src],
                    weight[:, :, a],
                    padding=tuple(k // 2 for k in weight.shape[3:]),
                    groups=groups,
                )
    return out if bias is None else out + bias.view(1, -1, 1, 1, 1, 1)


def timed(fn, repeats: int, sync=lambda: None, warmup: bool = True) -> tuple[float, float]:
    """Best wall-clock and best process CPU time (all threads) of ``repeats`` runs after a
    warm-up, ms. CPU time is less sensitive than wall time to other processes sharing the cores."""
    if warmup:
        fn()
        sync()
    wall = cpu = float("inf")
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        sync()
        wall, cpu = min(wall, time.perf_counter() - t), min(cpu, time.process_time() - c)
    return 1000 * wall, 1000 * cpu


def square_features(net: CoarseNet, path: Path, grid: int, device) -> torch.Tensor:
    """The backbone features of the photo at ``path`` resized square to ``grid`` cells."""
    img = cv2.resize(read_image(path), (16 * grid, 16 * grid), interpolation=cv2.INTER_AREA)
    x = torch.from_numpy(img).permute(2, 0, 1)[None].float().to(device)
    with torch.no_grad():
        return net.extract_features(net.normalize(x))[0]


def cm_sparse(cm: CoarseMatcher) -> str:
    """The matcher's sparse support for a row label, empty unless sparse."""
    return (
        f", k={cm.conf['sparse_k']} radius={cm.conf['sparse_radius']}"
        if cm.impl == "sparse"
        else ""
    )


def match_stage(images: list[Path], workers: list[int], rounds: int = 5) -> dict:
    """The issue's CPU target on one database: pycolmap SIFT extraction; on the same keypoints, the
    guided matcher's parts timed serially (backbone per image, coarse match and eq. 1 per pair; the
    backbone features go to an h5 cache); then, on copies of the database, pycolmap's exhaustive
    matching (with verification) and colmap_guided's ``match_database`` with the guided matcher and
    each number of pair workers (backbone + coarse + eq. 1 + verification), and once more with the
    most workers reading the backbone features from the cache (the per-pair cost alone); ``rounds``
    interleaved repetitions of these runs."""
    import pycolmap

    from colmap_guided import database as dbio
    from colmap_guided.match import match_database
    from colmap_guided.matchers import get_matcher

    work = Path(tempfile.mkdtemp(prefix="bench_coarse_"))
    try:
        (work / "images").mkdir()
        for p in images:
            shutil.copy(p, work / "images" / p.name)
        db = work / "db.db"
        t = time.perf_counter()
        pycolmap.extract_features(db, work / "images")
        out = {
            "extract_s_per_image": (time.perf_counter() - t) / len(images),
            "pairs": len(images) * (len(images) - 1) // 2,
        }

        cache = {"cache_path": str(work / "features.h5")}
        matcher = get_matcher("guided", {"workers": 1, "coarse": cache})
        with dbio.open_database(db) as database:
            data = [
                dbio.read_image_data(database, im, work / "images")
                for im in dbio.images_by_name(database).values()
            ]
        out["keypoints"] = int(np.mean([len(d.keypoints) for d in data]))
        t = time.perf_counter()
        for d in data:
            matcher.prepare(d)
        out["backbone_ms_per_image"] = 1000 * (time.perf_counter() - t) / len(data)
        coarse = eq1 = 0.0
        for i, a in enumerate(data):
            for b in data[i + 1 :]:
                t = time.perf_counter()
                flows = matcher.coarse_flows(a, b)
                coarse, t = coarse + time.perf_counter() - t, time.perf_counter()
                matcher.match_flows(a, b, flows)
                eq1 += time.perf_counter() - t
        out["coarse_ms"], out["eq1_ms"] = 1000 * coarse / out["pairs"], 1000 * eq1 / out["pairs"]

        runs = {
            "pycolmap": None,
            **{f"guided_{w}": {"workers": w} for w in workers},
            "guided_cached": {"workers": max(workers), "coarse": cache},
        }
        # interleaved rounds: a shared machine's slow spells hit every row alike
        for _ in range(rounds):
            for name, conf in runs.items():
                copy = work / f"{name}.db"
                shutil.copy(db, copy)
                t = time.perf_counter()
                if conf is None:
                    pycolmap.match_exhaustive(copy)
                else:
                    match_database(copy, work / "images", matcher=get_matcher("guided", conf))
                out.setdefault(name, []).append(1000 * (time.perf_counter() - t) / out["pairs"])
                with dbio.open_database(copy) as database:
                    out.setdefault(f"{name}_verified", set()).add(
                        dbio.database_summary(database)["num_verified_pairs"]
                    )
        return out
    finally:
        shutil.rmtree(work, ignore_errors=True)


def print_match_stage(r: dict, n_images: int, workers: list[int], set_name: str) -> None:
    """The match stage's table of ``match_stage``'s timings."""
    ref = np.array(r["pycolmap"])
    print(
        f"\nMatch stage on one database ({n_images} {set_name} images, {r['pairs']} pairs, "
        f"{r['keypoints']} SIFT keypoints/image, pycolmap {__import__('pycolmap').__version__}; "
        f"wall ms per pair, median of {len(ref)} interleaved rounds; vs pycolmap: median and "
        "range of the per-round ratios):\n"
    )
    print("| matching + verification | ms / pair | vs pycolmap | verified pairs |")
    print("|---|---|---|---|")
    rows = [("pycolmap", "pycolmap exhaustive (SIFT matching, all cores)")]
    rows += [
        (
            f"guided_{w}",
            f"guided `match_database`, {w} pair worker(s): "
            "backbone + coarse + eq. 1 + verification",
        )
        for w in workers
    ]
    rows += [
        (
            "guided_cached",
            f"guided, {max(workers)} pair worker(s), backbone "
            "features from the cache: coarse + eq. 1 + verification",
        )
    ]
    for key, label in rows:
        ratio = np.array(r[key]) / ref
        verified = "/".join(map(str, sorted(r[f"{key}_verified"])))
        print(
            f"| {label} | {np.median(r[key]):.0f} | {np.median(ratio):.2f} "
            f"({ratio.min():.2f}-{ratio.max():.2f}) | {verified} |"
        )
    ref, serial = np.median(ref), r["coarse_ms"] + r["eq1_ms"]
    print(
        f"\nGuided parts, serial, 1 thread: backbone {r['backbone_ms_per_image']:.0f} "
        f"ms/image; per pair coarse match + flows {r['coarse_ms']:.0f} ms + eq. 1 "
        f"{r['eq1_ms']:.0f} ms = {serial:.0f} ms ({serial / ref:.2f}x pycolmap's "
        f"matching + verification). SIFT extraction {r['extract_s_per_image']:.2f} s/image."
    )


def _parser():
    """The command line."""
    parser = script_parser(__doc__)
    parser.add_argument("--grids", type=int, nargs="+", default=[25, 32])
    parser.add_argument(
        "--supports",
        nargs="+",
        default=["3,0", "5,0", "10,0", "3,1"],
        help="sparse supports 'k,radius'",
    )
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-naive", action="store_true", help="skip the slow naive loop")
    parser.add_argument(
        "--sift-images",
        type=int,
        default=10,
        help="photos of --sift-set for the SIFT reference (0: skip)",
    )
    parser.add_argument(
        "--sift-set",
        default="sacre_coeur_hloc",
        help="the shared photo set of the SIFT reference (sceaux_castle: 6 MP)",
    )
    parser.add_argument(
        "--stage-rounds",
        type=int,
        default=5,
        help="interleaved repetitions of the match stage runs",
    )
    parser.add_argument(
        "--workers",
        type=int,
        nargs="+",
        default=[1, 2],
        help="pair workers of the guided match stage rows",
    )
    parser.add_argument(
        "--batch", type=int, default=8, help="pairs per batch for the batched GPU row"
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch CPU threads (1: as the pipeline matches on CPU, CoarseMatcher num_threads)",
    )
    return parser


def _filter_weights() -> tuple[Path, str]:
    """The trained filter weights, else random ones in a temporary file; and which of the two."""
    if DEFAULT_WEIGHTS.is_file():
        return DEFAULT_WEIGHTS, "trained"
    # the speed does not depend on the values
    weights = Path(tempfile.mkdtemp(prefix="bench_coarse_")) / "random.safetensors"
    save_filter_weights(CoarseNet({"pretrained": False}), weights, resize_max=512)
    return weights, "random"


def _supports(supports: list[str]) -> list[tuple[int, int]]:
    """``--supports`` values as (k, radius)."""
    return [tuple(map(int, sup.split(","))) for sup in supports]


def _timer(rows: list, device, grid: int, repeats: int, sync):
    """A function timing ``fn`` and adding its row to ``rows`` (times per pair of ``per``)."""

    def add(method: str, fn, per: int = 1, repeats: int = repeats, warmup: bool = True):
        ms, cpu = timed(fn, repeats, sync, warmup)
        rows.append((device.type, method, grid, ms / per, cpu / per))

    return add


def _cuda_rows(add, net: CoarseNet, fa, fb, vin, batch: int) -> None:
    """The GPU rows at one grid: the filter batched, the dense match single and batched."""
    vb = vin.expand(batch, -1, -1, -1, -1).contiguous()
    add(f"dense batched x{batch} (filter only)", lambda: net.filter(vb), per=batch)
    add("dense match (corr+filter+argmax)", lambda: net.match(fa, fb, "dense"))
    fab, fbb = (f[None].expand(batch, -1, -1, -1).contiguous() for f in (fa, fb))
    for name, dtype in PRECISIONS.items():  # the <= 2 ms/pair target: batched, features cached
        add(
            f"dense match batched x{batch}, {name} (corr+filter+argmax)",
            lambda: net.match_batch(fab, fbb, dtype),
            per=batch,
        )


def _grid_rows(net: CoarseNet, raw: CoarseNet, pair: list[Path], grid: int, device, args, sync):
    """The rows at one square grid: the filter alone (naive, dense) and each match mode."""
    rows = []
    add = _timer(rows, device, grid, args.repeats, sync)
    fa, fb = (square_features(net, p, grid, device) for p in pair)
    with torch.no_grad():
        vin = soft_mutual_nn(torch.relu(correlation(fa[None], fb[None])))
        if not args.no_naive and device.type == "cpu":

            def run_naive():
                x = vin.unsqueeze(1)
                for w, b, groups in net.filter.fused_layers():
                    x = torch.relu(conv4d_naive(x, w, b, groups))
                return x.mean(1)

            add("naive loop of conv3d (filter only)", run_naive, repeats=1, warmup=False)
        add("dense (filter only)", lambda: net.filter(vin))
        if device.type == "cuda":
            _cuda_rows(add, net, fa, fb, vin, args.batch)
        for k, r in _supports(args.supports):
            add(
                f"sparse k={k} radius={r} match (corr+filter+argmax)",
                lambda: net.match(fa, fb, "sparse", k, r),
            )
        add("raw mode match (corr+argmax)", lambda: raw.match(fa, fb))
    return rows


def _device_rows(device, weights: Path, raw: CoarseNet, pair: list[Path], args) -> list[tuple]:
    """The rows of one device: every grid, then the backbone and the matcher on the real pair."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    cm = CoarseMatcher(
        {"mode": "filter", "weights": weights, "device": device.type, "num_threads": None}
    )
    net = cm.net
    raw.to(device)
    rows = [
        row for grid in args.grids for row in _grid_rows(net, raw, pair, grid, device, args, sync)
    ]
    add = _timer(rows, device, 0, args.repeats, sync)
    img = (
        torch.from_numpy(cv2.resize(read_image(pair[0]), (512, 368)))
        .permute(2, 0, 1)[None]
        .float()
        .to(device)
    )
    with torch.no_grad():
        add("backbone Lite0 per image (512x368)", lambda: net.extract_features(net.normalize(img)))
    fa, fb = (cm.extract(read_image(p)) for p in pair)
    add(
        f"CoarseMatcher.match, real pair 32x23 / 24x32 (default: {cm.impl}{cm_sparse(cm)})",
        lambda: cm.match(fa, fb),
    )
    if device.type == "cpu":
        for k, r in _supports(args.supports):
            add(
                f"real pair 32x23 / 24x32, sparse k={k} radius={r}",
                lambda: net.match(fa.features, fb.features, "sparse", k, r),
            )
    return rows


def sift_reference(args) -> float | None:
    """pycolmap's matching + verification ms per pair (match stage table printed), or None."""
    if args.sift_images < 2:
        return None
    sc = sorted(
        p
        for p in (shared_data_dir() / args.sift_set / "images").iterdir()
        if p.suffix.lower() in (".jpg", ".jpeg")
    )
    sc = sc[: args.sift_images]
    stage = match_stage(sc, args.workers, args.stage_rounds)
    print_match_stage(stage, len(sc), args.workers, args.sift_set)
    return float(np.median(stage["pycolmap"]))


def print_filter_table(rows: list[tuple], label: str, sift: float | None) -> None:
    """The coarse filter's table, with ratios vs the naive loop and vs pycolmap's matching."""
    naive_ms = {(d, g): ms for d, m, g, ms, _ in rows if m.startswith("naive")}
    print(
        f"\nCoarse filter ({label} weights, {torch.get_num_threads()} CPU threads, "
        f"torch {torch.__version__}); CPU = process time of all threads; vs SIFT = "
        "wall time / pycolmap's exhaustive matching + verification per pair\n"
    )
    print(
        "| device | method | grid | ms / pair (wall) | "
        "ms / pair (CPU) | vs naive (wall) | vs SIFT (wall) |"
    )
    print("|---|---|---|---|---|---|---|")
    for d, m, g, ms, cpu in rows:
        ref = naive_ms.get((d, g))
        ratio = f"{ref / ms:.1f}x faster" if ref and g else ""
        vs_sift = f"{ms / sift:.2f}" if sift and d == "cpu" else ""
        print(
            f"| {d} | {m} | {f'{g}x{g}' if g else '-'} | "
            f"{ms:.1f} | {cpu:.1f} | {ratio} | {vs_sift} |"
        )


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    weights, label = _filter_weights()
    raw = CoarseNet({"filter": False}).eval()
    images = shared_data_dir() / "lightglue_assets" / "images"
    pair = [images / "sacre_coeur1.jpg", images / "sacre_coeur2.jpg"]
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    rows = [row for device in devices for row in _device_rows(device, weights, raw, pair, args)]
    sift = sift_reference(args)
    print_filter_table(rows, label, sift)
    return 0


if __name__ == "__main__":
    sys.exit(main())
