"""After stage 5: place a reconstruct workspace's model on the Earth, and every photo's camera on a
map.

    python -m colmap_guided georeference WORKSPACE [--control control.csv] [--accuracy M]
        [--model N] [--image_path DIR]

"Where was this photo taken, looking where?" A few photos' positions, read off a map (a control
file, CSV with the header ``name,latitude,longitude[,altitude][,accuracy]``: WGS84 degrees,
altitude in metres above sea level, accuracy in metres, both optional) or from the photos' GPS EXIF
(its horizontal positioning error as the accuracy, where written), fix a similarity (scale,
rotation, translation) from the model to a local east-north-up (ENU) frame in metres, whose origin
is the controls' centroid. A control file's line wins over the GPS EXIF of the same photo.

Each control carries its accuracy (one sigma, metres; ``--accuracy`` for those without one, 1 m by
default): the similarity is a least-squares fit weighted by 1 / accuracy^2, so a standpoint guessed
on a map to 20 m counts for less than a surveyed one. The fit is robust: every pair of controls
proposes a fit, refitted on the controls it places within their tolerance (``max_error_ratio``
times their accuracy, at least ``max_error_share`` of the controls' spread: the model's own shape
error; horizontal distances, since map-read and GPS altitudes are coarse) until they stay the same;
the fit most controls agree with is kept, and a control that disagrees is named with its residual
and accuracy and left out. At least 3 controls must agree (2 always fit exactly: nothing would
check them); where no fit has 3, the refusal says which accuracy would have let 3 agree. The up
direction comes from the photos (``geometry.photo_up``: photos are taken upright) unless at least 4
agreeing controls, all with altitudes, not on one line and accurate enough to fix it better
(``max_up_error``), fix all 7 degrees of freedom. Without any altitude, the controls' cameras are
put at eye height above the ground (KML altitudeMode relativeToGround).

``--model N`` georeferences WORKSPACE/sparse/N (0, the largest, by default: the one the report and
``localize`` use). Written in WORKSPACE/geo/ for model 0, WORKSPACE/geo_N/ for another (recorded in
the workspace's marker; sparse/ is only read), all at once (geo.partial/ renamed once complete):

- ``georeference.json``: the model and its index, the transform (ENU = scale R x + t), the ENU
  origin, each control's residual in metres beside its accuracy and tolerance, whether it was
  used, the used controls' RMS, and the model's digest (a changed model: stale);
- ``cameras.kml``: KML 2.2, one PhotoOverlay per registered photo (Camera, ViewVolume, the photo);
- ``cameras.geojson``: per photo a Point [lon, lat, alt] (name, heading, tilt, roll, fov_deg, era)
  and its view cone, a Polygon (QGIS);
- ``points.ply``: the model's 3D points in the ENU frame, metres.

report.html is written again: a map in metres, north up, each photo's latitude and longitude.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import difflib
import json
import math
import os
import shutil
import sys
import xml.etree.ElementTree as ET
from itertools import combinations
from pathlib import Path

import numpy as np
import pycolmap

from .conf import add_conf_flags, conf_from_flags, merge_conf
from .geoframe import RESULT, GeoFrame, enu_to_geodetic, geo_folder, geodetic_to_enu
from .geometry import image_rays, photo_up
from .log import add_verbosity_flags, logger
from .workspace import Workspace, model_digest

KML_NS = "http://www.opengis.net/kml/2.2"

default_conf = {
    # metres (one sigma) of a control whose line or EXIF gives none: a surveyed point, 3 m tolerated
    "accuracy": 1.0,
    # a control farther from the others' fit than this many times its accuracy is left out
    "max_error_ratio": 3.0,
    # ... but never one nearer than this share of the controls' spread (the model's own error)
    "max_error_share": 0.1,
    # smallest/largest spread of the controls below this: on one line (the up from the photos)
    "collinear_ratio": 0.05,
    # degrees: the photos' up is about this good; controls fix the up only where theirs is better
    "max_up_error": 1.0,
    "eye_height": 1.6,  # metres above the ground of the controls' cameras when no altitude is given
    "max_pairs": 500,  # pairs of controls tried (a random subset beyond)
}


# --- controls -----------------------------------------------------------------------------------


@dataclasses.dataclass
class Control:
    """A photo whose camera position is known: its name in the model, WGS84 degrees, metres."""

    name: str
    latitude: float
    longitude: float
    altitude: float | None
    source: str  # "control.csv line 3" or "GPS EXIF"
    accuracy: float | None = None  # metres, one sigma; None: the ``accuracy`` option's


def _check_range(latitude: float, longitude: float, where: str) -> None:
    if not (-90 <= latitude <= 90 and -180 <= longitude <= 180) or not all(
        math.isfinite(v) for v in (latitude, longitude)
    ):
        raise ValueError(
            f"{where}: latitude {latitude} / longitude {longitude} is off the Earth; write "
            "decimal degrees, latitude in [-90, 90] then longitude in [-180, 180] (e.g. 55.7047, "
            "13.1910)."
        )


def read_controls(path: Path, names: list[str], model: str = "sparse/0") -> list[Control]:
    """The controls of a CSV file ``name,latitude,longitude[,altitude][,accuracy]`` (lines starting
    with # and empty lines skipped; an empty altitude or accuracy: none given); one-line ValueError
    naming the line for anything else, or a name that is not a registered photo of the model
    (``names``, of ``model``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"No control file at {path}: pass --control PATH/control.csv.")
    known = set(names)
    out: dict[str, Control] = {}
    with path.open(newline="", encoding="utf-8-sig") as f:
        rows = [
            (i, row)
            for i, row in enumerate(csv.reader(f), start=1)
            if row and "".join(row).strip() and not row[0].lstrip().startswith("#")
        ]
    header = [c.strip().lower() for c in rows[0][1]] if rows else []
    optional = ([], ["altitude"], ["accuracy"], ["altitude", "accuracy"])
    if header[:3] != ["name", "latitude", "longitude"] or header[3:] not in optional:
        raise ValueError(
            f"{path.name} line {rows[0][0] if rows else 1}: the header must be "
            "name,latitude,longitude, then altitude, accuracy or both (altitude,accuracy)."
        )
    for line, row in rows[1:]:
        where = f"{path.name} line {line}"
        cells = dict(zip(header, (c.strip() for c in row)))
        if len(row) != len(header):
            raise ValueError(
                f"{where}: {len(row)} fields, {len(header)} expected ({','.join(header)})."
            )
        try:
            latitude, longitude = float(cells["latitude"]), float(cells["longitude"])
            altitude, accuracy = (
                float(cells[k]) if cells.get(k) else None for k in ("altitude", "accuracy")
            )
        except ValueError:
            raise ValueError(
                f"{where}: {','.join(list(cells.values())[1:])!r} is not numbers; write decimal "
                "degrees (and metres), e.g. DSC_0001.JPG,55.7047,13.1910,62.0."
            ) from None
        _check_range(latitude, longitude, where)
        if accuracy is not None and not 0 < accuracy < math.inf:
            raise ValueError(
                f"{where}: accuracy {accuracy} is not a distance; write how many metres the "
                "position may be off (one sigma), e.g. 20 for a standpoint guessed on a map."
            )
        name = cells["name"]
        if name not in known:
            near = difflib.get_close_matches(name, sorted(known), n=1)
            raise ValueError(
                f"{where}: no registered photo named {name!r} in the model; use the names of "
                f"{model} (e.g. {(near or sorted(known) or ['?'])[0]!r})."
            )
        if name in out:
            raise ValueError(f"{where}: {name!r} is given twice ({out[name].source}).")
        out[name] = Control(name, latitude, longitude, altitude, where, accuracy)
    return list(out.values())


def _degrees(dms, ref) -> float:
    value = sum(float(v) / 60**i for i, v in enumerate(dms))
    return -value if str(ref).strip().upper() in ("S", "W") else value


def exif_control(path: Path, name: str) -> Control | None:
    """The GPS EXIF position of one photo, None where it has none (or the file cannot be read)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            gps = im.getexif().get_ifd(0x8825)  # GPSInfo
        if not {1, 2, 3, 4} <= set(gps):
            return None
        latitude, longitude = _degrees(gps[2], gps[1]), _degrees(gps[4], gps[3])
        altitude = float(gps[6]) if 6 in gps else None
        if altitude is not None and gps.get(5) in (1, b"\x01"):  # below sea level
            altitude = -altitude
        _check_range(latitude, longitude, "GPS EXIF")
        # GPSHPositioningError (EXIF 2.31), metres; a zero or missing one: none given
        accuracy = float(gps[31]) if gps.get(31) and float(gps[31]) > 0 else None
    except ValueError as err:
        logger.warning("%s: %s; not used as a control.", path.name, err)
        return None
    except Exception as err:  # noqa: BLE001 - a photo without readable EXIF is no control
        logger.debug("No GPS EXIF read from %s (%s).", path, err)
        return None
    return Control(name, latitude, longitude, altitude, "GPS EXIF", accuracy)


# --- the similarity -----------------------------------------------------------------------------


def _level_rotation(up: np.ndarray) -> np.ndarray:
    """A rotation taking ``up`` to +z."""
    up = up / np.linalg.norm(up)
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(up, a), up])


def fit_upright(
    model: np.ndarray,
    enu: np.ndarray,
    has_alt: np.ndarray,
    up: np.ndarray,
    eye_height: float,
    weights: np.ndarray | None = None,
) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) with ENU = s R x + t, R taking the model's ``up`` to ENU's up: the horizontal part
    a weighted least-squares 2D similarity (complex numbers: w = a z + b), the vertical offset from
    the controls with altitude (without any: their cameras at ``eye_height``); ``weights``: per
    control, 1 / accuracy^2 (None: all alike)."""
    weights = np.ones(len(model)) if weights is None else np.asarray(weights, float)
    level = np.asarray(model, float) @ _level_rotation(up).T
    z = level[:, 0] + 1j * level[:, 1]
    w = enu[:, 0] + 1j * enu[:, 1]
    z0, w0 = np.average(z, weights=weights), np.average(w, weights=weights)
    zc, wc = z - z0, w - w0
    a = np.vdot(weights * zc, wc) / max(np.sum(weights * np.abs(zc) ** 2), 1e-300)
    s, yaw = abs(a), np.angle(a)
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    b = w0 - a * z0
    if has_alt.any():
        tz = np.average(enu[has_alt, 2] - s * level[has_alt, 2], weights=weights[has_alt])
    else:
        tz = eye_height - s * np.average(level[:, 2], weights=weights)
    return float(s), rz @ _level_rotation(up), np.array([b.real, b.imag, tz])


def fit_similarity(
    model: np.ndarray, enu: np.ndarray, weights: np.ndarray | None = None
) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) with ENU = s R x + t in the weighted least-squares sense (Umeyama 1991, eq.
    40-42, each point's term weighted; ``weights`` None: all alike)."""
    weights = np.ones(len(model)) if weights is None else np.asarray(weights, float)
    weights = weights / weights.sum()
    mu_x, mu_y = weights @ model, weights @ enu
    xc, yc = model - mu_x, enu - mu_y
    U, d, Vt = np.linalg.svd((weights[:, None] * yc).T @ xc)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    s = float(np.trace(np.diag(d) @ S) / max(weights @ np.sum(xc**2, axis=1), 1e-300))
    return s, R, mu_y - s * R @ mu_x


def _spread(points: np.ndarray) -> np.ndarray:
    """The singular values of the centred points: their extent along each principal axis."""
    return np.linalg.svd(points - points.mean(axis=0), compute_uv=False)


def _collinear(points: np.ndarray, ratio: float) -> bool:
    spread = _spread(points)
    return len(points) < 3 or spread[1] < ratio * max(spread[0], 1e-12)


def _up_error(enu: np.ndarray, accuracy: np.ndarray) -> float:
    """About how many degrees controls of this ``accuracy`` (metres) tilt the up: their RMS
    accuracy over their horizontal extent across their long axis."""
    across = _spread(enu[:, :2])[1]
    return math.degrees(math.atan2(float(np.sqrt(np.mean(accuracy**2))), across))


def _origin(controls: list[Control]) -> tuple[float, float, float]:
    """The controls' centroid (their mean altitude; 0 without any)."""
    alts = [c.altitude for c in controls if c.altitude is not None]
    return (
        float(np.mean([c.latitude for c in controls])),
        float(np.mean([c.longitude for c in controls])),
        float(np.mean(alts)) if alts else 0.0,
    )


def _enu(controls: list[Control], origin) -> np.ndarray:
    alt = [origin[2] if c.altitude is None else c.altitude for c in controls]
    return geodetic_to_enu(
        [c.latitude for c in controls], [c.longitude for c in controls], alt, origin
    ).reshape(-1, 3)


def _check_fit_inputs(controls: list[Control], up: np.ndarray | None) -> None:
    """One-line ValueError for fewer than 3 controls or photos without a common up."""
    if len(controls) < 3:
        raise ValueError(
            f"{len(controls)} photo(s) with a known position; at least 3 (not all at one spot) "
            "are needed: add lines to the control file (name,latitude,longitude) or photos with "
            "GPS EXIF."
        )
    if up is None:
        raise ValueError(
            "The photos' up directions disagree (scans rotated by 90 degrees?); rotate them "
            "upright, reconstruct again, then georeference."
        )


def _control_pairs(count: int, max_pairs: int) -> list[tuple[int, int]]:
    """Every pair of controls, or a fixed random subset of ``max_pairs`` of them."""
    pairs = list(combinations(range(count), 2))
    if len(pairs) > max_pairs:
        rng = np.random.default_rng(0)
        pairs = [pairs[i] for i in rng.choice(len(pairs), max_pairs, replace=False)]
    return pairs


def _horizontal_residuals(frame, centres: np.ndarray, enu: np.ndarray) -> np.ndarray:
    """Horizontal distances (m) from each control to its camera placed by ``frame`` (s, R, t)."""
    s, R, t = frame
    return np.linalg.norm((s * centres @ R.T + t - enu)[:, :2], axis=1)


@dataclasses.dataclass
class _Controls:
    """The controls as the fit sees them: camera centres (model), ENU metres, which have an
    altitude, their accuracy (m) and tolerance (m)."""

    centres: np.ndarray
    enu: np.ndarray
    has_alt: np.ndarray
    accuracy: np.ndarray
    tolerance: np.ndarray

    def upright(self, used: np.ndarray, up: np.ndarray, conf: dict):
        """The upright fit of the ``used`` controls, weighted by 1 / accuracy^2."""
        return fit_upright(
            self.centres[used],
            self.enu[used],
            self.has_alt[used],
            up,
            conf["eye_height"],
            self.accuracy[used] ** -2.0,
        )

    def agreement(self, frame) -> tuple[np.ndarray, tuple[int, float]]:
        """(the controls within their tolerance of ``frame``, its rank: the most of them, then
        the least sum of their (residual / accuracy)^2; smaller is better)."""
        residuals = _horizontal_residuals(frame, self.centres, self.enu)
        used = residuals <= self.tolerance
        return used, (-int(used.sum()), float(np.sum((residuals / self.accuracy)[used] ** 2)))


def _best_fit(controls: _Controls, up: np.ndarray, conf: dict) -> tuple[tuple, np.ndarray, tuple]:
    """(the upright fit most controls agree with, those controls, the pair's fit nearest to 3
    agreeing: its residuals (m)): every pair's fit, refitted on the controls it places within
    their tolerance until they stay the same."""
    best, best_rank, best_used, nearest = None, (1, 0.0), None, np.full(3, np.inf)
    for pair in _control_pairs(len(controls.enu), conf["max_pairs"]):
        if np.linalg.norm(np.subtract(*controls.enu[list(pair), :2])) < 1e-3:
            continue
        used = np.isin(np.arange(len(controls.enu)), pair)
        frame = controls.upright(used, up, conf)
        residuals = _horizontal_residuals(frame, controls.centres, controls.enu)
        if np.sort(residuals)[2] < np.sort(nearest)[2]:
            nearest = residuals
        used, rank = controls.agreement(frame)
        for _ in range(10):  # more controls, each refit weighted: a few rounds settle
            if used.sum() < 3:
                break
            refit = controls.upright(used, up, conf)
            again, refit_rank = controls.agreement(refit)
            if refit_rank >= rank:
                break
            frame, used, rank = refit, again, refit_rank
        if rank < best_rank:
            best, best_rank, best_used = frame, rank, used
    if best is None:
        raise ValueError(
            "The controls are all at one spot; give at least 3 photos taken from places "
            "metres apart."
        )
    return best, best_used, nearest


def _account(controls: list[Control], data: _Controls, error: np.ndarray, used, full: bool):
    """The fit's account: up's source, each control's residuals beside its accuracy and
    tolerance, its use, the used controls' RMS."""
    rows = [
        {
            **{k: v for k, v in dataclasses.asdict(c).items() if k != "accuracy"},
            "residual_m": round(float(np.linalg.norm(e[:2])), 3),
            **({"vertical_residual_m": round(float(e[2]), 3)} if c.altitude is not None else {}),
            "accuracy_m": round(float(a), 3),
            "tolerance_m": round(float(tol), 3),
            "used": bool(u),
        }
        for c, e, a, tol, u in zip(controls, error, data.accuracy, data.tolerance, used)
    ]
    rms = float(np.sqrt(np.mean([c["residual_m"] ** 2 for c in rows if c["used"]])))
    return {"up_from": "controls" if full else "photos", "controls": rows, "rms_m": round(rms, 3)}


def fit(
    controls: list[Control], centres: np.ndarray, up: np.ndarray | None, conf: dict
) -> tuple[GeoFrame, dict]:
    """The GeoFrame of the controls (camera ``centres`` in model coordinates, same order), weighted
    by their accuracy and robust to controls that disagree; and the fit's account: each control's
    residuals beside its accuracy and tolerance, whether it was used, where the up came from."""
    _check_fit_inputs(controls, up)
    enu = _enu(controls, _origin(controls))
    accuracy = np.array([c.accuracy or conf["accuracy"] for c in controls], float)
    horizontal = enu[:, :2]
    spread = float(np.median(np.linalg.norm(horizontal - np.median(horizontal, 0), axis=1)))
    tolerance = np.maximum(conf["max_error_ratio"] * accuracy, conf["max_error_share"] * spread)
    has_alt = np.array([c.altitude is not None for c in controls])
    data = _Controls(np.asarray(centres, float), enu, has_alt, accuracy, tolerance)
    frame, used, nearest = _best_fit(data, up, conf)
    if used.sum() < 3:
        # the accuracy, rounded up to a decimetre, that would put a third control within tolerance
        needed = math.ceil(np.sort(nearest)[2] / conf["max_error_ratio"] * 10) / 10
        raise ValueError(
            f"Only {used.sum()} of the {len(controls)} controls agree within "
            f"{conf['max_error_ratio']:g} times their accuracy (residual / accuracy: "
            f"{_listing(controls, nearest, accuracy)}); 3 must, and would with an accuracy of "
            f"{needed:g} m (--accuracy {needed:g}, or an accuracy column): check their names and "
            "positions, give their accuracy, or add controls."
        )
    # the final fit in the used controls' own frame
    origin = _origin([c for c, u in zip(controls, used) if u])
    data.enu = enu = _enu(controls, origin)
    full = (
        bool(has_alt[used].all() and used.sum() >= 4)
        and not _collinear(enu[used], conf["collinear_ratio"])
        and _up_error(enu[used], accuracy[used]) <= conf["max_up_error"]
    )
    if full:
        s, R, t = fit_similarity(centres[used], enu[used], accuracy[used] ** -2.0)
    else:
        s, R, t = data.upright(used, up, conf)
    frame = GeoFrame(origin, s, R, t, bool(has_alt[used].any()))
    return frame, _account(controls, data, frame.to_enu(centres) - enu, used, full)


def _listing(controls: list[Control], residuals, accuracy) -> str:
    return ", ".join(
        f"{c.name} {r:.1f} m / {a:g} m" for c, r, a in zip(controls, residuals, accuracy)
    )


# --- outputs ------------------------------------------------------------------------------------


def view_volume(camera: pycolmap.Camera) -> dict:
    """KML ViewVolume angles (degrees) of a camera: the rays through the middle of each image edge
    (distortion included)."""
    w, h = camera.width, camera.height
    cx, cy = camera.principal_point_x, camera.principal_point_y
    rays = image_rays(camera, np.array([[0, cy], [w, cy], [cx, h], [cx, 0]], float))
    left, right = (math.degrees(math.atan(v)) for v in rays[:2, 0])
    bottom, top = (-math.degrees(math.atan(v)) for v in rays[2:, 1])  # image y points down
    return {
        "leftFov": round(left, 3),
        "rightFov": round(right, 3),
        "bottomFov": round(bottom, 3),
        "topFov": round(top, 3),
    }


def _depth(rec: pycolmap.Reconstruction, image: pycolmap.Image) -> float | None:
    """Median distance (model units) from the camera to the 3D points the photo sees."""
    xyz = [rec.points3D[p.point3D_id].xyz for p in image.points2D if p.has_point3D()]
    if not xyz:
        return None
    return float(np.median(np.linalg.norm(np.array(xyz) - image.projection_center(), axis=1)))


def cameras_table(
    rec: pycolmap.Reconstruction, frame: GeoFrame, image_path: Path, eras: dict[str, str]
) -> list[dict]:
    """Per registered photo (by name): its file, camera on the Earth, view volume and the median
    distance of what it sees (m)."""
    out = []
    for image_id in sorted(rec.reg_image_ids(), key=lambda i: rec.images[i].name):
        image = rec.images[image_id]
        volume = view_volume(rec.cameras[image.camera_id])
        depth = _depth(rec, image)
        out.append(
            {
                "name": image.name,
                "photo": (Path(image_path) / image.name).resolve().as_uri(),
                **frame.camera(image.cam_from_world()),
                "fov_deg": round(volume["rightFov"] - volume["leftFov"], 3),
                "view_volume": volume,
                "depth_m": round(depth * frame.scale, 3) if depth else None,
                **({"era": eras[image.name]} if image.name in eras else {}),
            }
        )
    return out


def _destination(lat: float, lon: float, heading: float, distance: float) -> tuple[float, float]:
    """(lon, lat) ``distance`` metres from a point towards ``heading`` (ENU at the point)."""
    east = distance * math.sin(math.radians(heading))
    north = distance * math.cos(math.radians(heading))
    la, lo, _ = enu_to_geodetic([east, north, 0.0], (lat, lon, 0.0))
    return float(lo), float(la)


def geojson(cameras: list[dict], mode: str, cone_m: float) -> dict:
    """A FeatureCollection (RFC 7946: [lon, lat, alt], rings counter-clockwise): per photo its
    camera Point and its view cone Polygon (``depth_m`` long, else ``cone_m``)."""
    features = []
    for cam in cameras:
        props = {
            k: cam[k]
            for k in ("name", "heading", "tilt", "roll", "fov_deg", "era", "altitude")
            if k in cam
        }
        props.update(altitude_mode=mode, photo=cam["photo"])
        point = [cam["longitude"], cam["latitude"], cam["altitude"]]
        features.append(
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": point},
                "properties": {**props, "kind": "camera"},
            }
        )
        length = cam["depth_m"] or cone_m
        half = cam["fov_deg"] / 2
        apex = [cam["longitude"], cam["latitude"]]
        right = _destination(cam["latitude"], cam["longitude"], cam["heading"] + half, length)
        left = _destination(cam["latitude"], cam["longitude"], cam["heading"] - half, length)
        ring = [apex, list(right), list(left), apex]  # apex, right, left: counter-clockwise
        features.append(
            {
                "type": "Feature",
                "geometry": {
                    "type": "Polygon",
                    "coordinates": [[[round(v, 8) for v in p] for p in ring]],
                },
                "properties": {"name": cam["name"], "kind": "view cone", "length_m": length},
            }
        )
    return {"type": "FeatureCollection", "features": features}


def kml(cameras: list[dict], mode: str, title: str, near: float) -> bytes:
    """KML 2.2: one PhotoOverlay per photo, the photo at ``depth_m`` (else ``near``) in front of
    its Camera."""
    ET.register_namespace("", KML_NS)

    def sub(parent, tag, text=None):
        el = ET.SubElement(parent, f"{{{KML_NS}}}{tag}")
        if text is not None:
            el.text = str(text)
        return el

    root = ET.Element(f"{{{KML_NS}}}kml")
    doc = sub(root, "Document")
    sub(doc, "name", title)
    for cam in cameras:
        overlay = sub(doc, "PhotoOverlay")
        sub(overlay, "name", cam["name"])
        camera = sub(overlay, "Camera")
        for key in ("longitude", "latitude", "altitude", "heading", "tilt", "roll"):
            sub(camera, key, cam[key])
        sub(camera, "altitudeMode", mode)
        sub(sub(overlay, "Icon"), "href", cam["photo"])
        volume = sub(overlay, "ViewVolume")
        for key, value in cam["view_volume"].items():
            sub(volume, key, value)
        sub(volume, "near", cam["depth_m"] or near)
        point = sub(overlay, "Point")
        sub(point, "altitudeMode", mode)
        sub(point, "coordinates", f"{cam['longitude']},{cam['latitude']},{cam['altitude']}")
        sub(overlay, "shape", "rectangle")
    ET.indent(root)
    return ET.tostring(root, encoding="utf-8", xml_declaration=True)


def georeference(
    workspace: Path,
    control: Path | None = None,
    image_path: Path | None = None,
    conf: dict | None = None,
    model: int = 0,
) -> dict:
    """Georeference model ``model`` of a ``reconstruct`` workspace (WORKSPACE/sparse/N) from a
    control file and the photos' GPS EXIF; writes WORKSPACE/geo/ (geo_N/) and report.html again.
    Returns georeference.json's content."""
    from .localize import open_workspace
    from .report import read_manifest

    conf = merge_conf(default_conf, conf, "georeference")
    if not 0 < conf["accuracy"] < math.inf:
        raise ValueError(
            f"--accuracy {conf['accuracy']} is not a distance; give the metres a control may be "
            "off (one sigma), e.g. --accuracy 20 for standpoints guessed on a map."
        )
    path, report, model_dir = open_workspace(workspace, model)
    folder = geo_folder(model)
    image_path = Path(image_path or report["image_path"]).resolve()
    rec = pycolmap.Reconstruction(str(model_dir))
    images = {rec.images[i].name: rec.images[i] for i in rec.reg_image_ids()}
    label = f"sparse/{model}"
    given = read_controls(control, list(images), label) if control is not None else []
    from_file = {c.name for c in given}
    gps = [
        c
        for name in sorted(set(images) - from_file)
        if (c := exif_control(image_path / name, name)) is not None
    ]
    controls = given + gps
    up = photo_up(im.cam_from_world().rotation.matrix() for im in images.values())
    centres = np.array([images[c.name].projection_center() for c in controls]).reshape(-1, 3)
    frame, account = fit(controls, centres, up, conf)
    for c in account["controls"]:
        if not c["used"]:
            logger.warning(
                "Left out control %s (%s): %.1f m from where the others place it (accuracy "
                "%g m: more than %.1f m).",
                c["name"],
                c["source"],
                c["residual_m"],
                c["accuracy_m"],
                c["tolerance_m"],
            )
    eras = read_manifest(Path(report["manifest_path"])) if report.get("manifest_path") else {}
    cameras = cameras_table(rec, frame, image_path, eras)
    mode = "absolute" if frame.absolute_altitude else "relativeToGround"
    result = {
        "written_by": "colmap_guided georeference",
        "model": str(model_dir),
        "model_index": model,
        "model_sha256": model_digest(model_dir),
        **frame.to_json(),
        **account,
        "num_controls": {"control file": len(given), "GPS EXIF": len(gps)},
        "cameras": {
            c["name"]: {
                k: c[k] for k in ("latitude", "longitude", "altitude", "heading", "tilt", "roll")
            }
            for c in cameras
        },
    }
    ws = Workspace.claim(path, "reconstruct", keep=(image_path,))
    for name in (folder, f"{folder}.partial", f"{folder}.old"):
        ws.take(name)  # a geo/ folder of the user's own is refused, not replaced
    partial = ws.path / f"{folder}.partial"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    # for a photo that sees no 3D point: the others' median distance
    depth = float(np.median([c["depth_m"] for c in cameras if c["depth_m"]] or [10.0]))
    (partial / "cameras.geojson").write_text(
        json.dumps(geojson(cameras, mode, depth), indent=1) + "\n", encoding="utf-8"
    )
    (partial / "cameras.kml").write_bytes(kml(cameras, mode, report.get("scene", ""), depth))
    enu_points = pycolmap.Reconstruction(rec)
    enu_points.transform(frame.sim3d())
    enu_points.export_PLY(str(partial / "points.ply"))
    (partial / RESULT).write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    _swap(ws.path / folder, partial)
    result["geo_path"] = str(ws.path / folder)
    if ws.owns("report.html"):
        from .html_report import rewrite_report

        try:
            rewrite_report(ws.path)
        except Exception as err:  # noqa: BLE001 - geo/ is complete; a failed page must not hide it
            logger.warning("Could not write the HTML report again (%s); geo/ is complete.", err)
    return result


def _swap(current: Path, partial: Path) -> None:
    """geo.partial/ becomes geo/ (the old one removed once replaced)."""
    old = current.with_name(f"{current.name}.old")
    shutil.rmtree(old, ignore_errors=True)
    if current.exists():
        os.replace(current, old)
    os.replace(partial, current)
    shutil.rmtree(old, ignore_errors=True)


def summary_text(out: dict, listed: int = 12) -> str:
    """The command's summary: the fit, each control's residual beside its accuracy (the first
    ``listed`` used ones; every left-out one), where the files are."""
    used = [c for c in out["controls"] if c["used"]]
    counts = ", ".join(f"{k}: {v}" for k, v in out["num_controls"].items())
    model = f"model {out['model_index']} " if out.get("model_index") else ""
    lines = [
        f"Georeferenced {model}with {len(used)} of {len(out['controls'])} controls ({counts}); "
        f"residual {out['rms_m']:.2f} m RMS; up from the {out['up_from']}; "
        f"scale {out['enu_from_model']['scale']:.4g} m per model unit.",
    ]
    lines += [
        f"  {c['name']} ({c['source']}): {c['residual_m']:.1f} m, accuracy {c['accuracy_m']:g} m"
        for c in used[:listed]
    ]
    if len(used) > listed:
        lines.append(f"  and {len(used) - listed} more in georeference.json")
    lines += [
        f"Left out: {c['name']} ({c['source']}), {c['residual_m']:.1f} m off, accuracy "
        f"{c['accuracy_m']:g} m"
        for c in out["controls"]
        if not c["used"]
    ]
    o = out["origin"]
    lines.append(
        f"{len(out['cameras'])} photos placed; ENU origin {o['latitude']:.6f}, "
        f"{o['longitude']:.6f}. Google Earth: {out['geo_path']}/cameras.kml   QGIS: "
        f"{out['geo_path']}/cameras.geojson   points: {out['geo_path']}/points.ply"
    )
    return "\n".join(lines)


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "georeference",
        help="place the model on the Earth from a few photos' map positions or GPS EXIF: "
        "each photo's camera as KML PhotoOverlays and GeoJSON",
    )
    parser.add_argument(
        "workspace", type=Path, help="the --output folder of a reconstruct run (holds sparse/0)"
    )
    parser.add_argument(
        "--control",
        type=Path,
        default=None,
        help="CSV with the header name,latitude,longitude[,altitude][,accuracy]: where a few "
        "photos were taken (WGS84 degrees, metres above sea level, metres the position may be "
        "off); added to the photos' GPS EXIF",
    )
    add_conf_flags(parser, sys.modules[__name__], ["accuracy"], what="georeference")
    parser.add_argument(
        "--model",
        type=int,
        default=0,
        help="which model of WORKSPACE/sparse/N to georeference (default: 0, the largest); "
        "another than 0 is written in WORKSPACE/geo_N/",
    )
    parser.add_argument(
        "--image_path",
        type=Path,
        default=None,
        help="the photos' folder, if moved since reconstruct (only read)",
    )
    add_verbosity_flags(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    conf = conf_from_flags(args, sys.modules[__name__], ["accuracy"], "georeference")
    out = georeference(args.workspace, args.control, args.image_path, conf, args.model)
    print(summary_text(out))
