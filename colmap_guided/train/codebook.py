"""python -m colmap_guided.train.codebook [--out PATH] [--words K]

The retrieval codebook: k-means (OpenCV, seeded) of the ALIKED descriptors of the coarse network's
training scenes (``scenes.all_scenes`` less ``VAL_SCENES``; ``--scenes permissive``: the
permissively licensed ones), extracted as the archive runs ALIKED (1,024 keypoints at 1,024 px).
Retrieval ranks an ALIKED database's photos by their VLAD over these words (``pairs.vlad``). The
file's metadata records the command's options, the scenes and the descriptor count.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from colmap_guided.features import aliked, list_images
from colmap_guided.log import logger, progress, set_verbosity
from colmap_guided.pairs import CODEBOOK
from colmap_guided.train.scenes import PERMISSIVE_SCENES, VAL_SCENES, all_scenes, scene_image_dir

ALIKED_CONF = {"max_num_keypoints": 1024, "max_image_size": 1024}


def training_descriptors(scenes: list[str], per_image: int, seed: int) -> np.ndarray:
    """Up to ``per_image`` ALIKED descriptors of every photo of ``scenes``, drawn at random."""
    conf = aliked.check_conf(ALIKED_CONF)
    model, device = aliked.load_model(conf)
    rng, out = np.random.default_rng(seed), []
    photos = [scene_image_dir(s) / n for s in scenes for n in list_images(scene_image_dir(s))]
    for path in progress(photos, "codebook", "img"):
        _, desc = aliked.extract_image(model, device, path, conf)
        out.append(desc[rng.permutation(len(desc))[:per_image]])
    return np.concatenate(out)


def train_codebook(descriptors: np.ndarray, words: int, seed: int) -> np.ndarray:
    """(words, D) unit centres of k-means on the unit ``descriptors``."""
    cv2.setRNGSeed(seed)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-5)
    _, _, centres = cv2.kmeans(
        np.ascontiguousarray(descriptors, np.float32),
        words,
        None,
        criteria,
        3,
        cv2.KMEANS_PP_CENTERS,
    )
    return centres / np.linalg.norm(centres, axis=1, keepdims=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=CODEBOOK)
    parser.add_argument("--words", type=int, default=64, help="visual words (k-means' k)")
    parser.add_argument("--scenes", choices=("train", "permissive"), default="train")
    parser.add_argument("--per_image", type=int, default=256, help="descriptors drawn per photo")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    set_verbosity(False)
    scenes = (
        PERMISSIVE_SCENES
        if args.scenes == "permissive"
        else [s for s in all_scenes() if s not in VAL_SCENES]
    )
    descriptors = training_descriptors(scenes, args.per_image, args.seed)
    words = train_codebook(descriptors, args.words, args.seed)
    from safetensors.numpy import save_file

    record = {**vars(args), "out": args.out.name, "aliked": ALIKED_CONF, "scenes": scenes}
    record["descriptors"] = len(descriptors)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_file({"words": words.astype(np.float32)}, str(args.out), {"config": json.dumps(record)})
    logger.info(
        "%d words of %d descriptors of %d scenes: %s",
        args.words,
        len(descriptors),
        len(scenes),
        args.out,
    )


if __name__ == "__main__":
    main()
