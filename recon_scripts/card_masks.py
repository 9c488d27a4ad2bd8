"""Verified inliers on the parts of scanned cards that are not their picture, with and without the
card anatomy (colmap_guided/cards.py), and what each run places.

    python -m recon_scripts.card_masks [--data DIR] [--out DIR] [--landmarks laboe,boerse-essen]
        [--features aliked] [--matcher auto]

Per landmark of postcards_cmahnke (DIR/<landmark>/images): reconstruct with ``cards.enabled``
False (each scan one photo, every keypoint kept) and True (keypoints only on the picture, collage
cards split into their panels, repeated prints mapped once). Each verified inlier keypoint is put
back in its card's pixels (a panel's keypoints shifted by the panel's corner) and counted as
"off the picture" when no picture box of the card's layout (cards.find_layout) holds it. Prints a
markdown table: photos mapped, registered, verified pairs, inlier keypoints, the share off the
picture.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from colmap_guided import cards
from colmap_guided import database as dbio
from colmap_guided.paths import shared_data_dir
from colmap_guided.reconstruct import reconstruct
from recon_scripts import script_parser
from recon_scripts.evaluation.tables import markdown_table


def off_picture(database_path: Path, layouts: dict, panels: dict) -> tuple:
    """(inlier keypoints, of them off every picture box of their card) over the verified pairs."""
    origin = {}  # database name -> (card name, x, y of its corner in the card)
    for card, names in panels.items():
        for name, box in zip(names, layouts[card].panels):
            origin[name] = (card, box[0], box[1])
    total = off = 0
    with dbio.open_database(database_path) as db:
        names = dbio.image_names(db)
        for (id_a, id_b), inliers in dbio.read_verified_inliers(db).items():
            for image_id, column in ((id_a, 0), (id_b, 1)):
                name = names[image_id]
                card, dx, dy = origin.get(name, (name, 0, 0))
                xy = dbio.read_keypoints(db, image_id)[np.unique(inliers[:, column]), :2]
                xy = xy + np.array([dx, dy], np.float32)
                layout = layouts.get(card)
                boxes = (layout.panels or [layout.picture]) if layout else None
                inside = (
                    np.any([cards.in_box(xy, box) for box in boxes], axis=0)
                    if boxes
                    else np.ones(len(xy), bool)
                )
                total += len(xy)
                off += int((~inside).sum())
    return total, off


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--data", type=Path, default=shared_data_dir() / "postcards_cmahnke")
    parser.add_argument("--out", type=Path, default=Path("card_masks_runs"))
    parser.add_argument("--landmarks", default=None, help="comma-separated (default: all)")
    parser.add_argument("--features", default="auto")
    parser.add_argument("--matcher", default="auto")
    args = parser.parse_args()
    landmarks = (
        args.landmarks.split(",")
        if args.landmarks
        else sorted(p.name for p in args.data.iterdir() if (p / "images").is_dir())
    )
    rows, results = [], {}
    for landmark in landmarks:
        image_path = args.data / landmark / "images"
        conf = cards.check_conf(None)
        layouts = cards.find_layouts(image_path, sorted(p.name for p in image_path.iterdir()), conf)
        for enabled in (False, True):
            out = args.out / f"{landmark}_cards_{'on' if enabled else 'off'}"
            result = reconstruct(
                args.data / landmark,
                output=out,
                matcher=args.matcher,
                feature_conf={"type": args.features, "cards": {"enabled": enabled}},
                overwrite=True,
            )
            panels = {
                card: [panel["name"] for panel in entry.get("panels", [])]
                for card, entry in (result.get("cards") or {}).items()
            }
            total, off = off_picture(Path(result["database_path"]), layouts, panels)
            key = f"{landmark} cards {'on' if enabled else 'off'}"
            results[key] = {
                "photos": result["num_images"],
                "registered": result["num_registered"],
                "verified_pairs": result["database"].get("num_verified_pairs"),
                "inlier_keypoints": total,
                "off_picture": off,
                "repeated_prints": sorted(result.get("repeated_prints") or {}),
            }
            rows.append(
                [
                    landmark,
                    "on" if enabled else "off",
                    result["num_images"],
                    result["num_registered"],
                    result["database"].get("num_verified_pairs"),
                    total,
                    off,
                    f"{100 * off / max(total, 1):.1f} %",
                ]
            )
            print(json.dumps({key: results[key]}), flush=True)
    header = [
        "landmark",
        "cards",
        "photos",
        "registered",
        "verified pairs",
        "inlier keypoints",
        "off the picture",
        "share",
    ]
    print(markdown_table(header, rows))


if __name__ == "__main__":
    main()
