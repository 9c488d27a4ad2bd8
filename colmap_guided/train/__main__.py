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

from colmap_guided.conf import add_conf_flags, conf_from_flags
from colmap_guided.log import logger, set_verbosity
from colmap_guided.train import trainer
from colmap_guided.train.data import CoarseTrainData
from colmap_guided.train.scenes import PERMISSIVE_SCENES
from colmap_guided.train.trainer import Trainer

# the options of trainer.default_conf and CoarseTrainData.default_conf given as flags
TRAIN_KEYS = [
    "supervision",
    "iterations",
    "max_minutes",
    "batch_size",
    "lr",
    "lr_steps",
    "seed",
    "impl",
    "sparse_k",
    "sparse_radius",
    "finetune_backbone",
    "backbone_lr",
    "init",
    "val_every",
    "checkpoint_every",
    "log_every",
]
DATA_KEYS = [
    "backbone",
    "resolution",
    "max_cells",
    "val_pairs_per_scene",
    "synthetic_ratio",
    "n_synthetic",
    "n_variants",
    "max_images_per_scene",
    "archival_prob",
    "cache_dir",
]


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument(
        "--out", type=Path, required=True, help="output folder (checkpoint, curves, weights)"
    )
    p.add_argument(
        "--scenes",
        default=None,
        help="comma-separated training scenes, or 'permissive' (default: all but validation)",
    )
    p.add_argument(
        "--val_scenes",
        default=",".join(CoarseTrainData.default_conf["val_scenes"]),
        help="comma-separated held-out scenes of the validation PCK (default: %(default)s)",
    )
    p.add_argument(
        "--cache_only", action="store_true", help="only compute the frozen-backbone feature cache"
    )
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--verbose", action="store_true")
    add_conf_flags(
        p.add_argument_group("training options"),
        trainer,
        TRAIN_KEYS,
        types={"max_minutes": float, "init": str, "lr_steps": int},
        choices={"supervision": ["image", "epipolar", "points"], "impl": ["sparse", "dense"]},
        what="training",
    )
    add_conf_flags(
        p.add_argument_group("data options"),
        CoarseTrainData,
        DATA_KEYS,
        types={"max_cells": int, "max_images_per_scene": int, "cache_dir": str},
        what="data",
    )
    return p.parse_args(argv)


def conf_from_args(args: argparse.Namespace) -> dict:
    scenes = None
    if args.scenes == "permissive":
        scenes = PERMISSIVE_SCENES
    elif args.scenes:
        scenes = [s for s in args.scenes.split(",") if s]
    data = conf_from_flags(args, CoarseTrainData, DATA_KEYS, "data")
    data |= {"train_scenes": scenes, "val_scenes": [s for s in args.val_scenes.split(",") if s]}
    conf = conf_from_flags(args, trainer, TRAIN_KEYS, "training")
    return {**conf, "model": {"backbone": args.backbone}, "data": data}


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
