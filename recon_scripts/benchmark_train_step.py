"""Seconds per training iteration of the coarse filter's paths, interleaved in one run.

Sparse filter on whole grids (the default, what the CPU pipeline runs), dense filter on 12x12-cell
windows (the former CPU recipe) and dense on whole grids (the GPU recipe; slow on a CPU:
--dense_whole steps only). Uses the frozen-feature cache of the default training data
(built on first use).

    python -m recon_scripts.benchmark_train_step [--steps 6] [--dense_whole 1] [--resolution 512]
"""

from __future__ import annotations

import json
import tempfile
import time

import numpy as np
import torch

from colmap_guided.train.trainer import Trainer
from recon_scripts import script_parser


def main(argv=None):
    p = script_parser(__doc__)
    p.add_argument(
        "--steps", type=int, default=6, help="iterations of the sparse and the windowed dense path"
    )
    p.add_argument(
        "--dense_whole", type=int, default=1, help="iterations of the dense filter on whole grids"
    )
    p.add_argument("--resolution", type=int, default=512)
    p.add_argument("--batch_size", type=int, default=8)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    data = {"resolution": args.resolution, "val_pairs_per_scene": 1}
    paths = {
        "sparse, whole grids": ({"impl": "sparse"}, args.steps),
        "dense, 12x12-cell windows": (
            {"impl": "dense", "data": {**data, "max_cells": 12}},
            args.steps,
        ),
        "dense, whole grids": ({"impl": "dense"}, args.dense_whole),
    }
    times: dict[str, list[float]] = {k: [] for k in paths}
    with tempfile.TemporaryDirectory() as tmp:
        trainers = {
            k: Trainer(f"{tmp}/{i}", {"data": data, "batch_size": args.batch_size, **conf})
            for i, (k, (conf, _)) in enumerate(paths.items())
        }
        for r in range(max(n for _, n in paths.values())):
            for k, tr in trainers.items():
                if r < paths[k][1]:
                    t = time.perf_counter()
                    tr.step()
                    times[k].append(time.perf_counter() - t)
    print("| training path | s / iteration (median) | iterations |\n|---|---|---|")
    for k, v in times.items():
        if v:
            print(f"| {k} | {np.median(v):.2f} | {len(v)} |")
    print(json.dumps(times))


if __name__ == "__main__":
    main()
