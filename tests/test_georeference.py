"""`georeference` on a real reconstruct workspace of the synthetic scene (and a second, unrelated
one: two models), whose exact cameras are put on the Earth by a chosen similarity: 3 controls (a
CSV, or GPS EXIF written into copies of the photos) place the other cameras within 0.5 m and 1
degree of heading, a control 100 m off is named and left out, controls read off a map 15 m off
with their accuracy place the others as well as they allow and a control 200 m off among them is
left out, the second model goes to geo_1/, the KML and GeoJSON read back by xml.etree and shapely,
the report and localize give latitudes and longitudes, bad input is one line with nothing
written, and the benchmark preset measures the other photos' errors per seed."""

from __future__ import annotations

import json
import math
import re
import shutil
from fractions import Fraction
from pathlib import Path
from urllib.parse import unquote, urlparse
from xml.etree import ElementTree as ET

import numpy as np
import pytest
import shapely.geometry
from PIL import Image

from colmap_guided import geoframe
from colmap_guided import georeference as geo
from colmap_guided import localize as loc
from colmap_guided.__main__ import main
from colmap_guided.geometry import photo_up
from colmap_guided.images import folder_digests
from colmap_guided.log import set_verbosity
from colmap_guided.reconstruct import reconstruct
from colmap_guided.workspace import Workspace

ORIGIN = (48.85296, 2.34990, 35.0)  # the Earth origin the scene is put at (lat, lon, alt)
YAW = math.radians(30.0)  # the scene's x axis points 30 degrees north of east
SHIFT = np.array([40.0, -25.0, 3.0])  # metres east, north, up of the scene's origin
CONTROLS = ("view_000.jpg", "view_003.jpg", "view_007.jpg")
SCALE = 20.0  # metres per unit of the scene whose controls are read off a map: cameras over 700 m
COARSE = ("view_000.jpg", "view_002.jpg", "view_004.jpg", "view_006.jpg", "view_007.jpg")
KML = "{http://www.opengis.net/kml/2.2}"
OUR_ERROR = re.compile(r"^\[[\d:]+ colmap_guided ERROR\] (.+)$", re.MULTILINE)


def truth(synthetic_scene, scale: float = 1.0, prefix: str = "") -> dict[str, dict]:
    """Per photo (its name after ``prefix``): its true camera centre in ENU metres, heading, and
    WGS84 position; the scene ``scale`` metres per unit."""
    c, s = math.cos(YAW), math.sin(YAW)
    enu_from_scene = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    out = {}
    for name, (R, t) in synthetic_scene.cam_from_world.items():
        enu = scale * enu_from_scene @ (-R.T @ t) + SHIFT
        forward = enu_from_scene @ R.T @ [0.0, 0.0, 1.0]
        lat, lon, alt = geoframe.enu_to_geodetic(enu, ORIGIN)
        out[prefix + name] = {
            "enu": enu,
            "heading": math.degrees(math.atan2(forward[0], forward[1])) % 360,
            "latitude": float(lat),
            "longitude": float(lon),
            "altitude": float(alt),
        }
    return out


def control_csv(path: Path, rows: dict[str, dict], header="name,latitude,longitude,altitude"):
    """A control file: per row its name, then the fields ``header`` names."""
    digits = {"latitude": 9, "longitude": 9, "altitude": 3, "accuracy": 3}
    columns = header.split(",")[1:]
    lines = [header] + [
        ",".join([n, *("" if r[c] is None else f"{r[c]:.{digits[c]}f}" for c in columns)])
        for n, r in rows.items()
    ]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def other_scene(tmp_path_factory):
    """Another place (the synthetic scene of seed 1, 6 views): no photo of it matches the first."""
    from colmap_guided.synthetic import render_scene

    return render_scene(tmp_path_factory.mktemp("other") / "scene", num_images=6, seed=1)


@pytest.fixture(scope="module")
def workspace(synthetic_scene, other_scene, tmp_path_factory):
    """A reconstruct workspace of copies of the synthetic views (all 8 registered in sparse/0) and
    of the other place's, named other_*.jpg (sparse/1)."""
    root = tmp_path_factory.mktemp("georeference")
    shutil.copytree(synthetic_scene.image_dir, root / "scene" / "images")
    for photo in other_scene.image_dir.iterdir():
        shutil.copy(photo, root / "scene" / "images" / f"other_{photo.name}")
    mapping = {"mapper": "incremental", "num_threads": 1}
    result = reconstruct(root / "scene", output=root / "ws", matcher="raw", mapping_conf=mapping)
    assert result["num_registered"] == 8
    return root / "ws"


def check_placed(out: dict, synthetic_scene, controls) -> None:
    """Every other camera within 0.5 m and 1 degree of heading of its truth."""
    true = truth(synthetic_scene)
    placed = {n: c for n, c in out["cameras"].items() if n not in controls}
    assert len(placed) == 8 - len(controls)
    for name, cam in placed.items():
        enu = geoframe.geodetic_to_enu(cam["latitude"], cam["longitude"], cam["altitude"], ORIGIN)
        assert np.linalg.norm(enu - true[name]["enu"]) < 0.5, (name, enu, true[name]["enu"])
        heading_error = (cam["heading"] - true[name]["heading"] + 180) % 360 - 180
        assert abs(heading_error) < 1.0, (name, cam["heading"], true[name]["heading"])


def test_geodesy_against_known_lengths():
    """A degree of latitude and of longitude at 55.7 degrees as long as WGS84's series say
    (111132.954 - 559.822 cos 2p + 1.175 cos 4p, and 111412.84 cos p - 93.5 cos 3p + 0.118 cos 5p
    metres); an ECEF round trip exact to a micrometre."""
    p = math.radians(55.7)
    origin = (55.7, 13.2, 0.0)
    step = 0.0005  # a short step: the tangent plane is the arc to a micrometre
    north = geoframe.geodetic_to_enu(55.7 + step, 13.2, 0.0, origin)
    north -= geoframe.geodetic_to_enu(55.7 - step, 13.2, 0.0, origin)
    meridian = 111132.954 - 559.822 * math.cos(2 * p) + 1.175 * math.cos(4 * p)
    assert abs(north[1] / (2 * step) - meridian) < 0.05 and abs(north[0]) < 1e-6
    east = geoframe.geodetic_to_enu(55.7, 13.2 + step, 0.0, origin)
    east -= geoframe.geodetic_to_enu(55.7, 13.2 - step, 0.0, origin)
    parallel = 111412.84 * math.cos(p) - 93.5 * math.cos(3 * p) + 0.118 * math.cos(5 * p)
    assert abs(east[0] / (2 * step) - parallel) < 0.05 and abs(east[1]) < 1e-6
    np.testing.assert_allclose(geoframe.geodetic_to_ecef(0.0, 0.0, 0.0), [geoframe.WGS84_A, 0, 0])
    lat, lon, alt = np.array([55.7, -33.9, 89.9]), np.array([13.2, 151.2, -120.0]), [5, 2000, 0]
    back = geoframe.ecef_to_geodetic(geoframe.geodetic_to_ecef(lat, lon, alt))
    np.testing.assert_allclose(back[0], lat, atol=1e-11)
    np.testing.assert_allclose(back[1], lon, atol=1e-11)
    np.testing.assert_allclose(back[2], alt, atol=1e-6)


def test_photo_up_is_not_biased_by_pitch():
    """Photos pitched 12 degrees up, facing many ways, rolled a little, one scan rotated by 90
    degrees: the up is found within half a degree; the mean image-up is 10 degrees off."""
    rng = np.random.default_rng(0)
    rotations = []
    for az in rng.uniform(0, math.pi / 2, 12):  # a quarter circle: the pitch does not average out
        forward = np.array([math.cos(az) * math.cos(0.21), math.sin(az) * math.cos(0.21), 0.21])
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        roll = math.radians(rng.uniform(-1, 1))
        down = np.cross(forward, right)
        right, down = (
            math.cos(roll) * right + math.sin(roll) * down,
            -math.sin(roll) * right + math.cos(roll) * down,
        )
        rotations.append(np.stack([right, down, forward]))
    rotations.append(np.stack([rotations[0][1], -rotations[0][0], rotations[0][2]]))  # a scan
    up = photo_up(rotations)
    mean = -np.mean([R[1] for R in rotations[:-1]], axis=0)
    assert math.degrees(math.acos(up[2])) < 0.5
    assert math.degrees(math.acos(mean[2] / np.linalg.norm(mean))) > 8
    turned = [np.stack([R[1], -R[0], R[2]]) for R in rotations]  # every photo on its side
    assert photo_up(turned[:6] + rotations[6:]) is None


def test_three_controls_place_every_other_camera(workspace, synthetic_scene, tmp_path):
    before = folder_digests(workspace / "sparse")
    rows = {n: truth(synthetic_scene)[n] for n in CONTROLS}
    out = geo.georeference(workspace, control_csv(tmp_path / "control.csv", rows))
    check_placed(out, synthetic_scene, CONTROLS)
    saved = json.loads((workspace / "geo" / "georeference.json").read_text(encoding="utf-8"))
    assert saved["up_from"] == "photos" and saved["altitude_mode"] == "absolute"
    assert [c["used"] for c in saved["controls"]] == [True] * 3
    assert all(c["residual_m"] < 0.3 for c in saved["controls"])
    o = saved["origin"]  # the controls' centroid
    assert abs(o["latitude"] - np.mean([r["latitude"] for r in rows.values()])) < 1e-9
    assert folder_digests(workspace / "sparse") == before  # the model is only read
    assert sorted(p.name for p in (workspace / "geo").iterdir()) == [
        "cameras.geojson",
        "cameras.kml",
        "georeference.json",
        "points.ply",
    ]
    assert not (workspace / "geo.partial").exists() and not (workspace / "geo.old").exists()
    # points.ply: the model's points in ENU metres, around the controls' centroid
    ply = (workspace / "geo" / "points.ply").read_bytes()
    count = int(re.search(rb"element vertex (\d+)", ply).group(1))
    assert count == json.loads((workspace / "report.json").read_text())["num_points3D"]


def test_five_controls_fix_the_up_and_no_altitude_is_above_the_ground(
    workspace, synthetic_scene, tmp_path
):
    """5 surveyed controls (1 cm) with altitudes, not on one line: all 7 degrees of freedom from
    them. With the default accuracy (1 m over 9 m across) the photos' up is better, and taken.
    Without altitudes: the same places on the map, heights above the ground (the controls at eye
    height)."""
    true = truth(synthetic_scene)
    names = ("view_000.jpg", "view_002.jpg", "view_004.jpg", "view_005.jpg", "view_007.jpg")
    rows = {n: {**true[n], "accuracy": 0.01} for n in names}
    header = "name,latitude,longitude,altitude,accuracy"
    out = geo.georeference(workspace, control_csv(tmp_path / "control.csv", rows, header))
    assert out["up_from"] == "controls" and out["altitude_mode"] == "absolute"
    assert [c["accuracy_m"] for c in out["controls"]] == [0.01] * 5
    check_placed(out, synthetic_scene, names)
    out = geo.georeference(workspace, control_csv(tmp_path / "control.csv", rows))
    assert out["up_from"] == "photos" and out["altitude_mode"] == "absolute"
    assert [c["accuracy_m"] for c in out["controls"]] == [geo.default_conf["accuracy"]] * 5
    check_placed(out, synthetic_scene, names)
    out = geo.georeference(
        workspace, control_csv(tmp_path / "flat.csv", rows, header="name,latitude,longitude")
    )
    assert out["up_from"] == "photos" and out["altitude_mode"] == "relativeToGround"
    heights = [out["cameras"][n]["altitude"] for n in names]
    assert abs(np.mean(heights) - geo.default_conf["eye_height"]) < 1e-3
    for name, cam in out["cameras"].items():
        enu = geoframe.geodetic_to_enu(cam["latitude"], cam["longitude"], 0.0, ORIGIN)
        assert np.linalg.norm(enu[:2] - true[name]["enu"][:2]) < 0.5
    kml = ET.parse(workspace / "geo" / "cameras.kml").getroot()
    assert {m.text for m in kml.iter(f"{KML}altitudeMode")} == {"relativeToGround"}


def write_gps(path: Path, lat: float, lon: float, alt: float, accuracy=None) -> None:
    """GPS EXIF (degrees, minutes, seconds as rationals; the horizontal positioning error in
    metres where given) into a copy of a photo."""

    def dms(value: float):
        value = abs(value)
        degrees, minutes = int(value), int(value * 60) % 60
        seconds = Fraction(round((value * 3600 - degrees * 3600 - minutes * 60) * 10**6), 10**6)
        return (degrees, minutes, seconds)

    with Image.open(path) as im:
        exif = im.getexif()
        gps = exif.get_ifd(0x8825)
        gps.update(
            {
                1: "N" if lat >= 0 else "S",
                2: dms(lat),
                3: "E" if lon >= 0 else "W",
                4: dms(lon),
                5: b"\x00",
                6: Fraction(round(alt * 1000), 1000),
                **({31: Fraction(accuracy)} if accuracy else {}),
            }
        )
        pixels = im.copy()
    pixels.save(path, quality=95, exif=exif)


def test_gps_exif_of_three_photos_places_every_other_camera(workspace, synthetic_scene, tmp_path):
    photos = tmp_path / "photos"
    shutil.copytree(synthetic_scene.image_dir, photos)  # EXIF written into copies only
    true = truth(synthetic_scene)
    for name, accuracy in zip(CONTROLS, (None, 0.5, None)):
        t = true[name]
        write_gps(photos / name, t["latitude"], t["longitude"], t["altitude"], accuracy)
    read = geo.exif_control(photos / CONTROLS[0], CONTROLS[0])
    assert abs(read.latitude - true[CONTROLS[0]]["latitude"]) < 1e-8
    out = geo.georeference(workspace, image_path=photos)
    assert out["num_controls"] == {"control file": 0, "GPS EXIF": 3}
    assert [c["source"] for c in out["controls"]] == ["GPS EXIF"] * 3
    assert [c["accuracy_m"] for c in out["controls"]] == [1.0, 0.5, 1.0]  # the EXIF's, or 1 m
    check_placed(out, synthetic_scene, CONTROLS)
    kml = ET.parse(workspace / "geo" / "cameras.kml").getroot()
    hrefs = {unquote(urlparse(h.text).path) for h in kml.iter(f"{KML}href")}
    assert hrefs == {str((photos / n).resolve()) for n in synthetic_scene.names}


def test_a_control_100_m_off_is_named_and_left_out(workspace, synthetic_scene, tmp_path, capsys):
    set_verbosity()
    true = truth(synthetic_scene)
    rows = {n: dict(true[n]) for n in (*CONTROLS, "view_005.jpg")}
    lat, lon, alt = geoframe.enu_to_geodetic(true["view_005.jpg"]["enu"] + [100.0, 0, 0], ORIGIN)
    rows["view_005.jpg"].update(latitude=float(lat), longitude=float(lon))
    assert (
        main(
            [
                "georeference",
                str(workspace),
                "--control",
                str(control_csv(tmp_path / "c.csv", rows)),
            ]
        )
        == 0
    )
    printed = capsys.readouterr()
    assert re.search(r"Left out control view_005\.jpg \(c\.csv line 5\): 10\d\.\d m", printed.err)
    assert "Left out: view_005.jpg (c.csv line 5)" in printed.out
    saved = json.loads((workspace / "geo" / "georeference.json").read_text(encoding="utf-8"))
    by_name = {c["name"]: c for c in saved["controls"]}
    assert not by_name["view_005.jpg"]["used"] and 95 < by_name["view_005.jpg"]["residual_m"] < 105
    assert all(by_name[n]["used"] for n in CONTROLS)
    check_placed(saved, synthetic_scene, CONTROLS)


def coarse_controls(synthetic_scene, noise: float = 15.0) -> tuple[dict, dict]:
    """(the truth at SCALE, COARSE as read off a map: each ``noise`` metres off in a random
    direction, seed 0, with an accuracy of 20 m)."""
    true = truth(synthetic_scene, SCALE)
    rng = np.random.default_rng(0)
    rows = {}
    for name in COARSE:
        turn = rng.uniform(0, 2 * math.pi)
        moved = true[name]["enu"] + noise * np.array([math.cos(turn), math.sin(turn), 0.0])
        lat, lon, alt = geoframe.enu_to_geodetic(moved, ORIGIN)
        rows[name] = {"latitude": lat, "longitude": lon, "altitude": alt, "accuracy": 20.0}
    return true, rows


def check_as_expected(out: dict, true: dict, noise: float, others=()) -> None:
    """Every camera but COARSE (and ``others``, controls too) where a least-squares similarity
    from COARSE, each ``noise`` metres off, leaves it: horizontally within 2.5 times the RMS error
    it predicts there, noise^2 (1/n + d^2 / sum d_i^2) with d the distance from the controls'
    centroid (Rayleigh: beyond it once in 500), heading within 3 sigma, noise / sqrt(2 sum d_i^2)
    radians, and a degree."""
    xy = np.array([true[n]["enu"][:2] for n in COARSE])
    centre, spread = xy.mean(axis=0), np.sum((xy - xy.mean(axis=0)) ** 2)
    placed = {n: c for n, c in out["cameras"].items() if n not in (*COARSE, *others)}
    assert len(placed) == 8 - len(COARSE) - len(others)
    for name, cam in placed.items():
        enu = geoframe.geodetic_to_enu(cam["latitude"], cam["longitude"], cam["altitude"], ORIGIN)
        d2 = np.sum((true[name]["enu"][:2] - centre) ** 2)
        expected = noise * math.sqrt(1 / len(xy) + d2 / spread)
        error = np.linalg.norm(enu[:2] - true[name]["enu"][:2])
        assert error < 2.5 * expected, (name, error, expected)
        heading_error = (cam["heading"] - true[name]["heading"] + 180) % 360 - 180
        assert abs(heading_error) < 3 * math.degrees(noise / math.sqrt(2 * spread)) + 1.0


def test_controls_read_off_a_map_are_used_with_their_accuracy(
    workspace, synthetic_scene, tmp_path, capsys
):
    """5 standpoints guessed on a map, each 15 m off, over 700 m, no accuracy given (--accuracy
    20), and a far view's guessed to 100 m, 150 m off: all used, the far view weighing 1/25 of
    one of the others (weighed alike, it would move them by 25 m); each residual printed and
    saved beside its accuracy; the others placed as well as the 5 allow. Their altitudes do not
    fix the up (20 m over 190 m across: 6 degrees)."""
    true, rows = coarse_controls(synthetic_scene)
    for row in rows.values():
        row["accuracy"] = None  # an empty cell: --accuracy's
    lat, lon, alt = geoframe.enu_to_geodetic(true["view_005.jpg"]["enu"] + [0, -150.0, 0], ORIGIN)
    rows["view_005.jpg"] = {"latitude": lat, "longitude": lon, "altitude": alt, "accuracy": 100.0}
    path = control_csv(tmp_path / "c.csv", rows, "name,latitude,longitude,altitude,accuracy")
    set_verbosity()
    assert main(["georeference", str(workspace), "--control", str(path), "--accuracy", "20"]) == 0
    printed = capsys.readouterr().out
    saved = json.loads((workspace / "geo" / "georeference.json").read_text(encoding="utf-8"))
    assert [(c["name"], c["used"], c["accuracy_m"]) for c in saved["controls"]] == [
        *((n, True, 20.0) for n in COARSE),
        ("view_005.jpg", True, 100.0),
    ]
    residuals = [c["residual_m"] for c in saved["controls"]]
    assert saved["up_from"] == "photos" and 140 < residuals[-1] < 160 and max(residuals[:-1]) < 30
    assert abs(saved["rms_m"] - math.sqrt(np.mean(np.square(residuals)))) < 1e-3
    assert f"residual {saved['rms_m']:.2f} m RMS" in printed
    for line, c in enumerate(saved["controls"], start=2):
        assert 0 < c["residual_m"] < c["tolerance_m"] == 3 * c["accuracy_m"]
        expected = f"  {c['name']} (c.csv line {line}): {c['residual_m']:.1f} m, accuracy "
        assert f"{expected}{c['accuracy_m']:g} m" in printed
    check_as_expected(saved, true, 15.0, others=["view_005.jpg"])


def test_a_control_200_m_off_among_coarse_ones_is_named_and_left_out(
    workspace, synthetic_scene, tmp_path, capsys
):
    """The same controls, accuracy 20 m in the file, and a 6th 200 m off: named with its residual
    and accuracy, left out; the others placed as well as the 5 allow."""
    true, rows = coarse_controls(synthetic_scene)
    lat, lon, alt = geoframe.enu_to_geodetic(true["view_005.jpg"]["enu"] + [200.0, 0, 0], ORIGIN)
    rows["view_005.jpg"] = {"latitude": lat, "longitude": lon, "altitude": alt, "accuracy": 20.0}
    path = control_csv(tmp_path / "c.csv", rows, "name,latitude,longitude,altitude,accuracy")
    set_verbosity()
    assert main(["georeference", str(workspace), "--control", str(path)]) == 0
    printed = capsys.readouterr()
    assert re.search(
        r"Left out control view_005\.jpg \(c\.csv line 7\): \d+\.\d m from where the "
        r"others place it \(accuracy 20 m: more than 60\.0 m\)",
        printed.err,
    ), printed.err
    saved = json.loads((workspace / "geo" / "georeference.json").read_text(encoding="utf-8"))
    (off,) = [c for c in saved["controls"] if not c["used"]]
    assert off["name"] == "view_005.jpg" and 180 < off["residual_m"] < 220
    assert (off["accuracy_m"], off["tolerance_m"]) == (20.0, 60.0)
    line = f"Left out: view_005.jpg (c.csv line 7), {off['residual_m']:.1f} m off, accuracy 20 m"
    assert line in printed.out
    check_as_expected(saved, true, 15.0, others=["view_005.jpg"])


def test_kml_and_geojson_read_back(workspace, synthetic_scene, tmp_path):
    true = truth(synthetic_scene)
    rows = {n: true[n] for n in CONTROLS}
    geo.georeference(workspace, control_csv(tmp_path / "control.csv", rows))
    root = ET.parse(workspace / "geo" / "cameras.kml").getroot()
    assert root.tag == f"{KML}kml"
    overlays = root.findall(f"{KML}Document/{KML}PhotoOverlay")
    assert sorted(o.findtext(f"{KML}name") for o in overlays) == synthetic_scene.names
    for overlay in overlays:
        camera = overlay.find(f"{KML}Camera")
        values = {
            k: float(camera.findtext(f"{KML}{k}"))
            for k in ("longitude", "latitude", "altitude", "heading", "tilt", "roll")
        }
        name = overlay.findtext(f"{KML}name")
        assert abs(values["latitude"] - true[name]["latitude"]) < 1e-5
        assert abs(values["longitude"] - true[name]["longitude"]) < 1e-5
        assert 60 < values["tilt"] < 120 and abs(values["roll"]) < 5  # upright, near the horizon
        assert camera.findtext(f"{KML}altitudeMode") == "absolute"
        volume = overlay.find(f"{KML}ViewVolume")
        fov = {
            k: float(volume.findtext(f"{KML}{k}"))
            for k in ("leftFov", "rightFov", "bottomFov", "topFov", "near")
        }
        # the synthetic camera: f = 1.1 w, so the half width is atan(0.5 / 1.1) = 24.4 degrees
        assert abs(fov["rightFov"] - 24.44) < 1.5 and abs(fov["leftFov"] + fov["rightFov"]) < 1.5
        assert abs(fov["topFov"] - 18.4) < 1.5 and fov["bottomFov"] < 0 and 10 < fov["near"] < 40
        href = overlay.findtext(f"{KML}Icon/{KML}href")
        assert href.startswith("file:///") and Path(unquote(urlparse(href).path)).is_file()

    collection = json.loads((workspace / "geo" / "cameras.geojson").read_text(encoding="utf-8"))
    assert collection["type"] == "FeatureCollection"
    points, cones = {}, {}
    for feature in collection["features"]:
        shape = shapely.geometry.shape(feature["geometry"])
        assert shape.is_valid
        props = feature["properties"]
        (points if props["kind"] == "camera" else cones)[props["name"]] = (shape, props)
    assert sorted(points) == sorted(cones) == synthetic_scene.names
    for name in CONTROLS:  # [lon, lat]: x is the longitude
        point, props = points[name]
        assert abs(point.x - true[name]["longitude"]) < 1e-6
        assert abs(point.y - true[name]["latitude"]) < 1e-6
    for name, (point, props) in points.items():
        assert point.has_z and abs(props["fov_deg"] - 48.9) < 2
        assert abs((props["heading"] - true[name]["heading"] + 180) % 360 - 180) < 1
        cone = cones[name][0]
        assert cone.geom_type == "Polygon" and cone.exterior.is_ccw and cone.area > 0
        assert cone.exterior.distance(point) < 1e-9  # the apex is the camera
        # the cone points where the camera looks: its centroid lies along the heading
        d_lon, d_lat = cone.centroid.x - point.x, cone.centroid.y - point.y
        bearing = math.degrees(math.atan2(d_lon * math.cos(math.radians(point.y)), d_lat))
        assert abs((bearing - props["heading"] + 180) % 360 - 180) < 2


def test_report_and_localize_give_latitude_and_longitude(workspace, synthetic_scene, tmp_path):
    rows = {n: truth(synthetic_scene)[n] for n in CONTROLS}
    out = geo.georeference(workspace, control_csv(tmp_path / "control.csv", rows))
    page = (workspace / "report.html").read_text(encoding="utf-8")
    for cam in out["cameras"].values():
        lat, lon = f"{cam['latitude']:.6f}", f"{cam['longitude']:.6f}"
        assert (
            f"https://www.openstreetmap.org/?mlat={lat}&amp;mlon={lon}#map=19/{lat}/{lon}" in page
        )
    assert "north up, in metres" in page
    data = json.loads(re.search(r"id='model-data'>(.*?)</script>", page).group(1))
    np.testing.assert_allclose(data["frame"]["axes"], np.eye(3), atol=1e-12)  # z: the true up
    photo = workspace.parent / "scene" / "images" / "view_004.jpg"
    entry = loc.localize(workspace, [photo], matcher="raw")["photos"][0]
    assert entry["status"] == "placed"
    cam = out["cameras"]["view_004.jpg"]
    here = geoframe.geodetic_to_enu(
        entry["latitude"], entry["longitude"], entry["altitude"], ORIGIN
    )
    there = geoframe.geodetic_to_enu(cam["latitude"], cam["longitude"], cam["altitude"], ORIGIN)
    assert np.linalg.norm(here - there) < 0.2 and abs(entry["heading"] - cam["heading"]) < 0.5
    saved = json.loads((workspace / "localized.json").read_text(encoding="utf-8"))
    assert saved["photos"][0]["latitude"] == entry["latitude"]
    page = (workspace / "report.html").read_text(encoding="utf-8")
    assert f"mlat={entry['latitude']:.6f}" in page.split("Photos localized in the model")[1]


BAD = {
    "unknown photo": (
        "name,latitude,longitude\nview_000.jpg,48.85,2.35\nnot_there.jpg,48.85,2.35\n",
        r"control\.csv line 3: no registered photo named 'not_there\.jpg'",
    ),
    "two controls": (
        "name,latitude,longitude\nview_000.jpg,48.85,2.35\nview_003.jpg,48.8501,2.3501\n",
        r"2 photo\(s\) with a known position; at least 3",
    ),
    "malformed line": (
        "name,latitude,longitude\nview_000.jpg,48.85,2.35\nview_003.jpg,48°51'N,2.35\n",
        r"control\.csv line 3: .* is not numbers",
    ),
    "too few fields": (
        "name,latitude,longitude\nview_000.jpg,48.85\n",
        r"control\.csv line 2: 2 fields, 3 expected",
    ),
    "latitude out of range": (
        "name,latitude,longitude\nview_000.jpg,95.0,2.35\n",
        r"control\.csv line 2: latitude 95\.0 / longitude 2\.35 is off the Earth",
    ),
    "longitude out of range": (
        "name,latitude,longitude\nview_000.jpg,48.85,200\n",
        r"line 2: .*off the Earth",
    ),
    "no header": ("view_000.jpg,48.85,2.35\n", r"line 1: the header must be name,latitude"),
    "accuracy not a distance": (
        "name,latitude,longitude,accuracy\nview_000.jpg,48.85,2.35,0\n",
        r"control\.csv line 2: accuracy 0\.0 is not a distance",
    ),
    "accuracy before altitude": (
        "name,latitude,longitude,accuracy,altitude\nview_000.jpg,48.85,2.35,20,35\n",
        r"line 1: the header must be name,latitude,longitude, then altitude, accuracy or both",
    ),
    "--accuracy not a distance": (
        "name,latitude,longitude\nview_000.jpg,48.85,2.35\n",
        r"^--accuracy -5\.0 is not a distance",
        ["--accuracy", "-5"],
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_is_one_line_and_nothing_is_written(case, workspace, tmp_path, capsys):
    text, message, *flags = BAD[case]
    (tmp_path / "control.csv").write_text(text, encoding="utf-8")
    before = {
        "geo": folder_digests(workspace / "geo") if (workspace / "geo").exists() else None,
        "files": sorted(p.name for p in workspace.iterdir()),
        "sparse": folder_digests(workspace / "sparse"),
    }
    set_verbosity()
    control = ["--control", str(tmp_path / "control.csv")]
    assert main(["georeference", str(workspace), *control, *(flags[0] if flags else [])]) == 2
    err = capsys.readouterr().err
    errors = OUR_ERROR.findall(err)
    assert len(errors) == 1 and len(err.strip().splitlines()) == 1, err
    assert re.search(message, errors[0]), errors[0]
    after = {
        "geo": folder_digests(workspace / "geo") if (workspace / "geo").exists() else None,
        "files": sorted(p.name for p in workspace.iterdir()),
        "sparse": folder_digests(workspace / "sparse"),
    }
    assert after == before


def test_controls_that_disagree_are_refused(workspace, synthetic_scene, tmp_path, capsys):
    """3 controls, one 100 m off: no 3 agree, so none can be trusted; the residuals are listed
    beside the accuracies, and the accuracy that would have let them agree is named: given, it
    does."""
    true = truth(synthetic_scene)
    rows = {n: dict(true[n]) for n in CONTROLS}
    lat, lon, _ = geoframe.enu_to_geodetic(true[CONTROLS[1]]["enu"] + [0, 100.0, 0], ORIGIN)
    rows[CONTROLS[1]].update(latitude=float(lat), longitude=float(lon))
    before = folder_digests(workspace / "geo") if (workspace / "geo").exists() else None
    set_verbosity()
    path = control_csv(tmp_path / "control.csv", rows)
    assert main(["georeference", str(workspace), "--control", str(path)]) == 2
    (error,) = OUR_ERROR.findall(capsys.readouterr().err)
    assert error.startswith("Only 2 of the 3 controls agree within 3 times their accuracy")
    assert re.search(r"view_003\.jpg \d+\.\d m / 1 m", error), error
    needed = re.search(r"would with an accuracy of ([\d.]+) m \(--accuracy \1,", error)
    assert needed and 10 < float(needed.group(1)) < 50, error
    assert (folder_digests(workspace / "geo") if (workspace / "geo").exists() else None) == before
    assert main(["georeference", str(workspace), "--control", str(path), "--accuracy", "10"]) == 2
    assert (
        main(["georeference", str(workspace), "--control", str(path), "--accuracy", needed[1]]) == 0
    )
    saved = json.loads((workspace / "geo" / "georeference.json").read_text(encoding="utf-8"))
    assert [c["used"] for c in saved["controls"]] == [True] * 3


def test_another_model_goes_to_its_own_folder(workspace, other_scene, tmp_path, capsys):
    """--model 1 georeferences sparse/1 (the other place) into geo_1/, recorded as the project's
    (reconstruct --overwrite removes it); geo/ stays as it was; a model that is not there is one
    line naming those that are."""
    true = truth(other_scene, prefix="other_")
    names = ("other_view_000.jpg", "other_view_002.jpg", "other_view_005.jpg")
    path = control_csv(tmp_path / "control.csv", {n: true[n] for n in names})
    before = {
        "geo": folder_digests(workspace / "geo") if (workspace / "geo").exists() else None,
        "sparse": folder_digests(workspace / "sparse"),
    }
    set_verbosity()
    assert main(["georeference", str(workspace), "--control", str(path), "--model", "1"]) == 0
    assert "Georeferenced model 1 with 3 of 3 controls" in capsys.readouterr().out
    saved = json.loads((workspace / "geo_1" / "georeference.json").read_text(encoding="utf-8"))
    assert saved["model_index"] == 1 and saved["model"] == str(workspace / "sparse" / "1")
    assert sorted(saved["cameras"]) == sorted(true)
    for name, cam in saved["cameras"].items():
        enu = geoframe.geodetic_to_enu(cam["latitude"], cam["longitude"], cam["altitude"], ORIGIN)
        assert np.linalg.norm(enu - true[name]["enu"]) < 0.5, (name, enu, true[name]["enu"])
    assert {
        "geo": folder_digests(workspace / "geo") if (workspace / "geo").exists() else None,
        "sparse": folder_digests(workspace / "sparse"),
    } == before
    assert main(["georeference", str(workspace), "--control", str(path), "--model", "2"]) == 2
    (error,) = OUR_ERROR.findall(capsys.readouterr().err)
    assert (
        error
        == f"--model 2: {workspace / 'sparse'} holds models 0, 1 (0 the largest); pass one of them."
    )
    assert main(["georeference", str(workspace), "--control", str(path)]) == 2
    assert "use the names of sparse/0" in OUR_ERROR.findall(capsys.readouterr().err)[0]
    copy = tmp_path / "ws"
    shutil.copytree(workspace, copy)
    (copy / "notes.txt").write_text("mine", encoding="utf-8")
    Workspace.claim(copy, "reconstruct", overwrite=True)  # what reconstruct --overwrite does
    assert sorted(p.name for p in copy.iterdir()) == [".colmap_guided.json", "notes.txt"]


def test_the_benchmark_preset_measures_the_other_photos_per_seed(
    workspace, synthetic_scene, tmp_path
):
    """``python -m recon_scripts georeference`` on this workspace, the rendering's cameras as the
    reference: with exact controls the other 5 photos land within 5 cm and 0.5 degrees of
    heading; moved by map-reading noise, one run per seed, each seed moves them its own way and
    further; controls 100-200 m off are refused, the command's message in the table's place."""
    from recon_scripts.__main__ import main as bench

    def run(name: str, *options: str) -> dict:
        output = tmp_path / f"{name}.json"
        assert bench(["georeference", f"sets={workspace}", f"output={output}", *options]) == 0
        (results,) = json.loads(output.read_text())["results"].values()
        return results

    controls = f"controls={' '.join(CONTROLS)}"
    common = (f"reference={synthetic_scene.gt_dir}", controls, f"work={tmp_path / 'work'}")
    exact = run("exact", *common)["seed 0"]
    assert [row[0] for row in exact["errors"]] == [
        n for n in synthetic_scene.names if n not in CONTROLS
    ]
    assert max(row[3] for row in exact["errors"]) < 0.05, exact["errors"]
    assert max(abs(row[4]) for row in exact["errors"]) < 0.5, exact["errors"]
    noisy = run("noisy", *common, "noise=0.2", "seeds=0 1")
    assert list(noisy) == ["seed 0", "seed 1"] and noisy["seed 0"] != noisy["seed 1"]
    for r in noisy.values():
        assert max(row[3] for row in r["errors"]) > max(row[3] for row in exact["errors"])
    table = (tmp_path / "noisy.md").read_text()
    assert table.count("| photo | horizontal (m) | vertical (m) | 3D (m) | heading (deg) |") == 2
    assert "| median |" in table and "reconstruction: photo_up is" in table
    refused = run("refused", *common, "moved=100 200")["seed 0"]
    assert refused["refused"].startswith("Only "), refused
    assert "Refused: Only " in (tmp_path / "refused.md").read_text()
