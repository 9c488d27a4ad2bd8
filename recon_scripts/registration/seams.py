"""Where a model would be cut (``join.find_cut``): each model's weakest seam in shared points and
how its two sides see each other; a model of one place should not be cut, two places that look
alike mapped as one should.

    python -m recon_scripts.registration.seams [in_front=X] [MODEL ...]

MODEL: a COLMAP model folder, or a workspace's sparse/ (each model in it); default: every COLMAP
model of ../shared/data (the sets' reference models, each of one place). ``in_front``: a conflict
is a point at most this share of the depth seen (default ``join.SPLIT_IN_FRONT``; the join's own
test counts 0.95).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pycolmap

from colmap_guided import join
from colmap_guided.paths import shared_data_dir


def model_folders(paths: list[str]) -> list[Path]:
    """The model folders of ``paths`` (a model, or a folder of models), or of ../shared/data."""
    if not paths:
        found = {
            p.parent for p in shared_data_dir().rglob("images.*") if p.suffix in (".bin", ".txt")
        }
        return sorted(
            p for p in found if (p / "points3D.bin").exists() or (p / "points3D.txt").exists()
        )
    out = []
    for path in map(Path, paths):
        models = [path] if (path / "images.bin").exists() else sorted(path.glob("[0-9]*"))
        out += [m for m in models if (m / "images.bin").exists() or (m / "images.txt").exists()]
    return out


def main(argv: list[str]) -> None:
    root = shared_data_dir()
    in_front = join.SPLIT_IN_FRONT
    if argv and argv[0].startswith("in_front="):
        in_front = float(argv.pop(0).split("=", 1)[1])
    print("| model | photos | seam: photos of one side | conflicts / agreements | share | cut |")
    print("|---|---|---|---|---|---|")
    for folder in model_folders(argv):
        rec = pycolmap.Reconstruction(str(folder))
        found = join.find_cut(rec, in_front)
        c, a = found["conflicts"], found["agreements"]
        side = len(found["side"]) if found["side"] else "–"
        name = folder.relative_to(root) if folder.is_relative_to(root) else folder
        print(
            f"| {name} | {rec.num_reg_images()} | {side} | {c} / {a} | {c / max(1, c + a):.3f} "
            f"| {'yes' if found['cut'] else 'no'} |",
            flush=True,
        )


if __name__ == "__main__":
    main(sys.argv[1:])
