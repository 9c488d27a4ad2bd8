"""Georeferencing on a real set with a reference model: the reference's camera centres placed on
the Earth (its own units taken as metres, or ``--scale`` metres each; its photos' up as the
vertical, a chosen origin and heading) are the truth; 3 of them (or ``--controls``) are the
controls, the other photos' position and heading errors are measured. The controls can be moved
as a map reading moves them: ``--noise`` (Gaussian) or ``--moved MIN MAX`` (each by a distance
between MIN and MAX metres, in a random direction: a standpoint guessed on a map), and given an
``--accuracy``.

    python -m recon_scripts.eval_georeference WORKSPACE \
        [--reference ../shared/data/lund_door_gtsfm/colmap_ground_truth] [--scale 1] \
        [--controls DSC_0001.JPG DSC_0006.JPG DSC_0012.JPG] [--noise METRES | --moved MIN MAX] \
        [--accuracy METRES] [--seed 0] [--off DSC_0009.JPG]

WORKSPACE: a `reconstruct` output of the set (georeferenced by this script: WORKSPACE/geo/).
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pycolmap

from colmap_guided import geoframe
from colmap_guided import georeference as geo
from colmap_guided.geometry import photo_up
from recon_scripts import script_parser
from recon_scripts.evaluation.tables import markdown_table


def truth_frame(
    reference: pycolmap.Reconstruction, origin, yaw_deg: float, scale: float = 1.0
) -> geoframe.GeoFrame:
    """The reference on the Earth: its photos' up as the vertical, turned by ``yaw_deg``, ``scale``
    metres per unit, its cameras' centroid at ``origin``."""
    images = [reference.images[i] for i in reference.reg_image_ids()]
    up = photo_up(im.cam_from_world().rotation.matrix() for im in images)
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ geo._level_rotation(up)
    centres = np.array([im.projection_center() for im in images])
    return geoframe.GeoFrame(tuple(origin), scale, R, -scale * R @ centres.mean(axis=0), True)


def _parser():
    """The command line."""
    parser = script_parser(__doc__)
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
    parser.add_argument("--off", default=None, help="also this photo as a control, 100 m east off")
    parser.add_argument(
        "--noise", type=float, default=0.0, help="metres (sigma) of map-reading error per control"
    )
    parser.add_argument(
        "--moved",
        type=float,
        nargs=2,
        default=None,
        metavar=("MIN", "MAX"),
        help="move each control by MIN to MAX metres (uniform) in a random direction",
    )
    parser.add_argument(
        "--accuracy",
        type=float,
        default=None,
        help="metres: the controls' accuracy column (default: none, the command's default)",
    )
    parser.add_argument(
        "--scale", type=float, default=1.0, help="metres per unit of the reference (its spread)"
    )
    parser.add_argument("--seed", type=int, default=0, help="of --noise and --moved")
    return parser


def geodetic(position: np.ndarray, origin) -> dict:
    """A control point's latitude, longitude, altitude at ``position`` (metres E, N, U)."""
    lat, lon, alt = geoframe.enu_to_geodetic(position, origin)
    return {"latitude": float(lat), "longitude": float(lon), "altitude": float(alt)}


def enu(cam: dict, origin) -> np.ndarray:
    """A camera's position in metres east, north, up of ``origin``."""
    return geoframe.geodetic_to_enu(cam["latitude"], cam["longitude"], cam["altitude"], origin)


def control_points(true_cams: dict, args, origin) -> dict:
    """The ``--controls`` at their true positions, moved by ``--noise`` or ``--moved``; ``--off``
    100 m east; each with ``--accuracy``."""
    controls = {n: true_cams[n] for n in args.controls}
    rng = np.random.default_rng(args.seed)
    for name in controls:  # horizontal error of a position read off a map
        shift = rng.normal(0, args.noise, 2) if args.noise else np.zeros(2)
        if args.moved:
            distance, turn = rng.uniform(*args.moved), rng.uniform(0, 2 * math.pi)
            shift = shift + distance * np.array([math.cos(turn), math.sin(turn)])
        controls[name] = geodetic(enu(controls[name], origin) + [*shift, 0], origin)
    if args.off:
        controls[args.off] = geodetic(enu(true_cams[args.off], origin) + [100, 0, 0], origin)
    return {n: {**c, "accuracy": args.accuracy} for n, c in controls.items()}


def georeference(workspace: Path, controls: dict) -> dict:
    """``georeference``'s output for the workspace fitted to ``controls`` (a temporary CSV)."""
    with tempfile.TemporaryDirectory() as tmp:
        control = Path(tmp) / "control.csv"
        control.write_text(
            "name,latitude,longitude,altitude,accuracy\n"
            + "".join(
                f"{n},{r['latitude']:.9f},{r['longitude']:.9f},{r['altitude']:.3f},"
                f"{'' if r['accuracy'] is None else r['accuracy']}\n"
                for n, r in controls.items()
            )
        )
        return geo.georeference(workspace, control)


def error_table(cameras: dict, controls: dict, true_cams: dict, origin) -> str:
    """Position and heading errors of the photos that are not controls, then median and max."""
    rows = []
    for name, cam in sorted(cameras.items()):
        if name in controls or name not in true_cams:
            continue
        d = enu(cam, origin) - enu(true_cams[name], origin)
        dh = (cam["heading"] - true_cams[name]["heading"] + 180) % 360 - 180
        rows.append((name, np.linalg.norm(d[:2]), d[2], np.linalg.norm(d), dh))
    cells = [
        [name, f"{h:.3f}", f"{v:+.3f}", f"{p:.3f}", f"{dh:+.2f}"] for name, h, v, p, dh in rows
    ]
    err = np.abs(np.array([r[1:] for r in rows]))  # horizontal and 3D: already >= 0
    for label, v in (("median", np.median(err, axis=0)), ("max", err.max(axis=0))):
        cells.append([label, *(f"{x:.3f}" for x in v[:3]), f"{v[3]:.2f}"])
    headers = ["photo", "horizontal (m)", "vertical (m)", "3D (m)", "heading (deg)"]
    return markdown_table(headers, cells)


def photo_up_angle(rec: pycolmap.Reconstruction) -> float:
    """Degrees between the model's photo up and its photos' mean image-up."""
    rotations = [rec.images[i].cam_from_world().rotation.matrix() for i in rec.reg_image_ids()]
    mean = -np.mean([R[1] for R in rotations], axis=0)
    return math.degrees(math.acos(photo_up(rotations) @ mean / np.linalg.norm(mean)))


def main(argv=None) -> None:
    args = _parser().parse_args(argv)
    reference = pycolmap.Reconstruction(str(args.reference))
    truth = truth_frame(reference, args.origin, args.yaw, args.scale)
    by_name = {reference.images[i].name: reference.images[i] for i in reference.reg_image_ids()}
    true_cams = {name: truth.camera(image.cam_from_world()) for name, image in by_name.items()}
    controls = control_points(true_cams, args, truth.origin)
    try:
        out = georeference(args.workspace, controls)
    except ValueError as err:  # no 3 controls agree: the command's message is the result
        print(f"Refused: {err}")
        return
    print(geo.summary_text(out))
    print("\n" + error_table(out["cameras"], controls, true_cams, truth.origin))
    extent = np.ptp(np.array([enu(c, truth.origin) for c in true_cams.values()]), axis=0)
    print(f"\nThe {len(true_cams)} reference cameras span {extent[0]:.1f} x {extent[1]:.1f} m.")
    # how far the photos' up (the vertical of the truth and of the fit) is from their mean image-up
    print(f"reference: photo_up is {photo_up_angle(reference):.1f} deg from the mean image-up")
    rec = pycolmap.Reconstruction(str(Path(args.workspace) / "sparse" / "0"))
    print(f"reconstruction: photo_up is {photo_up_angle(rec):.1f} deg from the mean image-up")


if __name__ == "__main__":
    main()
