"""Georeferencing from a few controls: other photos' position and heading errors vs a reference.

    python -m colmap_guided reconstruct ../shared/data/lund_door_gtsfm --output WORKSPACE
    python -m recon_scripts georeference sets=WORKSPACE \\
        [reference=../shared/data/lund_door_gtsfm/colmap_ground_truth] [scale=1] \\
        [controls="DSC_0001.JPG DSC_0006.JPG DSC_0012.JPG"] [noise=METRES | moved="MIN MAX"] \\
        [accuracy=METRES] [seeds="0 1 2"] [off=DSC_0009.JPG]

Sets: ``reconstruct`` outputs of the reference's photos (each georeferenced: WORKSPACE/geo/). The
reference's camera centres placed on the Earth (its own units taken as metres, or ``scale`` metres
each; its photos' up as the vertical, turned by ``yaw`` degrees, centred at ``origin``: lat lon alt)
are the truth; 3 of them (or ``controls``) are the controls, the other photos' position and
heading errors are measured. The controls can be moved as a map reading moves them: ``noise``
(Gaussian, metres sigma) or ``moved`` (each by a distance between MIN and MAX metres, in a random
direction: a standpoint guessed on a map), one run per seed, and given an ``accuracy`` (metres;
none: the command's default). ``off``: also this photo as a control, 100 m east off.
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
from recon_scripts.bench import Benchmark
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


def geodetic(position: np.ndarray, origin) -> dict:
    """A control point's latitude, longitude, altitude at ``position`` (metres E, N, U)."""
    lat, lon, alt = geoframe.enu_to_geodetic(position, origin)
    return {"latitude": float(lat), "longitude": float(lon), "altitude": float(alt)}


def enu(cam: dict, origin) -> np.ndarray:
    """A camera's position in metres east, north, up of ``origin``."""
    return geoframe.geodetic_to_enu(cam["latitude"], cam["longitude"], cam["altitude"], origin)


def control_points(true_cams: dict, config: dict, origin) -> dict:
    """The ``controls`` at their true positions, moved by ``noise`` or ``moved`` (drawn with
    ``seed``); ``off`` 100 m east; each with ``accuracy``."""
    controls = {n: true_cams[n] for n in config["controls"]}
    rng = np.random.default_rng(config["seed"])
    for name in controls:  # horizontal error of a position read off a map
        shift = rng.normal(0, config["noise"], 2) if config["noise"] else np.zeros(2)
        if config["moved"]:
            distance, turn = rng.uniform(*config["moved"]), rng.uniform(0, 2 * math.pi)
            shift = shift + distance * np.array([math.cos(turn), math.sin(turn)])
        controls[name] = geodetic(enu(controls[name], origin) + [*shift, 0], origin)
    if config["off"]:
        controls[config["off"]] = geodetic(
            enu(true_cams[config["off"]], origin) + [100, 0, 0], origin
        )
    return {n: {**c, "accuracy": config["accuracy"]} for n, c in controls.items()}


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


def errors(cameras: dict, controls: dict, true_cams: dict, origin) -> list[list]:
    """Per photo that is not a control: [name, horizontal, vertical, 3D (m), heading (deg)]."""
    rows = []
    for name, cam in sorted(cameras.items()):
        if name in controls or name not in true_cams:
            continue
        d = enu(cam, origin) - enu(true_cams[name], origin)
        dh = (cam["heading"] - true_cams[name]["heading"] + 180) % 360 - 180
        rows.append([name, *map(float, (np.linalg.norm(d[:2]), d[2], np.linalg.norm(d), dh))])
    return rows


def error_table(rows: list[list]) -> str:
    """The ``errors`` of each photo, then median and max."""
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


class GeoreferenceBenchmark(Benchmark):
    name = "georeference"
    default_conf = {
        "sets": ["outputs/geo_lund"],  # reconstruct outputs of the reference's photos
        "reference": "../shared/data/lund_door_gtsfm/colmap_ground_truth",
        "controls": ["DSC_0001.JPG", "DSC_0006.JPG", "DSC_0012.JPG"],
        "origin": [55.7047, 13.1934, 70.0],  # lat lon alt
        "yaw": 30.0,  # the reference's turn, degrees
        "off": None,  # also this photo as a control, 100 m east off
        "noise": 0.0,  # metres (sigma) of map-reading error per control
        "moved": [],  # MIN MAX: each control moved by MIN to MAX metres in a random direction
        "accuracy": None,  # metres: the controls' accuracy column (none: the command's default)
        "scale": 1.0,  # metres per unit of the reference (its spread)
        "seeds": [0],  # of noise and moved
    }

    def configs(self):
        options = {
            k: v for k, v in self.conf.items() if k not in ("sets", "seeds", "work", "output")
        }
        return {f"seed {s}": {**options, "seed": s} for s in self.conf["seeds"]}

    def images(self, name, work):
        """The workspace, what each run georeferences."""
        return Path(name)

    def run_config(self, name, image_path, prepared, label, config, out):
        reference = pycolmap.Reconstruction(str(config["reference"]))
        truth = truth_frame(reference, config["origin"], config["yaw"], config["scale"])
        by_name = {reference.images[i].name: reference.images[i] for i in reference.reg_image_ids()}
        true_cams = {name: truth.camera(image.cam_from_world()) for name, image in by_name.items()}
        controls = control_points(true_cams, config, truth.origin)
        try:
            result = georeference(image_path, controls)
        except ValueError as err:  # no 3 controls agree: the command's message is the result
            return {"refused": str(err)}
        extent = np.ptp(np.array([enu(c, truth.origin) for c in true_cams.values()]), axis=0)
        rec = pycolmap.Reconstruction(str(image_path / "sparse" / "0"))
        return {
            "summary": geo.summary_text(result),
            "errors": errors(result["cameras"], controls, true_cams, truth.origin),
            "cameras": len(true_cams),
            "extent": extent.tolist(),
            # how far the photos' up (the vertical of the truth and of the fit) is from their
            # mean image-up
            "photo_up": {
                "reference": photo_up_angle(reference),
                "reconstruction": photo_up_angle(rec),
            },
        }

    def progress(self, results, name, label):
        r = results[name][label]
        return f"{name}, {label}: " + (
            "refused" if "refused" in r else f"{len(r['errors'])} photos"
        )

    def summarize(self, results):
        return "\n\n".join(
            f"### {name}, {label}\n\n{report(r)}"
            for name, by_seed in results.items()
            for label, r in by_seed.items()
        )


def report(r: dict) -> str:
    """One run: the command's summary, the error table, the cameras' span, the photo up."""
    if "refused" in r:
        return f"Refused: {r['refused']}"
    extent, up = r["extent"], r["photo_up"]
    return (
        f"{r['summary']}\n\n{error_table(r['errors'])}\n\n"
        f"The {r['cameras']} reference cameras span {extent[0]:.1f} x {extent[1]:.1f} m.\n"
        f"reference: photo_up is {up['reference']:.1f} deg from the mean image-up\n"
        f"reconstruction: photo_up is {up['reconstruction']:.1f} deg from the mean image-up"
    )
