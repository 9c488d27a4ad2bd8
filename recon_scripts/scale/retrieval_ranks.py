"""Where retrieval ranks each photo's own place in the development archive: GeM of the coarse
network's backbone against VLAD of ALIKED (``colmap_guided.pairs``), on one run's database.

    python -m recon_scripts.scale.retrieval_ranks WORKSPACE ARCHIVE

WORKSPACE: a run's output (its database.db holds ALIKED); ARCHIVE: the archive (``images/``,
``labels.json``). Per kind of label (training scenes left out: the codebook's and the network's
data), over the photos whose label has another photo: the share whose most similar photo of their
own label ranks first, within 5 and within 10 among all the archive's photos, the median rank, and
the share of the 10 nearest that are of other labels.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from recon_scripts.scale.archive import label_of


def kind(label: str) -> str:
    prefix = label.split(":")[0]
    return prefix if prefix in ("rendered", "wxbs") else "real"


def ranks(desc: np.ndarray, labels: list[str]) -> dict[str, dict]:
    """Per kind: recall at 1, 5, 10 of the photo's own label, median rank, others in the top 10."""
    sim = desc @ desc.T
    np.fill_diagonal(sim, -np.inf)
    order = np.argsort(-sim, axis=1, kind="stable")
    out: dict[str, list] = {}
    for i, label in enumerate(labels):
        if label.startswith("train:") or labels.count(label) < 2:
            continue
        same = np.array([labels[j] == label for j in order[i]])
        out.setdefault(kind(label), []).append((int(np.argmax(same)), 1 - same[:10].mean()))
    return {
        k: {
            "photos": len(v),
            **{f"r@{n}": float(np.mean([r < n for r, _ in v])) for n in (1, 5, 10)},
            "median": float(np.median([r for r, _ in v])),
            "others_in_top10": float(np.mean([o for _, o in v])),
        }
        for k, v in sorted(out.items())
    }


def main() -> None:
    from colmap_guided import database as dbio
    from colmap_guided.match import _global_descriptors
    from colmap_guided.matchers import get_matcher

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("archive", type=Path)
    args = parser.parse_args()
    of = label_of(json.loads((args.archive / "labels.json").read_text()))
    images = args.archive / "images"
    with dbio.open_database(args.workspace / "database.db") as db:
        names = [n for n in sorted(dbio.images_by_name(db)) if of(n)]
        matcher = get_matcher("guided_lightglue")
        found = {"VLAD of ALIKED": _global_descriptors(matcher, images, names, db)}
    found["GeM of the backbone"] = _global_descriptors(matcher, images, names)
    labels = [of(n) for n in names]
    print("| descriptor | labels | photos | r@1 | r@5 | r@10 | median rank | others in top 10 |")
    print("|---|---|---|---|---|---|---|---|")
    for name, desc in found.items():
        for k, r in ranks(desc, labels).items():
            print(
                f"| {name} | {k} | {r['photos']} | {r['r@1']:.2f} | {r['r@5']:.2f} "
                f"| {r['r@10']:.2f} | {r['median']:.0f} | {r['others_in_top10']:.2f} |"
            )


if __name__ == "__main__":
    main()
