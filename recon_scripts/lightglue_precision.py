"""LightGlue's layers in lower precision against float32, on the same pairs: matches kept and time.

    python -m recon_scripts.lightglue_precision [--set sacre_coeur_hloc] [--pairs 4]

Per pair of the set's first photos (ALIKED extracted as the pipeline does, in a temporary database):
LightGlue in float32 (the reference, timed before and after the others), with its linear layers
quantised to int8 (torch's dynamic quantisation: VNNI where the CPU has it) and with its layers
under bfloat16 autocast (``bf16=True``: emulated, and slower, where the CPU lacks native bf16).
Prints Markdown.
"""

from __future__ import annotations

import itertools
import tempfile
import time
from pathlib import Path

import torch

from colmap_guided import database as dbio
from colmap_guided import features
from colmap_guided.matchers import get_matcher
from colmap_guided.matchers.lightglue import native_bf16
from colmap_guided.paths import shared_data_dir
from recon_scripts import script_parser


def main(argv=None) -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--set", default="sacre_coeur_hloc")
    parser.add_argument("--pairs", type=int, default=4)
    args = parser.parse_args(argv)
    image_path = shared_data_dir() / args.set / "images"
    names = features.list_images(image_path)
    with tempfile.TemporaryDirectory() as tmp:
        db_path = Path(tmp) / "database.db"
        conf = features.check_conf({"type": "aliked"})
        features.extract_features(db_path, image_path, names, conf)
        with dbio.open_database(db_path) as db:
            data = {
                n: dbio.read_image_data(db, im, image_path)
                for n, im in dbio.images_by_name(db).items()
            }
    fp32 = get_matcher("lightglue", {"bf16": False})
    int8 = get_matcher("lightglue", {"bf16": False})
    int8.net = torch.ao.quantization.quantize_dynamic(
        int8.net, {torch.nn.Linear}, dtype=torch.qint8
    )
    bf16 = get_matcher("lightglue", {"bf16": True})
    variants = {"float32": fp32, "int8 linear layers": int8, "bfloat16 layers": bf16}
    print(f"\n{args.set}, native bf16: {native_bf16()}, torch threads {torch.get_num_threads()}\n")
    print("| pair | " + " | ".join(f"{v}: matches (kept), s" for v in variants) + " |")
    print("|---|" + "---|" * len(variants))
    for a, b in itertools.islice(itertools.combinations(sorted(data), 2), args.pairs):
        cells, reference = [], None
        for label, matcher in variants.items():
            start = time.perf_counter()
            matches = {tuple(m) for m in matcher.match(data[a], data[b]).tolist()}
            seconds = time.perf_counter() - start
            reference = matches if reference is None else reference
            kept = len(matches & reference) / max(len(reference), 1)
            cells.append(f"{len(matches)} ({kept:.1%}), {seconds:.2f}")
        start = time.perf_counter()
        fp32.match(data[a], data[b])
        cells[0] += f" / {time.perf_counter() - start:.2f}"
        print(f"| {Path(a).stem[:8]}–{Path(b).stem[:8]} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
