"""python -m colmap_guided.train --supervision epipolar --out DIR [--iterations N] [--max_minutes M]
...

Trains the coarse network's 4D filter (paper §4.2–4.3) on the SfM scenes of ../shared/data/train and
synthetic homography pairs, validates PCK on held-out scenes, and exports
OUT/coarse_filter.safetensors. Running the same command again resumes from OUT/checkpoint.pt.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from colmap_guided.log import logger, set_verbosity
from colmap_guided.train.data import CoarseTrainData
from colmap_guided.train.scenes import PERMISSIVE_SCENES
from colmap_guided.train.trainer import Trainer, default_conf

data_conf = CoarseTrainData.default_conf


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("--supervision", choices=["image", "epipolar", "points"], default="epipolar")
    p.add_argument(
        "--out", type=Path, required=True, help="output folder (checkpoint, curves, weights)"
    )
    p.add_argument("--iterations", type=int, default=default_conf["iterations"])
    p.add_argument(
        "--max_minutes", type=float, default=None, help="stop and checkpoint after this wall time"
    )
    p.add_argument("--batch_size", type=int, default=default_conf["batch_size"])
    p.add_argument("--lr", type=float, default=default_conf["lr"])
    p.add_argument(
        "--lr_steps",
        type=int,
        nargs="*",
        default=[],
        help="iterations after which the learning rates drop 10x",
    )
    p.add_argument("--seed", type=int, default=default_conf["seed"])
    p.add_argument("--backbone", default=data_conf["backbone"])
    p.add_argument(
        "--resolution",
        type=int,
        default=data_conf["resolution"],
        help="long side of training images (multiple of 16; the pipeline's resize_max is 512)",
    )
    p.add_argument(
        "--impl",
        choices=["sparse", "dense"],
        default=default_conf["impl"],
        help="sparse: the filter the CPU pipeline runs, on whole grids "
        "(default); dense: batched 4D conv (GPU, or --max_cells windows)",
    )
    p.add_argument(
        "--sparse_k",
        type=int,
        default=default_conf["sparse_k"],
        help="sparse support: best cells per cell and direction",
    )
    p.add_argument(
        "--sparse_radius",
        type=int,
        default=default_conf["sparse_radius"],
        help="sparse support: cells around each best match",
    )
    p.add_argument(
        "--max_cells",
        type=int,
        default=None,
        help="train on windows of at most this many feature "
        "cells per side (CPU budget); default: whole grids",
    )
    p.add_argument(
        "--scenes",
        default=None,
        help="comma-separated training scenes, or 'permissive' (default: all but validation)",
    )
    p.add_argument("--val_scenes", default=",".join(data_conf["val_scenes"]))
    p.add_argument("--val_pairs_per_scene", type=int, default=data_conf["val_pairs_per_scene"])
    p.add_argument(
        "--synthetic_ratio",
        type=float,
        default=data_conf["synthetic_ratio"],
        help="share of positives from homography pairs (0: SfM only, 1: synthetic only)",
    )
    p.add_argument(
        "--n_synthetic",
        type=int,
        default=data_conf["n_synthetic"],
        help="homography views cached per training photo",
    )
    p.add_argument(
        "--n_variants",
        type=int,
        default=data_conf["n_variants"],
        help="cached versions per image: clean, archival "
        "print, small soft scan (+ more alternating)",
    )
    p.add_argument(
        "--max_images_per_scene",
        type=int,
        default=None,
        help="at most this many images per scene (cache budget)",
    )
    p.add_argument("--archival_prob", type=float, default=data_conf["archival_prob"])
    p.add_argument(
        "--finetune_backbone", action="store_true", help="second stage: also train the backbone"
    )
    p.add_argument("--backbone_lr", type=float, default=default_conf["backbone_lr"])
    p.add_argument(
        "--init", type=Path, default=None, help="checkpoint.pt or .safetensors to start from"
    )
    p.add_argument("--val_every", type=int, default=default_conf["val_every"])
    p.add_argument("--checkpoint_every", type=int, default=default_conf["checkpoint_every"])
    p.add_argument("--log_every", type=int, default=default_conf["log_every"])
    p.add_argument("--cache_dir", type=Path, default=None)
    p.add_argument(
        "--cache_only", action="store_true", help="only compute the frozen-backbone feature cache"
    )
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--verbose", action="store_true")
    return p.parse_args(argv)


def conf_from_args(args: argparse.Namespace) -> dict:
    scenes = None
    if args.scenes == "permissive":
        scenes = PERMISSIVE_SCENES
    elif args.scenes:
        scenes = [s for s in args.scenes.split(",") if s]
    data = {
        "backbone": args.backbone,
        "resolution": args.resolution,
        "max_cells": args.max_cells,
        "train_scenes": scenes,
        "val_scenes": [s for s in args.val_scenes.split(",") if s],
        "val_pairs_per_scene": args.val_pairs_per_scene,
        "synthetic_ratio": args.synthetic_ratio,
        "n_synthetic": args.n_synthetic,
        "n_variants": args.n_variants,
        "archival_prob": args.archival_prob,
        "max_images_per_scene": args.max_images_per_scene,
        "cache_dir": str(args.cache_dir) if args.cache_dir else None,
    }
    return {
        "supervision": args.supervision,
        "impl": args.impl,
        "sparse_k": args.sparse_k,
        "sparse_radius": args.sparse_radius,
        "iterations": args.iterations,
        "max_minutes": args.max_minutes,
        "batch_size": args.batch_size,
        "lr": args.lr,
        "lr_steps": tuple(args.lr_steps),
        "seed": args.seed,
        "finetune_backbone": args.finetune_backbone,
        "backbone_lr": args.backbone_lr,
        "init": str(args.init) if args.init else None,
        "val_every": args.val_every,
        "checkpoint_every": args.checkpoint_every,
        "log_every": args.log_every,
        "model": {"backbone": args.backbone},
        "data": data,
    }


def main(argv=None) -> int:
    args = parse_args(argv)
    set_verbosity(args.verbose)
    if args.threads:
        torch.set_num_threads(args.threads)
    conf = conf_from_args(args)
    logger.info("Training conf: %s", json.dumps(conf))
    try:
        trainer = Trainer(args.out, conf)  # builds the feature cache when the backbone is frozen
    except ValueError as err:
        logger.error("%s", err)
        return 2
    if args.cache_only:
        return 0
    done = trainer.train()
    return 0 if done else 3  # 3: stopped on --max_minutes, resume with the same command


if __name__ == "__main__":
    raise SystemExit(main())
