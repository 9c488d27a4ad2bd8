"""The model on the Earth, as ``georeference`` wrote it (WORKSPACE/geo/georeference.json): WGS84
latitude, longitude and height to Earth-centred Earth-fixed (ECEF) to local east-north-up (ENU)
coordinates, the similarity from the model to ENU and each camera's KML pose; read by the report
and ``localize``."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pycolmap

from .log import logger
from .workspace import model_digest

GEO = "geo"  # georeference's folder in the workspace
RESULT = "georeference.json"

# WGS84 ellipsoid: semi-major axis (m), flattening, first eccentricity squared
WGS84_A = 6378137.0
WGS84_F = 1 / 298.257223563
WGS84_E2 = WGS84_F * (2 - WGS84_F)


# --- WGS84 <-> ECEF <-> ENU ---------------------------------------------------------------------


def geodetic_to_ecef(lat, lon, alt) -> np.ndarray:
    """Earth-centred, Earth-fixed coordinates (m) of WGS84 latitude, longitude (degrees) and
    height (m): (..., 3)."""
    lat, lon = np.radians(np.asarray(lat, float)), np.radians(np.asarray(lon, float))
    alt = np.asarray(alt, float)
    n = WGS84_A / np.sqrt(1 - WGS84_E2 * np.sin(lat) ** 2)  # prime vertical radius of curvature
    return np.stack(
        [
            (n + alt) * np.cos(lat) * np.cos(lon),
            (n + alt) * np.cos(lat) * np.sin(lon),
            (n * (1 - WGS84_E2) + alt) * np.sin(lat),
        ],
        axis=-1,
    )


def ecef_to_geodetic(xyz) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(latitude, longitude (degrees), height (m)) of ECEF points (..., 3): the fixed-point
    iteration on the latitude, converged to below a micrometre in 6 steps near the surface."""
    xyz = np.asarray(xyz, float)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1 - WGS84_E2))
    for _ in range(6):
        n = WGS84_A / np.sqrt(1 - WGS84_E2 * np.sin(lat) ** 2)
        alt = p / np.maximum(np.cos(lat), 1e-12) - n
        lat = np.arctan2(z, p * (1 - WGS84_E2 * n / (n + alt)))
    n = WGS84_A / np.sqrt(1 - WGS84_E2 * np.sin(lat) ** 2)
    alt = p / np.maximum(np.cos(lat), 1e-12) - n
    return np.degrees(lat), np.degrees(np.arctan2(y, x)), alt


def enu_axes(lat: float, lon: float) -> np.ndarray:
    """Rows: the east, north and up unit vectors at (lat, lon) in ECEF."""
    lat, lon = math.radians(lat), math.radians(lon)
    return np.array(
        [
            [-math.sin(lon), math.cos(lon), 0.0],
            [-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)],
            [math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)],
        ]
    )


def geodetic_to_enu(lat, lon, alt, origin: tuple[float, float, float]) -> np.ndarray:
    """East, north, up (m) of WGS84 points relative to ``origin`` (lat, lon, alt)."""
    ecef = geodetic_to_ecef(lat, lon, alt) - geodetic_to_ecef(*origin)
    return ecef @ enu_axes(*origin[:2]).T


def enu_to_geodetic(enu, origin: tuple[float, float, float]):
    """(latitude, longitude, height) of ENU points (..., 3) relative to ``origin``."""
    return ecef_to_geodetic(
        np.asarray(enu, float) @ enu_axes(*origin[:2]) + geodetic_to_ecef(*origin)
    )


@dataclasses.dataclass
class GeoFrame:
    """The model on the Earth: ENU = scale R x + t, the ENU frame at ``origin`` (lat, lon, alt)."""

    origin: tuple[float, float, float]
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    absolute_altitude: bool  # altitudes above sea level (else above the ground, approximately)

    def to_enu(self, points) -> np.ndarray:
        return self.scale * np.asarray(points, float) @ self.rotation.T + self.translation

    def to_geodetic(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(latitude, longitude, altitude) of model points; altitude: the origin's plus ENU up."""
        enu = self.to_enu(points)
        lat, lon, _ = enu_to_geodetic(enu, self.origin)
        return lat, lon, self.origin[2] + enu[..., 2]

    def sim3d(self) -> pycolmap.Sim3d:
        return pycolmap.Sim3d(self.scale, pycolmap.Rotation3d(self.rotation), self.translation)

    def camera(self, pose: pycolmap.Rigid3d) -> dict:
        """Where a photo (its cam_from_world ``pose``) was taken, looking where, as KML's Camera
        defines it: heading (degrees clockwise from north), tilt (0 looking down, 90 at the
        horizon), roll (positive: the camera turned counter-clockwise, its right side up)."""
        world_from_cam = self.rotation @ pose.rotation.matrix().T  # columns: right, down, forward
        right, forward = world_from_cam[:, 0], world_from_cam[:, 2]
        lat, lon, alt = self.to_geodetic(pose.inverse().translation)
        # looking straight down or up: the heading is where the top of the photo points
        ahead = forward if np.hypot(*forward[:2]) > 1e-6 else -world_from_cam[:, 1]
        heading = math.degrees(math.atan2(ahead[0], ahead[1])) % 360
        tilt = math.degrees(math.acos(float(np.clip(-forward[2], -1, 1))))
        level = np.cross(forward, [0.0, 0.0, 1.0])
        level = level / np.linalg.norm(level) if np.linalg.norm(level) > 1e-9 else right
        roll = math.degrees(math.atan2(right @ np.cross(level, forward), right @ level))
        return {
            "latitude": round(float(lat), 8),
            "longitude": round(float(lon), 8),
            "altitude": round(float(alt), 3),
            "heading": round(heading, 3),
            "tilt": round(tilt, 3),
            "roll": round(roll, 3),
        }

    def to_json(self) -> dict:
        return {
            "origin": dict(zip(("latitude", "longitude", "altitude"), self.origin)),
            "enu_from_model": {
                "scale": self.scale,
                "rotation": self.rotation.tolist(),
                "translation": self.translation.tolist(),
            },
            "altitude_mode": "absolute" if self.absolute_altitude else "relativeToGround",
        }

    @classmethod
    def from_json(cls, data: dict) -> GeoFrame:
        o, sim = data["origin"], data["enu_from_model"]
        return cls(
            (o["latitude"], o["longitude"], o["altitude"]),
            float(sim["scale"]),
            np.array(sim["rotation"], float),
            np.array(sim["translation"], float),
            data.get("altitude_mode") == "absolute",
        )


def osm_url(place: dict) -> str:
    """OpenStreetMap at a point ({"latitude": ..., "longitude": ...}), zoomed to the street."""
    lat, lon = f"{place['latitude']:.6f}", f"{place['longitude']:.6f}"
    return f"https://www.openstreetmap.org/?mlat={lat}&mlon={lon}#map=19/{lat}/{lon}"


# --- the command --------------------------------------------------------------------------------


def geo_folder(model: int) -> str:
    """The folder of a model's georeference in the workspace: geo/ for model 0 (the largest),
    geo_N/ for model N."""
    return GEO if model == 0 else f"{GEO}_{model}"


def load(workspace: Path, model: int = 0) -> tuple[GeoFrame, dict] | None:
    """(GeoFrame, georeference.json) of a workspace's model sparse/``model``, None where it is not
    georeferenced or the model changed since (a reconstruct rerun)."""
    path = Path(workspace) / geo_folder(model) / RESULT
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        frame = GeoFrame.from_json(data)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if data.get("model_sha256") != model_digest(Path(workspace) / "sparse" / str(model)):
        logger.warning("%s is older than the model; run georeference again.", path)
        return None
    return frame, data


def add_places(workspace: Path, entries, model: int = 0) -> None:
    """Each entry of localized.json with a pose in sparse/``model`` gets its camera on the Earth
    (latitude, longitude, altitude, heading, tilt, roll), where that model is georeferenced."""
    geo = load(workspace, model)
    for entry in entries if geo is not None else []:
        if "qvec_wxyz" in entry:
            w, x, y, z = entry["qvec_wxyz"]
            rotation = pycolmap.Rotation3d(np.array([x, y, z, w]))
            entry.update(geo[0].camera(pycolmap.Rigid3d(rotation, np.asarray(entry["tvec"]))))
