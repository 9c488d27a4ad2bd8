"""The SfM scenes training and validation read (paper §4.3, as its MegaDepth use): every scene is a
``pycolmap.Reconstruction``; positive pairs are registered images sharing at least ``min_shared``
(30) 3D points, with F from the calibrations and poses (x_B^T F x_A = 0) and ground-truth point
matches from the two observations of each shared track.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from colmap_guided.geometry import fundamental_from_poses
from colmap_guided.log import logger
from colmap_guided.paths import shared_data_dir

# Whole scenes held out for validation (the evaluation issue reports on them) ...
VAL_SCENES = ["strecha_castle", "strecha_entry_P10", "instantngp_fox", "lund_door_gtsfm"]
# Training scenes under permissive terms (BSD/Apache/CC BY, no NC/SA/GPL clause) per the licence
# column of train/README.md, for the permissive-only variant of the weights.
# Left out on purpose: Flickr photo sets (per-image CC, some NC), GPL/AGPL and NC/research-only
# sets.
PERMISSIVE_SCENES = ["aliked_tum", "dim_cyprus", "gtsfm_hilti_exp4"]


def scene_model_dir(scene: str) -> Path:
    """The COLMAP model of a scene: train/<scene>/colmap, or a reference model for lund_door."""
    root = shared_data_dir()
    if scene == "lund_door_gtsfm":
        return root / "lund_door_gtsfm" / "colmap_ground_truth"
    return root / "train" / scene / "colmap"


def scene_image_dir(scene: str) -> Path:
    root = shared_data_dir()
    return (
        root / scene / "images" if scene == "lund_door_gtsfm" else root / "train" / scene / "images"
    )


def all_scenes() -> list[str]:
    """Every scene with a model: the 20 training scenes and lund_door's reference model."""
    train = sorted(p.parent.name for p in (shared_data_dir() / "train").glob("*/colmap"))
    return train + (["lund_door_gtsfm"] if scene_model_dir("lund_door_gtsfm").exists() else [])


@dataclass
class SfmImage:
    scene: str
    name: str
    path: Path
    width: int
    height: int
    K: np.ndarray
    R: np.ndarray  # world-to-camera
    t: np.ndarray
    camera: pycolmap.Camera = field(repr=False)


@dataclass
class SfmPair:
    scene: str
    a: str
    b: str
    F: np.ndarray  # (3, 3), ideal pixels of the stored images: x_b^T F x_a = 0
    xy_a: np.ndarray  # (N, 2) observed pixels of the shared tracks in A
    xy_b: np.ndarray  # (N, 2) the same tracks in B

    @property
    def n_shared(self) -> int:
        return len(self.xy_a)


@dataclass
class SfmScene:
    name: str
    images: dict[str, SfmImage]
    pairs: list[SfmPair]


def load_scene(scene: str, min_shared: int = 30) -> SfmScene:
    """Registered images, and positive pairs (≥ ``min_shared`` common 3D points) with F and GT
    matches."""
    rec = pycolmap.Reconstruction(str(scene_model_dir(scene)))
    image_dir = scene_image_dir(scene)
    images: dict[str, SfmImage] = {}
    obs: dict[int, dict[int, np.ndarray]] = {}  # image_id -> point3D_id -> xy
    id_to_name = {}
    for image_id, im in rec.images.items():
        if not im.has_pose:
            continue
        cam = rec.cameras[im.camera_id]
        pose = im.cam_from_world()
        images[im.name] = SfmImage(
            scene,
            im.name,
            image_dir / im.name,
            cam.width,
            cam.height,
            cam.calibration_matrix(),
            pose.rotation.matrix(),
            np.asarray(pose.translation),
            cam,
        )
        id_to_name[image_id] = im.name
        obs[image_id] = {p.point3D_id: np.asarray(p.xy) for p in im.points2D if p.has_point3D()}
    ids = sorted(obs)
    pairs = []
    for i, ia in enumerate(ids):
        pa = obs[ia]
        for ib in ids[i + 1 :]:
            pb = obs[ib]
            shared = sorted(set(pa) & set(pb))
            if len(shared) < min_shared:
                continue
            A, B = images[id_to_name[ia]], images[id_to_name[ib]]
            F = fundamental_from_poses(A.K, A.R, A.t, B.K, B.R, B.t)
            pairs.append(
                SfmPair(
                    scene,
                    A.name,
                    B.name,
                    F,
                    np.stack([pa[k] for k in shared]),
                    np.stack([pb[k] for k in shared]),
                )
            )
    logger.debug(
        "Scene %s: %d images, %d positive pairs (>= %d shared points).",
        scene,
        len(images),
        len(pairs),
        min_shared,
    )
    return SfmScene(scene, images, pairs)


def subset_scene(scene: SfmScene, n: int) -> SfmScene:
    """At most n images, taken from the pairs with the most shared points
    (keeps pairs available)."""
    keep: list[str] = []
    for p in sorted(scene.pairs, key=lambda p: -p.n_shared):
        for name in (p.a, p.b):
            if name not in keep and len(keep) < n:
                keep.append(name)
    images = {k: scene.images[k] for k in keep}
    pairs = [p for p in scene.pairs if p.a in images and p.b in images]
    return SfmScene(scene.name, images, pairs)
