"""What ``localize`` records per photo in localized.json: its verdict, and for the report the model
with the cameras of the photos it placed."""

from __future__ import annotations

import numpy as np
import pycolmap

PLACED, UNCERTAIN, NOT_PLACED = "placed", "uncertain", "not placed"


def with_localized(
    rec: pycolmap.Reconstruction, entries: list[dict]
) -> tuple[pycolmap.Reconstruction, list[str]]:
    """A copy of ``rec`` with the cameras of the placed and uncertain photos of localized.json
    (named by their path, no points), for the report's 3D view and map; and their names."""
    shown = pycolmap.Reconstruction(rec)
    names = []
    for entry in entries:
        if entry.get("status") not in (PLACED, UNCERTAIN) or "qvec_wxyz" not in entry:
            continue
        cam = entry["camera"]
        camera = pycolmap.Camera(
            model=cam["model"], width=cam["width"], height=cam["height"], params=cam["params"]
        )
        camera.camera_id = max([*shown.cameras, *shown.rigs], default=0) + 1
        image_id = max([*shown.images, *shown.frames], default=0) + 1
        w, x, y, z = entry["qvec_wxyz"]
        pose = pycolmap.Rigid3d(
            pycolmap.Rotation3d(np.array([x, y, z, w])), np.asarray(entry["tvec"], float)
        )
        shown.add_camera_with_trivial_rig(camera)
        shown.add_image_with_trivial_frame(
            pycolmap.Image(name=entry["photo"], camera_id=camera.camera_id, image_id=image_id), pose
        )
        names.append(entry["photo"])
    return shown, names
