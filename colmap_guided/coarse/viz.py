"""Visual check of coarse matches: ``python -m colmap_guided.coarse IMG_A IMG_B --out flow.png``.

Draws A and B side by side; each A cell's match is a dot of the same colour in both images (colour
= position in A), joined by a line for mutual matches. Non-mutual matches are drawn smaller.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from colmap_guided.coarse.flow import CoarseResult
from colmap_guided.coarse.geometry import as_rgb
from colmap_guided.conf import add_conf_flags, conf_from_flags
from colmap_guided.log import logger, set_verbosity


def draw_coarse_matches(
    image_a: np.ndarray,
    image_b: np.ndarray,
    result: CoarseResult,
    height: int = 600,
    lines: bool = True,
) -> np.ndarray:
    """RGB uint8 canvas with both images at ``height`` px and the A→B coarse matches
    colour-coded."""
    a, b = as_rgb(image_a), as_rgb(image_b)
    sa, sb = height / a.shape[0], height / b.shape[0]
    a = cv2.resize(a, (round(a.shape[1] * sa), height), interpolation=cv2.INTER_AREA)
    b = cv2.resize(b, (round(b.shape[1] * sb), height), interpolation=cv2.INTER_AREA)
    canvas = (np.concatenate([a, b], axis=1) * 0.6).astype(np.uint8)
    src, dst, _, mutual = result.grid_matches_ab()
    ga = result.geometry_a
    hue = (src[:, 0] / ga.width * 150).astype(np.uint8)
    val = (130 + src[:, 1] / ga.height * 125).astype(np.uint8)
    colours = cv2.cvtColor(
        np.stack([hue, np.full_like(hue, 255), val], 1)[None], cv2.COLOR_HSV2RGB
    )[0]
    pa, pb = src * sa, dst * sb + [a.shape[1], 0]
    for m in np.argsort(mutual, kind="stable"):  # mutual matches drawn last, on top
        c = tuple(int(v) for v in colours[m])
        p, q = tuple(int(v) for v in pa[m]), tuple(int(v) for v in pb[m])
        if mutual[m] and lines:
            cv2.line(canvas, p, q, c, 1, cv2.LINE_AA)
        r = 4 if mutual[m] else 2
        cv2.circle(canvas, p, r, c, -1, cv2.LINE_AA)
        cv2.circle(canvas, q, r, c, -1, cv2.LINE_AA)
    return canvas


def add_parser(sub) -> None:
    """``coarse`` in the package's command list; its own parser (``main``) reads its arguments."""
    sub.add_parser(
        "coarse",
        help="coarse matches of two images drawn to a PNG (see `coarse --help`)",
        add_help=False,
    )


def main(argv: list[str] | None = None) -> int:
    import torch

    from colmap_guided.coarse.matcher import CoarseMatcher
    from colmap_guided.images import read_image
    from colmap_guided.workspace import check_output_file

    parser = argparse.ArgumentParser(
        prog="python -m colmap_guided.coarse",
        description="Coarse matches of two images, drawn to a PNG.",
    )
    parser.add_argument("image_a", type=Path)
    parser.add_argument("image_b", type=Path)
    parser.add_argument("--out", type=Path, default=Path("coarse_matches.png"))
    parser.add_argument(
        "--mode",
        choices=["filter", "raw", "auto"],
        default="auto",
        help="auto: filter if weights exist, else raw",
    )
    keys = add_conf_flags(
        parser,
        CoarseMatcher,
        ["weights", "backbone", "resize_max", "impl", "device"],
        types={"weights": str},
        choices={"impl": ["auto", "dense", "sparse"]},
    )
    parser.add_argument("--no-lines", action="store_true")
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args(argv)
    set_verbosity(args.verbose)
    try:  # a drawing never replaces a file
        check_output_file(args.out)
    except ValueError as err:
        logger.error("%s", err)
        return 2
    conf = conf_from_flags(args, CoarseMatcher, keys)
    if args.mode == "auto":
        try:
            cm = CoarseMatcher({**conf, "mode": "filter"})
        except FileNotFoundError as e:
            logger.warning("%s; using raw mode", e)
            cm = CoarseMatcher({**conf, "mode": "raw"})
    else:
        cm = CoarseMatcher({**conf, "mode": args.mode})
    img_a, img_b = read_image(args.image_a), read_image(args.image_b)
    if cm.torch_threads is not None:  # a command line owns its process: the pipeline's CPU threads
        torch.set_num_threads(cm.torch_threads)
    t0 = time.perf_counter()
    fa, fb = cm.extract(img_a), cm.extract(img_b)
    t1 = time.perf_counter()
    res = cm.match(fa, fb)
    t2 = time.perf_counter()
    mutual = res.matches.mutual_ab
    logger.info(
        "%s mode (%s): grids %dx%d / %dx%d, %d/%d mutual; features %.0f ms, matching %.0f ms",
        cm.conf["mode"],
        cm.impl,
        fa.geometry.grid_width,
        fa.geometry.grid_height,
        fb.geometry.grid_width,
        fb.geometry.grid_height,
        mutual.sum(),
        mutual.size,
        1000 * (t1 - t0),
        1000 * (t2 - t1),
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    canvas = draw_coarse_matches(img_a, img_b, res, lines=not args.no_lines)
    if not cv2.imwrite(str(args.out), cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR)):
        raise OSError(
            f"Could not write {args.out}: check the folder and the extension (.png, .jpg)"
        )
    logger.info("Wrote %s", args.out)
    return 0
