"""Reference cameras (intrinsics + cam_from_world pose) of the scenes the two-view protocol uses.

Every loader returns a ``RefScene`` in the pixel frame of the image files as they are on disk
(COLMAP's convention, pixel centre = +0.5), so keypoints extracted from those files can be
normalised directly.

Sources (see ../shared/data/README.md and train/README.md)
- ``lund_door_gtsfm``: ``colmap_ground_truth/`` (COLMAP text model, full-size images).
- ``train/strecha_*``: ``calibration_gt*.json`` (K, R, T with x_cam = R x_world + T, 3072x2048
  frame), K rescaled to the downscaled files; real reference cameras.
- ``train/instantngp_fox``: ``transforms.json`` (NeRF camera-to-world, OpenGL axes, OPENCV
  distortion).
- any ``train/<scene>``: ``colmap/`` pseudo ground truth (``source='pseudo_gt'``).
Covisibility (shared 3D points) always comes from a COLMAP model of the scene: the reference model
for lund_door, the pseudo-GT model of the train scenes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from colmap_guided.geometry import relative_pose
from colmap_guided.images import image_size
from colmap_guided.paths import shared_data_dir

# Scenes with real reference cameras; they are held out of training for the reported model.
TWO_VIEW_SCENES = (
    "lund_door_gtsfm",
    "train/strecha_castle",
    "train/strecha_entry_P10",
    "train/instantngp_fox",
)
HELD_OUT_SCENES = TWO_VIEW_SCENES


@dataclass
class RefView:
    name: str
    camera: pycolmap.Camera
    R: np.ndarray  # cam_from_world rotation
    t: np.ndarray  # cam_from_world translation
    group: str = ""  # views of different groups have different world frames (Strecha P19 vs P30)

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t


@dataclass
class RefScene:
    key: str  # e.g. 'train/strecha_castle'
    image_dir: Path
    views: dict[str, RefView]
    source: str  # 'reference' (real cameras) or 'pseudo_gt'
    observations: dict[str, set] = field(default_factory=dict)  # image name -> ids of its 3D points

    def covisibility(self, a: str, b: str) -> int:
        return len(self.observations.get(a, set()) & self.observations.get(b, set()))

    def comparable(self, a: str, b: str) -> bool:
        """Both views have a reference pose in one world frame."""
        return a in self.views and b in self.views and self.views[a].group == self.views[b].group

    def relative_pose(self, a: str, b: str) -> tuple[np.ndarray, np.ndarray]:
        """cam_b_from_cam_a."""
        if not self.comparable(a, b):
            raise KeyError(f"{a} and {b} have no reference poses in one frame")
        va, vb = self.views[a], self.views[b]
        return relative_pose(va.R, va.t, vb.R, vb.t)


def _observations(rec: pycolmap.Reconstruction) -> dict[str, set]:
    out = {}
    for image in rec.images.values():
        out[image.name] = {p.point3D_id for p in image.points2D if p.has_point3D()}
    return out


def _views_from_model(rec: pycolmap.Reconstruction) -> dict[str, RefView]:
    views = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        pose = image.cam_from_world()
        views[image.name] = RefView(
            image.name,
            rec.cameras[image.camera_id],
            pose.rotation.matrix(),
            np.asarray(pose.translation, float),
        )
    return views


def load_colmap_model(model_dir: Path) -> pycolmap.Reconstruction:
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise FileNotFoundError(f"No COLMAP model at {model_dir}")
    return pycolmap.Reconstruction(str(model_dir))


def _orthonormal(R) -> np.ndarray:
    """Nearest rotation (the calibration files round R to 6 digits)."""
    U, _, Vt = np.linalg.svd(np.asarray(R, float))
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def _strecha_views(scene_dir: Path) -> dict[str, RefView]:
    views = {}
    for path in sorted(scene_dir.glob("calibration_gt*.json")):
        for name, cal in json.loads(path.read_text()).items():
            file = scene_dir / "images" / name
            if not file.is_file():
                continue
            w, h = image_size(file)
            K = np.asarray(cal["K"], float)
            sx, sy = w / 3072.0, h / 2048.0  # calibration frame: the original 3072x2048 photos
            camera = pycolmap.Camera(
                model="PINHOLE",
                width=w,
                height=h,
                params=[K[0, 0] * sx, K[1, 1] * sy, K[0, 2] * sx, K[1, 2] * sy],
            )
            # Each calibration file has its own world frame (castle P19 and P30 differ by a
            # similarity).
            views[name] = RefView(
                name, camera, _orthonormal(cal["R"]), np.asarray(cal["T"], float), group=path.stem
            )
    return views


def _instantngp_views(scene_dir: Path) -> dict[str, RefView]:
    data = json.loads((scene_dir / "transforms.json").read_text())
    # OpenGL camera axes (x right, y up, z back) -> OpenCV (y down, z forward)
    flip = np.diag([1.0, -1.0, -1.0])
    views = {}
    for frame in data["frames"]:
        name = Path(frame["file_path"]).name
        file = scene_dir / "images" / name
        if not file.is_file():
            continue
        fw, fh = float(frame.get("w", data["w"])), float(frame.get("h", data["h"]))
        w, h = image_size(file)
        sx, sy = w / fw, h / fh

        def g(k):  # per-frame value or the global one
            return float(frame.get(k, data.get(k, 0.0)))

        camera = pycolmap.Camera(
            model="OPENCV",
            width=w,
            height=h,
            params=[
                g("fl_x") * sx,
                g("fl_y") * sy,
                g("cx") * sx,
                g("cy") * sy,
                g("k1"),
                g("k2"),
                g("p1"),
                g("p2"),
            ],
        )
        c2w = np.asarray(frame["transform_matrix"], float)
        R_c2w = _orthonormal(c2w[:3, :3] @ flip)
        R = R_c2w.T
        views[name] = RefView(name, camera, R, -R @ c2w[:3, 3])
    return views


def load_reference(key: str, source: str = "auto", data_dir: Path | None = None) -> RefScene:
    """Reference of a scene of ../shared/data ('lund_door_gtsfm', 'train/strecha_castle', ...).

    source: 'auto' (real reference cameras where the set has them, else the pseudo-GT model),
    'reference' (real cameras only; error if none) or 'pseudo_gt' (the COLMAP model of
    train/<scene>).
    """
    data_dir = Path(data_dir) if data_dir else shared_data_dir()
    scene_dir = data_dir / key
    if not scene_dir.is_dir():
        raise FileNotFoundError(f"Scene {key} not found in {data_dir}")
    gt_model = scene_dir / "colmap_ground_truth"
    pseudo_model = scene_dir / "colmap"
    model = load_colmap_model(gt_model if gt_model.is_dir() else pseudo_model)
    observations = _observations(model)
    if source in ("auto", "reference"):
        if gt_model.is_dir():
            return RefScene(
                key, scene_dir / "images", _views_from_model(model), "reference", observations
            )
        if list(scene_dir.glob("calibration_gt*.json")):
            return RefScene(
                key, scene_dir / "images", _strecha_views(scene_dir), "reference", observations
            )
        if (scene_dir / "transforms.json").is_file():
            return RefScene(
                key, scene_dir / "images", _instantngp_views(scene_dir), "reference", observations
            )
        if source == "reference":
            raise FileNotFoundError(f"{key} has no reference cameras; use source='pseudo_gt'")
    if not pseudo_model.is_dir():
        if gt_model.is_dir():  # the set's reference is itself a COLMAP model
            return RefScene(
                key, scene_dir / "images", _views_from_model(model), "reference", observations
            )
        raise FileNotFoundError(f"{key} has no pseudo-GT model ({pseudo_model})")
    return RefScene(key, scene_dir / "images", _views_from_model(model), "pseudo_gt", observations)


def reference_model_dir(key: str, data_dir: Path | None = None) -> Path | None:
    """The COLMAP model a registration is checked against (reference where it exists, else
    pseudo-GT)."""
    scene_dir = (Path(data_dir) if data_dir else shared_data_dir()) / key
    for sub in ("colmap_ground_truth", "colmap"):
        if (scene_dir / sub).is_dir():
            return scene_dir / sub
    return None
