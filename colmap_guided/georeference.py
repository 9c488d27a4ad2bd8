"""After stage 5: place a reconstruct workspace's model on the Earth, and every photo's camera on a
map.

    python -m colmap_guided georeference WORKSPACE [--control control.csv] [--image_path DIR]

"Where was this photo taken, looking where?" A few photos' positions, read off a map (a control
file, CSV with the header ``name,latitude,longitude[,altitude]``: WGS84 degrees, altitude in metres
above sea level, optional) or from the photos' GPS EXIF, fix a similarity (scale, rotation,
translation) from the model to a local east-north-up (ENU) frame in metres, whose origin is the
controls' centroid. A control file's line wins over the GPS EXIF of the same photo.

The fit is robust: every pair of controls proposes a fit, the one most controls agree with (within
``max_error``: a share of the controls' spread, at least ``min_max_error`` metres; horizontal
distances, since map-read and GPS altitudes are coarse) is refitted on them, and a control that
disagrees is named with its residual and left out. At least 3 controls must agree (2 always fit
exactly: nothing would check them). The up direction comes from the photos (``geometry.photo_up``:
photos are taken upright) unless at least 4 agreeing controls, all with altitudes and not on one
line, fix all 7 degrees of freedom. Without any altitude, the controls' cameras are put at eye
height above the ground (KML altitudeMode relativeToGround).

Written in WORKSPACE/geo/ (recorded in the workspace's marker; sparse/ is only read), all at once
(geo.partial/ renamed once complete):

- ``georeference.json``: the transform (ENU = scale R x + t), the ENU origin, each control's
  residual in metres and whether it was used, and the model's digest (a changed model: stale);
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
import xml.etree.ElementTree as ET
from itertools import combinations
from pathlib import Path

import numpy as np
import pycolmap

from .conf import merge_conf
from .geoframe import GEO, RESULT, GeoFrame, enu_to_geodetic, geodetic_to_enu
from .geometry import image_rays, photo_up
from .log import add_verbosity_flags, logger
from .workspace import Workspace, model_digest

WRITES = (GEO, f"{GEO}.partial", f"{GEO}.old")
KML_NS = "http://www.opengis.net/kml/2.2"

default_conf = {
    # a control farther from the others' fit than this share of the controls' spread is left out
    "max_error_share": 0.1,
    "min_max_error": 3.0,  # metres: the least such threshold (map reading, GPS noise)
    # smallest/largest spread of the controls below this: on one line (the up from the photos)
    "collinear_ratio": 0.05,
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


def _check_range(latitude: float, longitude: float, where: str) -> None:
    if not (-90 <= latitude <= 90 and -180 <= longitude <= 180) or not all(
        math.isfinite(v) for v in (latitude, longitude)
    ):
        raise ValueError(
            f"{where}: latitude {latitude} / longitude {longitude} is off the Earth; write "
            "decimal degrees, latitude in [-90, 90] then longitude in [-180, 180] (e.g. 55.7047, "
            "13.1910)."
        )


def read_controls(path: Path, names: list[str]) -> list[Control]:
    """The controls of a CSV file ``name,latitude,longitude[,altitude]`` (lines starting with # and
    empty lines skipped); one-line ValueError naming the line for anything else, or a name that is
    not a registered photo of the model (``names``)."""
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
    if header[:3] != ["name", "latitude", "longitude"] or header[3:] not in ([], ["altitude"]):
        raise ValueError(
            f"{path.name} line {rows[0][0] if rows else 1}: the header must be "
            "name,latitude,longitude or name,latitude,longitude,altitude."
        )
    for line, row in rows[1:]:
        where = f"{path.name} line {line}"
        cells = [c.strip() for c in row]
        if len(cells) != len(header):
            raise ValueError(
                f"{where}: {len(cells)} fields, {len(header)} expected ({','.join(header)})."
            )
        try:
            latitude, longitude = float(cells[1]), float(cells[2])
            altitude = float(cells[3]) if len(cells) > 3 and cells[3] else None
        except ValueError:
            raise ValueError(
                f"{where}: {','.join(cells[1:])!r} is not numbers; write decimal degrees "
                "(and metres), e.g. DSC_0001.JPG,55.7047,13.1910,62.0."
            ) from None
        _check_range(latitude, longitude, where)
        name = cells[0]
        if name not in known:
            near = difflib.get_close_matches(name, sorted(known), n=1)
            raise ValueError(
                f"{where}: no registered photo named {name!r} in the model; use the names of "
                f"sparse/0 (e.g. {(near or sorted(known) or ['?'])[0]!r})."
            )
        if name in out:
            raise ValueError(f"{where}: {name!r} is given twice ({out[name].source}).")
        out[name] = Control(name, latitude, longitude, altitude, where)
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
    except ValueError as err:
        logger.warning("%s: %s; not used as a control.", path.name, err)
        return None
    except Exception as err:  # noqa: BLE001 - a photo without readable EXIF is no control
        logger.debug("No GPS EXIF read from %s (%s).", path, err)
        return None
    return Control(name, latitude, longitude, altitude, "GPS EXIF")


# --- the similarity -----------------------------------------------------------------------------


def _level_rotation(up: np.ndarray) -> np.ndarray:
    """A rotation taking ``up`` to +z."""
    up = up / np.linalg.norm(up)
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(up, a), up])


def fit_upright(
    model: np.ndarray, enu: np.ndarray, has_alt: np.ndarray, up: np.ndarray, eye_height: float
) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) with ENU = s R x + t, R taking the model's ``up`` to ENU's up: the horizontal part
    a least-squares 2D similarity (complex numbers: w = a z + b), the vertical offset from the
    controls with altitude (without any: their cameras at ``eye_height``)."""
    level = np.asarray(model, float) @ _level_rotation(up).T
    z = level[:, 0] + 1j * level[:, 1]
    w = enu[:, 0] + 1j * enu[:, 1]
    zc, wc = z - z.mean(), w - w.mean()
    a = np.vdot(zc, wc) / max(np.vdot(zc, zc).real, 1e-300)
    s, yaw = abs(a), np.angle(a)
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    b = w.mean() - a * z.mean()
    heights = enu[has_alt, 2] - s * level[has_alt, 2] if has_alt.any() else None
    tz = heights.mean() if heights is not None else eye_height - s * level[:, 2].mean()
    return float(s), rz @ _level_rotation(up), np.array([b.real, b.imag, tz])


def fit_similarity(model: np.ndarray, enu: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) with ENU = s R x + t in the least-squares sense (Umeyama 1991, eq. 40-42)."""
    mu_x, mu_y = model.mean(axis=0), enu.mean(axis=0)
    xc, yc = model - mu_x, enu - mu_y
    U, d, Vt = np.linalg.svd(yc.T @ xc / len(model))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    s = float(np.trace(np.diag(d) @ S) / max(np.mean(np.sum(xc**2, axis=1)), 1e-300))
    return s, R, mu_y - s * R @ mu_x


def _collinear(points: np.ndarray, ratio: float) -> bool:
    spread = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return len(points) < 3 or spread[1] < ratio * max(spread[0], 1e-12)


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


def _best_pair_fit(centres, enu, has_alt, up, conf: dict, threshold: float):
    """The upright fit through a pair of controls that most controls agree with (MSAC)."""
    best, best_score = None, np.inf
    for i, j in _control_pairs(len(enu), conf["max_pairs"]):
        if np.linalg.norm(enu[i, :2] - enu[j, :2]) < 1e-3:
            continue
        sample = np.array([i, j])
        guess = fit_upright(centres[sample], enu[sample], has_alt[sample], up, conf["eye_height"])
        score = np.minimum(_horizontal_residuals(guess, centres, enu), threshold).sum()
        if score < best_score:
            best, best_score = guess, score
    if best is None:
        raise ValueError(
            "The controls are all at one spot; give at least 3 photos taken from places "
            "metres apart."
        )
    return best


def _account(controls: list[Control], error: np.ndarray, used, threshold: float, full: bool):
    """The fit's account: threshold, up's source, each control's residuals and use, their RMS."""
    rows = [
        {
            **dataclasses.asdict(c),
            "residual_m": round(float(np.linalg.norm(e[:2])), 3),
            **({"vertical_residual_m": round(float(e[2]), 3)} if c.altitude is not None else {}),
            "used": bool(u),
        }
        for c, e, u in zip(controls, error, used)
    ]
    rms = float(np.sqrt(np.mean([c["residual_m"] ** 2 for c in rows if c["used"]])))
    return {
        "threshold_m": round(threshold, 3),
        "up_from": "controls" if full else "photos",
        "controls": rows,
        "rms_m": round(rms, 3),
    }


def fit(
    controls: list[Control], centres: np.ndarray, up: np.ndarray | None, conf: dict
) -> tuple[GeoFrame, dict]:
    """The GeoFrame of the controls (camera ``centres`` in model coordinates, same order), robust
    to controls that disagree; and the fit's account: each control's residuals, whether it was
    used, the threshold, where the up direction came from."""
    _check_fit_inputs(controls, up)
    enu = _enu(controls, _origin(controls))
    has_alt = np.array([c.altitude is not None for c in controls])
    horizontal = enu[:, :2]
    spread = float(np.median(np.linalg.norm(horizontal - np.median(horizontal, 0), axis=1)))
    threshold = max(conf["min_max_error"], conf["max_error_share"] * spread)
    residuals = _horizontal_residuals(
        _best_pair_fit(centres, enu, has_alt, up, conf, threshold), centres, enu
    )
    used = residuals < threshold
    if used.sum() < 3:
        raise ValueError(
            f"Only {used.sum()} of the {len(controls)} controls agree within {threshold:.1f} m "
            f"(residuals: {_listing(controls, residuals)}); 3 must: check their "
            "names and positions, or add controls."
        )
    # the final fit in the used controls' own frame
    origin = _origin([c for c, u in zip(controls, used) if u])
    enu = _enu(controls, origin)
    full = bool(has_alt[used].all() and used.sum() >= 4) and not _collinear(
        enu[used], conf["collinear_ratio"]
    )
    if full:
        s, R, t = fit_similarity(centres[used], enu[used])
    else:
        s, R, t = fit_upright(centres[used], enu[used], has_alt[used], up, conf["eye_height"])
    frame = GeoFrame(origin, s, R, t, bool(has_alt[used].any()))
    return frame, _account(controls, frame.to_enu(centres) - enu, used, threshold, full)


def _listing(controls: list[Control], residuals) -> str:
    return ", ".join(f"{c.name} {r:.1f} m" for c, r in zip(controls, residuals))


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
) -> dict:
    """Georeference the model of a ``reconstruct`` workspace from a control file and the photos'
    GPS EXIF; writes WORKSPACE/geo/ and report.html again. Returns georeference.json's content."""
    from .localize import open_workspace
    from .report import read_manifest

    conf = merge_conf(default_conf, conf, "georeference")
    path, report, model_dir = open_workspace(workspace)
    image_path = Path(image_path or report["image_path"]).resolve()
    rec = pycolmap.Reconstruction(str(model_dir))
    images = {rec.images[i].name: rec.images[i] for i in rec.reg_image_ids()}
    given = read_controls(control, list(images)) if control is not None else []
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
                "Left out control %s (%s): %.1f m from where the others place it (more than "
                "%.1f m).",
                c["name"],
                c["source"],
                c["residual_m"],
                account["threshold_m"],
            )
    eras = read_manifest(Path(report["manifest_path"])) if report.get("manifest_path") else {}
    cameras = cameras_table(rec, frame, image_path, eras)
    mode = "absolute" if frame.absolute_altitude else "relativeToGround"
    result = {
        "written_by": "colmap_guided georeference",
        "model": str(model_dir),
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
    for name in WRITES:  # a geo/ folder of the user's own is refused, not replaced
        ws.take(name)
    partial = ws.path / f"{GEO}.partial"
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
    _swap(ws.path, partial)
    result["geo_path"] = str(ws.path / GEO)
    if ws.owns("report.html"):
        from .html_report import rewrite_report

        try:
            rewrite_report(ws.path)
        except Exception as err:  # noqa: BLE001 - geo/ is complete; a failed page must not hide it
            logger.warning("Could not write the HTML report again (%s); geo/ is complete.", err)
    return result


def _swap(root: Path, partial: Path) -> None:
    """geo.partial/ becomes geo/ (the old one removed once replaced)."""
    current, old = root / GEO, root / f"{GEO}.old"
    shutil.rmtree(old, ignore_errors=True)
    if current.exists():
        os.replace(current, old)
    os.replace(partial, current)
    shutil.rmtree(old, ignore_errors=True)


def summary_text(out: dict) -> str:
    used = [c for c in out["controls"] if c["used"]]
    counts = ", ".join(f"{k}: {v}" for k, v in out["num_controls"].items())
    lines = [
        f"Georeferenced with {len(used)} of {len(out['controls'])} controls ({counts}); "
        f"residual {out['rms_m']:.2f} m RMS; up from the {out['up_from']}; "
        f"scale {out['enu_from_model']['scale']:.4g} m per model unit.",
    ]
    lines += [
        f"Left out: {c['name']} ({c['source']}), {c['residual_m']:.1f} m off"
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
        help="CSV with the header name,latitude,longitude[,altitude]: where a few photos were "
        "taken (WGS84 degrees, metres above sea level); added to the photos' GPS EXIF",
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
    print(summary_text(georeference(args.workspace, args.control, args.image_path)))
