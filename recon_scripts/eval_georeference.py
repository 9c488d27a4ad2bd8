"""Georeferencing on a real set with a reference model: the reference's camera centres placed on
the Earth (its own units taken as metres, its photos' up as the vertical, a chosen origin and
heading) are the truth; 3 of them are the controls, the other photos' position and heading errors
are measured.

    python recon_scripts/eval_georeference.py WORKSPACE \
        [--reference ../shared/data/lund_door_gtsfm/colmap_ground_truth] \
        [--controls DSC_0001.JPG DSC_0006.JPG DSC_0012.JPG]

WORKSPACE: a `reconstruct` output of the set (georeferenced by this script: WORKSPACE/geo/).
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import numpy as np
import pycolmap

from colmap_guided import georeference as geo
from colmap_guided.geometry import photo_up


def truth_frame(reference: pycolmap.Reconstruction, origin, yaw_deg: float) -> geo.GeoFrame:
    """The reference on the Earth: its photos' up as the vertical, turned by ``yaw_deg``, scale 1,
    its cameras' centroid at ``origin``."""
    images = [reference.images[i] for i in reference.reg_image_ids()]
    up = photo_up(im.cam_from_world().rotation.matrix() for im in images)
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ geo._level_rotation(up)
    centres = np.array([im.projection_center() for im in images])
    return geo.GeoFrame(tuple(origin), 1.0, R, -R @ centres.mean(axis=0), True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument(
        "--reference",
        type=Path,
        default=Path("../shared/data/lund_door_gtsfm/colmap_ground_truth"),
    )
    parser.add_argument(
        "--controls", nargs="+", default=["DSC_0001.JPG", "DSC_0006.JPG", "DSC_0012.JPG"]
    )
    parser.add_argument(
        "--origin", type=float, nargs=3, default=[55.7047, 13.1934, 70.0], help="lat lon alt"
    )
    parser.add_argument("--yaw", type=float, default=30.0, help="the reference's turn, degrees")
    args = parser.parse_args(argv)
    reference = pycolmap.Reconstruction(str(args.reference))
    truth = truth_frame(reference, args.origin, args.yaw)
    by_name = {reference.images[i].name: reference.images[i] for i in reference.reg_image_ids()}
    true_cams = {name: truth.camera(image.cam_from_world()) for name, image in by_name.items()}
    with tempfile.TemporaryDirectory() as tmp:
        control = Path(tmp) / "control.csv"
        control.write_text(
            "name,latitude,longitude,altitude\n"
            + "".join(
                f"{n},{true_cams[n]['latitude']},{true_cams[n]['longitude']},"
                f"{true_cams[n]['altitude']}\n"
                for n in args.controls
            )
        )
        out = geo.georeference(args.workspace, control)
    print(geo.summary_text(out))

    def enu(cam):
        return geo.geodetic_to_enu(cam["latitude"], cam["longitude"], cam["altitude"], truth.origin)

    rows = []
    for name, cam in sorted(out["cameras"].items()):
        if name in args.controls or name not in true_cams:
            continue
        d = enu(cam) - enu(true_cams[name])
        dh = (cam["heading"] - true_cams[name]["heading"] + 180) % 360 - 180
        rows.append((name, np.linalg.norm(d[:2]), d[2], np.linalg.norm(d), dh))
    print("\n| photo | horizontal (m) | vertical (m) | 3D (m) | heading (deg) |")
    print("|---|---|---|---|---|")
    for name, h, v, p, dh in rows:
        print(f"| {name} | {h:.3f} | {v:+.3f} | {p:.3f} | {dh:+.2f} |")
    err = np.array([r[1:] for r in rows])
    print(
        f"| median | {np.median(err[:, 0]):.3f} | {np.median(np.abs(err[:, 1])):.3f} | "
        f"{np.median(err[:, 2]):.3f} | {np.median(np.abs(err[:, 3])):.2f} |"
    )
    print(
        f"| max | {err[:, 0].max():.3f} | {np.abs(err[:, 1]).max():.3f} | {err[:, 2].max():.3f} "
        f"| {np.abs(err[:, 3]).max():.2f} |"
    )
    extent = np.ptp(np.array([enu(c) for c in true_cams.values()]), axis=0)
    print(f"\nThe {len(true_cams)} reference cameras span {extent[0]:.1f} x {extent[1]:.1f} m.")


if __name__ == "__main__":
    main()
