"""Training data for the coarse network (paper §4.3), from COLMAP models and from single photos.

Sources
* SfM pairs, as the paper's MegaDepth use: every scene is a ``pycolmap.Reconstruction``; positive pairs
  are registered images sharing at least ``min_shared`` (30) 3D points; the fundamental matrix comes from
  the calibrations and poses (x_B^T F x_A = 0); ground-truth point matches are the two observations of
  each shared track. Negatives pair images of two different scenes (half of each batch for the image
  and epipolar supervisions).
* Synthetic pairs from single photos: B is a random homography warp (rotation, scale, perspective,
  crop) of A, so every point has an exact match. A homography does not determine a fundamental
  matrix; we use the plane-induced one, F = [e']_× H, with a random virtual epipole e' (as if the
  camera had also moved along a random direction while looking at a plane): every true
  correspondence satisfies x_B^T F x_A = x_B·(e' × H x_A) = 0, so the epipolar loss gets the same
  weak, line-only supervision as on real pairs, and the point loss gets the exact matches.

Coordinates. COLMAP's: (0, 0) is the top-left corner of the top-left pixel. The models of the training
scenes are in the frame of the stored (downscaled) images. A training image is resized to at most
``resolution`` px on its long side with both sides multiples of the stride; this maps x_train =
(sx·x, sy·y), a pure scale in the corner convention. Lens distortion: F is defined on ideal
(undistorted) pinhole pixels, so the feature-cell centres used by the epipolar loss are undistorted
with the camera model before F is applied (``ideal_xy``); observed keypoints are used as they are for
point supervision and PCK.

Archival augmentation (``colmap_guided.archival``) is applied to training images; with a frozen
backbone the features of ``n_variants`` versions of each image (version 0 clean, the others degraded
with a seed derived from the image name) are cached in an HDF5 file, and every draw picks a version.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import h5py
import numpy as np
import pycolmap
import torch
from tqdm import tqdm

from colmap_guided import archival, paths
from colmap_guided.coarse.backbone import BACKBONES, build_backbone
from colmap_guided.coarse.geometry import ImageGeometry, resize_geometry, resize_image, stack_padded
from colmap_guided.conf import merge_conf
from colmap_guided.images import read_image
from colmap_guided.log import logger
from colmap_guided.paths import shared_data_dir

# Whole scenes held out for validation (the evaluation issue reports on them) ...
VAL_SCENES = ["strecha_castle", "strecha_entry_P10", "instantngp_fox", "lund_door_gtsfm"]
# Training scenes under permissive terms (BSD/Apache/CC BY, no NC/SA/GPL clause) per the licence
# column of train/README.md, for the permissive-only variant of the weights (issue 7, item 5).
# Left out on purpose: Flickr photo sets (per-image CC, some NC), GPL/AGPL and NC/research-only sets.
PERMISSIVE_SCENES = ["aliked_tum", "dim_cyprus", "gtsfm_hilti_exp4"]


def scene_model_dir(scene: str) -> Path:
    """The COLMAP model of a scene: train/<scene>/colmap, or a reference model for lund_door."""
    root = shared_data_dir()
    if scene == "lund_door_gtsfm":
        return root / "lund_door_gtsfm" / "colmap_ground_truth"
    return root / "train" / scene / "colmap"


def scene_image_dir(scene: str) -> Path:
    root = shared_data_dir()
    return root / scene / "images" if scene == "lund_door_gtsfm" else root / "train" / scene / "images"


def all_scenes() -> list[str]:
    """Every scene with a model: the 20 training scenes and lund_door's reference model."""
    train = sorted(p.parent.name for p in (shared_data_dir() / "train").glob("*/colmap"))
    return train + (["lund_door_gtsfm"] if scene_model_dir("lund_door_gtsfm").exists() else [])


# ----------------------------------------------------------------------------------------- geometry
def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=np.float64)


def fundamental_from_poses(K_a, R_a, t_a, K_b, R_b, t_b) -> np.ndarray:
    """F with x_B^T F x_A = 0 for ideal pixels, from world-to-camera poses (R, t) and intrinsics.

    Relative pose B←A: R = R_b R_a^T, t = t_b − R t_a; E = [t]_× R; F = K_b^{-T} E K_a^{-1},
    normalised to unit Frobenius norm.
    """
    R = R_b @ R_a.T
    t = t_b - R @ t_a
    F = np.linalg.inv(K_b).T @ skew(t) @ R @ np.linalg.inv(K_a)
    return F / np.linalg.norm(F)


def scale_fundamental(F: np.ndarray, scale_a, scale_b) -> np.ndarray:
    """F in frames scaled by (sx, sy) per image: F' = S_b^{-T} F S_a^{-1}."""
    Sa_inv = np.diag([1.0 / scale_a[0], 1.0 / scale_a[1], 1.0])
    Sb_inv = np.diag([1.0 / scale_b[0], 1.0 / scale_b[1], 1.0])
    return Sb_inv.T @ F @ Sa_inv


def induced_fundamental(H: np.ndarray, epipole_b: np.ndarray) -> np.ndarray:
    """Plane-induced F = [e']_× H (Hartley & Zisserman, result 13.3): x_B^T F x_A = 0 if x_B ~ H x_A."""
    F = skew(epipole_b) @ H
    return F / np.linalg.norm(F)


def colmap_to_cv(H: np.ndarray) -> np.ndarray:
    """A homography between COLMAP pixel frames → the same map in OpenCV's (centre-at-integer) frames."""
    T = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1.0]])
    return np.linalg.inv(T) @ H @ T


def apply_h(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    p = np.concatenate([pts, np.ones((len(pts), 1))], 1) @ H.T
    return p[:, :2] / p[:, 2:3]


def ideal_pixels(camera: pycolmap.Camera, xy: np.ndarray) -> np.ndarray:
    """Undistort observed pixels (N, 2) to the ideal pinhole pixels of the same calibration matrix."""
    if camera.model_name in ("SIMPLE_PINHOLE", "PINHOLE"):
        return xy.astype(np.float64)
    normalized = camera.cam_from_img(np.ascontiguousarray(xy, dtype=np.float64))
    K = camera.calibration_matrix()
    return normalized @ K[:2, :2].T + K[:2, 2]


# ------------------------------------------------------------------------------------------- scenes
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
    """Registered images, and positive pairs (≥ ``min_shared`` common 3D points) with F and GT matches."""
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
            scene, im.name, image_dir / im.name, cam.width, cam.height, cam.calibration_matrix(),
            pose.rotation.matrix(), np.asarray(pose.translation), cam,
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
            pairs.append(SfmPair(scene, A.name, B.name, F, np.stack([pa[k] for k in shared]), np.stack([pb[k] for k in shared])))
    logger.debug("Scene %s: %d images, %d positive pairs (>= %d shared points).", scene, len(images), len(pairs), min_shared)
    return SfmScene(scene, images, pairs)


# ---------------------------------------------------------------------------------- synthetic pairs
def random_homography(width: int, height: int, out_w: int, out_h: int, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """Random H (COLMAP frames) from a (width, height) photo to an (out_w, out_h) view of it.

    A random crop (35–100 % of the area) of the photo is rotated (±30°·strength), its corners moved by
    up to 12 %·strength of its size (perspective), and fitted into the output frame.
    """
    frac = np.sqrt(rng.uniform(0.35, 1.0))
    cw, ch = width * frac, height * frac
    cx = rng.uniform(cw / 2, width - cw / 2)
    cy = rng.uniform(ch / 2, height - ch / 2)
    src = np.array([[cx - cw / 2, cy - ch / 2], [cx + cw / 2, cy - ch / 2], [cx + cw / 2, cy + ch / 2], [cx - cw / 2, cy + ch / 2]])
    angle = np.deg2rad(rng.uniform(-30, 30) * strength)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    src = (src - [cx, cy]) @ rot.T + [cx, cy]
    src = src + rng.uniform(-0.12, 0.12, size=(4, 2)) * [cw, ch] * strength
    dst = np.array([[0, 0], [out_w, 0], [out_w, out_h], [0, out_h]], dtype=np.float64)
    H = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32)).astype(np.float64)
    return H  # photo pixels -> output pixels (corners of the crop -> corners of the output)


def warp_image(image: np.ndarray, H: np.ndarray, out_w: int, out_h: int) -> np.ndarray:
    """Warp with H given between COLMAP frames (pixel centres at +0.5); black outside the photo.

    When H shrinks the photo, it is first downscaled with area averaging (no aliasing) and H adapted.
    """
    h, w = image.shape[:2]
    centre = np.array([[w / 2, h / 2], [w / 2 + 1, h / 2], [w / 2, h / 2 + 1]])
    m = apply_h(H, centre)
    scale = np.sqrt(abs(np.cross(m[1] - m[0], m[2] - m[0])))  # local linear scale of H
    if scale < 0.8:
        small = cv2.resize(image, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
        S = np.diag([small.shape[1] / w, small.shape[0] / h, 1.0])
        image, H = small, H @ np.linalg.inv(S)
    return cv2.warpPerspective(image, colmap_to_cv(H), (out_w, out_h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def random_epipole(width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """A virtual epipole for the plane-induced F: at infinity (sideways motion) or outside/inside the
    image (forward motion), so epipolar lines take varied directions."""
    angle = rng.uniform(0, 2 * np.pi)
    if rng.random() < 0.5:
        return np.array([np.cos(angle), np.sin(angle), 0.0])
    r = rng.uniform(0.0, 2.0) * max(width, height)
    return np.array([width / 2 + r * np.cos(angle), height / 2 + r * np.sin(angle), 1.0])


def variant_seed(*keys) -> int:
    """Stable seed from names (Python's hash() is salted per process)."""
    return zlib.crc32("/".join(map(str, keys)).encode())


# ------------------------------------------------------------------------------------ views & cache
@dataclass
class View:
    """One network input: a (possibly degraded) stored image or a synthetic warp of one."""

    key: str  # "img/<scene>/<name>/v<k>" (k = 0 clean, k > 0 archival) or "syn/<scene>/<name>/h<k>"
    scene: str
    name: str
    geometry: ImageGeometry
    xy_ideal: np.ndarray  # (gh, gw, 2) cell centres in the resized frame, undistorted (frame of F)
    H: np.ndarray | None = None  # synthetic views: source photo's original pixels -> this view's pixels
    window: tuple[int, int, int, int] | None = None  # training crop of the grid: (row0, col0, rows, cols)

    @property
    def grid(self) -> tuple[int, int, int, int]:
        """(row0, col0, rows, cols) of the cells the network sees (the whole grid without a window)."""
        g = self.geometry
        return self.window if self.window is not None else (0, 0, g.grid_height, g.grid_width)

    def crop(self, array):
        """Crop a (..., gh, gw) array or tensor of this view's full grid to its window."""
        r0, c0, h, w = self.grid
        return array[..., r0 : r0 + h, c0 : c0 + w]

    def crop_xy(self) -> np.ndarray:
        r0, c0, h, w = self.grid
        return self.xy_ideal[r0 : r0 + h, c0 : c0 + w]


@dataclass
class PairSample:
    """A training or validation pair, everything in numpy; ``collate`` turns a list into tensors."""

    a: View
    b: View
    positive: bool
    source: str  # 'sfm', 'synthetic' or 'negative'
    F: np.ndarray  # (3, 3) resized frames: xy_b^T F xy_a = 0 for the centres in View.xy_ideal
    pts_a: np.ndarray  # (N, 2) ground-truth matches in original pixels of a's geometry (N may be 0)
    pts_b: np.ndarray

    def swapped(self) -> "PairSample":
        return PairSample(self.b, self.a, self.positive, self.source, self.F.T.copy(), self.pts_b, self.pts_a)


def _plain_centres(geometry: ImageGeometry) -> np.ndarray:
    """Cell centres in the resized frame, (gh, gw, 2)."""
    return (geometry.cell_centers() * geometry.scale).reshape(geometry.grid_height, geometry.grid_width, 2)


class FeatureCache:
    """HDF5 file of frozen-backbone features, one float16 (C, gh, gw) dataset per view key.

    ``put_many`` opens, writes and closes the file for each chunk, so that a run killed while
    computing loses at most the current chunk; everything read is kept in memory (a few hundred MB
    for all training views at 400 px).
    """

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._memory: dict[str, np.ndarray] = {}
        self._keys: set[str] | None = None

    def keys(self) -> set[str]:
        if self._keys is None:
            self._keys = set()
            if self.path.exists():
                with h5py.File(self.path, "r") as f:
                    f.visit(lambda name: self._keys.add(name) if isinstance(f[name], h5py.Dataset) else None)
        return self._keys

    def __contains__(self, key: str) -> bool:
        return key in self._memory or key in self.keys()

    def put_many(self, items: dict[str, np.ndarray]) -> None:
        with h5py.File(self.path, "a") as f:
            for key, features in items.items():
                if key in f:
                    del f[key]
                f.create_dataset(key, data=features.astype(np.float16))
                self._memory[key] = features.astype(np.float16)
                self.keys().add(key)

    def get(self, key: str) -> np.ndarray:
        if key not in self._memory:
            with h5py.File(self.path, "r") as f:
                self._memory[key] = f[key][()]
        return self._memory[key]

    def load_all(self, keys) -> None:
        """Read many entries in one opening of the file."""
        missing = [k for k in keys if k not in self._memory]
        if missing:
            with h5py.File(self.path, "r") as f:
                for k in missing:
                    self._memory[k] = f[k][()]


class CoarseTrainData:
    """Scenes, views, positive/negative pairs, the feature cache, and a seeded batch sampler."""

    default_conf = {
        "backbone": "efficientnet-lite0",
        "resolution": 400,  # long side of training images (paper: 401 px), multiple of the stride
        "min_shared": 30,  # positive pair: at least this many common 3D points (paper §4.3)
        "train_scenes": None,  # None: every scene with a model except val_scenes
        "val_scenes": VAL_SCENES,
        "max_images_per_scene": None,  # small subsets for smoke tests
        "n_variants": 2,  # cached versions of each image: 0 clean, 1.. archival
        "archival_prob": 0.5,  # chance that a side of a pair is an archival version
        "archival_strength": 1.0,
        "n_synthetic": 1,  # homography views cached per training photo
        "synthetic_ratio": 0.3,  # share of positives that are synthetic homography pairs
        "homography_strength": 1.0,
        "max_matches": 256,  # ground-truth matches kept per pair (point loss, PCK)
        "val_pairs_per_scene": 16,
        "max_cells": None,  # training crop: at most this many cells per grid side (CPU budget), see crop_sample
        "cache_dir": None,  # default: ~/.cache/colmap_guided/train_features ($COLMAP_GUIDED_CACHE)
    }

    def __init__(self, conf: dict | None = None):
        self.conf = c = merge_conf(self.default_conf, conf, "data")
        self.spec = BACKBONES[c["backbone"]]
        val = list(c["val_scenes"])
        train = c["train_scenes"] if c["train_scenes"] is not None else [s for s in all_scenes() if s not in val]
        overlap = set(train) & set(val)
        if overlap:
            raise ValueError(f"Scenes both in training and validation: {sorted(overlap)}")
        self.train_scenes, self.val_scenes = list(train), val
        self.scenes: dict[str, SfmScene] = {}
        for name in self.train_scenes + self.val_scenes:
            scene = load_scene(name, c["min_shared"])
            if c["max_images_per_scene"]:
                scene = _subset(scene, c["max_images_per_scene"])
            self.scenes[name] = scene
        self.train_scenes = [s for s in self.train_scenes if self.scenes[s].pairs]
        if not self.train_scenes:
            raise ValueError("No training scene has a positive pair")
        self.views: dict[str, View] = {}
        for name, scene in self.scenes.items():
            n_var = c["n_variants"] if name in self.train_scenes else 1
            for im in scene.images.values():
                for k in range(n_var):
                    self._image_view(im, k)
                if name in self.train_scenes:
                    for k in range(c["n_synthetic"]):
                        self._synthetic_view(im, k)
        self.val_samples = self._make_val_samples()
        cache_dir = Path(c["cache_dir"]) if c["cache_dir"] else paths.cache_dir("train_features")
        tag = f"{c['backbone']}_l2_r{c['resolution']}_a{c['archival_strength']:g}_h{c['homography_strength']:g}"
        self.cache = FeatureCache(cache_dir / f"{tag}.h5")
        n_pairs = sum(len(self.scenes[s].pairs) for s in self.train_scenes)
        logger.info(
            "Training data: %d scenes, %d positive pairs, %d views; validation: %d scenes, %d pairs.",
            len(self.train_scenes), n_pairs, len(self.views), len(self.val_scenes), len(self.val_samples),
        )

    # -------------------------------------------------------------------------------- views
    def geometry_of(self, width: int, height: int) -> ImageGeometry:
        return resize_geometry(width, height, self.conf["resolution"], self.spec.stride, self.spec.cell_offset)

    def _image_view(self, im: SfmImage, k: int) -> View:
        key = f"img/{im.scene}/{im.name}/v{k}"
        if key not in self.views:
            geom = self.geometry_of(im.width, im.height)
            centres = geom.cell_centers()  # original pixels
            ideal = ideal_pixels(im.camera, centres) * geom.scale
            self.views[key] = View(key, im.scene, im.name, geom, ideal.reshape(geom.grid_height, geom.grid_width, 2))
        return self.views[key]

    def _synthetic_view(self, im: SfmImage, k: int) -> View:
        key = f"syn/{im.scene}/{im.name}/h{k}"
        if key not in self.views:
            src = self.geometry_of(im.width, im.height)
            out_w, out_h = src.resized_width, src.resized_height
            rng = np.random.default_rng(variant_seed(key))
            H = random_homography(im.width, im.height, out_w, out_h, rng, self.conf["homography_strength"])
            geom = ImageGeometry(out_w, out_h, out_w, out_h, self.spec.stride, self.spec.cell_offset)
            self.views[key] = View(key, im.scene, im.name, geom, _plain_centres(geom), H)
        return self.views[key]

    def render(self, key: str) -> np.ndarray:
        """The resized uint8 RGB network input of a view (deterministic: seeds come from the key)."""
        view = self.views[key]
        im = self.scenes[view.scene].images[view.name]
        rgb = read_image(im.path)
        if (rgb.shape[1], rgb.shape[0]) != (im.width, im.height):
            raise ValueError(f"{im.path} is {rgb.shape[1]}x{rgb.shape[0]}, its model says {im.width}x{im.height}")
        kind, k = key.split("/")[0], int(key.rsplit("/", 1)[1][1:])
        if kind == "img":
            out = resize_image(rgb, view.geometry)
            if k > 0:
                out = archival.degrade(out, np.random.default_rng(variant_seed(key)), self.conf["archival_strength"])
            return out
        out = warp_image(rgb, view.H, view.geometry.resized_width, view.geometry.resized_height)
        rng = np.random.default_rng(variant_seed(key, "archival"))
        if rng.random() < self.conf["archival_prob"]:
            out = archival.degrade(out, rng, self.conf["archival_strength"])
        return out

    def build_cache(self, backbone: torch.nn.Module | None = None, keys: list[str] | None = None) -> int:
        """Compute and store the frozen-backbone features of every view missing from the cache."""
        keys = [k for k in (keys or sorted(self.views)) if k not in self.cache]
        if not keys:
            return 0
        backbone = backbone if backbone is not None else build_backbone(self.conf["backbone"])
        backbone.eval()
        logger.info("Caching backbone features of %d views in %s ...", len(keys), self.cache.path)
        chunk: dict[str, np.ndarray] = {}
        for i, key in enumerate(tqdm(keys, desc="features", mininterval=10, disable=len(keys) < 20)):
            rgb = self.render(key)
            x = torch.from_numpy(rgb).permute(2, 0, 1).float()[None]
            with torch.inference_mode():
                chunk[key] = backbone(backbone.normalize(x))[0].numpy()
            if len(chunk) == 25 or i == len(keys) - 1:
                self.cache.put_many(chunk)
                chunk = {}
        return len(keys)

    def features(self, key: str) -> torch.Tensor:
        return torch.from_numpy(self.cache.get(key).astype(np.float32))

    # -------------------------------------------------------------------------------- pairs
    def sfm_sample(self, pair: SfmPair, va: int = 0, vb: int = 0, rng: np.random.Generator | None = None) -> PairSample:
        scene = self.scenes[pair.scene]
        a = self._image_view(scene.images[pair.a], va)
        b = self._image_view(scene.images[pair.b], vb)
        F = scale_fundamental(pair.F, a.geometry.scale, b.geometry.scale)
        pts_a, pts_b = pair.xy_a, pair.xy_b
        m = self.conf["max_matches"]
        if len(pts_a) > m:
            idx = (rng if rng is not None else np.random.default_rng(0)).choice(len(pts_a), m, replace=False)
            pts_a, pts_b = pts_a[idx], pts_b[idx]
        return PairSample(a, b, True, "sfm", F, pts_a, pts_b)

    def synthetic_sample(self, image: SfmImage, k: int, va: int, rng: np.random.Generator) -> PairSample:
        a = self._image_view(image, va)
        b = self._synthetic_view(image, k)
        Ha = b.H @ np.diag([1 / a.geometry.scale[0], 1 / a.geometry.scale[1], 1.0])  # A resized -> B
        F = induced_fundamental(Ha, random_epipole(b.geometry.width, b.geometry.height, rng))
        # Exact matches: A's cell centres seen in B, and B's cell centres seen in A (inside both images).
        ca = a.geometry.cell_centers()
        cb = b.geometry.cell_centers()
        ca_b = apply_h(b.H, ca)
        cb_a = apply_h(np.linalg.inv(b.H), cb)
        in_b = _inside(ca_b, b.geometry)
        in_a = _inside(cb_a, a.geometry)
        pts_a = np.concatenate([ca[in_b], cb_a[in_a]])
        pts_b = np.concatenate([ca_b[in_b], cb[in_a]])
        m = self.conf["max_matches"]
        if len(pts_a) > m:
            idx = rng.choice(len(pts_a), m, replace=False)
            pts_a, pts_b = pts_a[idx], pts_b[idx]
        # xy_ideal of an image view is undistorted; H relates observed pixels, so use plain centres.
        a_plain = View(a.key, a.scene, a.name, a.geometry, _plain_centres(a.geometry))
        return PairSample(a_plain, b, True, "synthetic", F, pts_a, pts_b)

    def negative_sample(self, rng: np.random.Generator) -> PairSample:
        s1, s2 = rng.choice(len(self.train_scenes), 2, replace=False)
        views = []
        for s in (s1, s2):
            scene = self.scenes[self.train_scenes[s]]
            names = sorted(scene.images)
            im = scene.images[names[rng.integers(len(names))]]
            views.append(self._image_view(im, self._variant(rng)))
        empty = np.zeros((0, 2))
        return PairSample(views[0], views[1], False, "negative", np.zeros((3, 3)), empty, empty)

    def _variant(self, rng: np.random.Generator) -> int:
        n = self.conf["n_variants"]
        return int(rng.integers(1, n)) if n > 1 and rng.random() < self.conf["archival_prob"] else 0

    def sample_batch(self, rng: np.random.Generator, batch_size: int, n_negative: int) -> list[PairSample]:
        """``batch_size`` pairs: ``n_negative`` negatives, the rest positives (a share synthetic)."""
        c = self.conf
        samples = []
        for i in range(batch_size):
            if i < n_negative and len(self.train_scenes) > 1:
                samples.append(self.negative_sample(rng))
                continue
            scene = self.scenes[self.train_scenes[rng.integers(len(self.train_scenes))]]
            if c["n_synthetic"] > 0 and rng.random() < c["synthetic_ratio"]:
                names = sorted(scene.images)
                im = scene.images[names[rng.integers(len(names))]]
                s = self.synthetic_sample(im, int(rng.integers(c["n_synthetic"])), self._variant(rng), rng)
            else:
                pair = scene.pairs[rng.integers(len(scene.pairs))]
                s = self.sfm_sample(pair, self._variant(rng), self._variant(rng), rng)
            samples.append(s.swapped() if rng.random() < 0.5 else s)
        if c["max_cells"]:
            samples = [crop_sample(s, c["max_cells"], rng) for s in samples]
        return samples

    def _make_val_samples(self) -> list[PairSample]:
        """Fixed validation pairs: up to ``val_pairs_per_scene`` per held-out scene, clean images."""
        rng = np.random.default_rng(12345)
        out = []
        for name in self.val_scenes:
            pairs = self.scenes[name].pairs
            n = min(len(pairs), self.conf["val_pairs_per_scene"])
            for i in sorted(rng.choice(len(pairs), n, replace=False)) if n else []:
                out.append(self.sfm_sample(pairs[i], 0, 0, np.random.default_rng(i)))
        return out


def crop_sample(sample: PairSample, max_cells: int, rng: np.random.Generator) -> PairSample:
    """Crop both feature grids to at most ``max_cells`` per side, keeping the feature scale.

    The 4D filter is what costs on a CPU (its work grows with the fourth power of the grid side), so
    training can see windows of the native-resolution grids instead of downscaled images. For a
    positive pair both windows are centred (with a random jitter of a quarter window) on the two
    cells of one random ground-truth match, so they overlap in the scene; negatives get random windows.
    F, the cell centres and the GT matches stay in the full resized frames (collate crops them).
    """
    def window(view: View, centre) -> tuple[int, int, int, int]:
        g = view.geometry
        h, w = min(max_cells, g.grid_height), min(max_cells, g.grid_width)
        if centre is None:
            r0 = int(rng.integers(0, g.grid_height - h + 1))
            c0 = int(rng.integers(0, g.grid_width - w + 1))
        else:
            col, row = centre + rng.uniform(-0.25, 0.25, 2) * [w, h]
            r0 = int(np.clip(round(row - (h - 1) / 2), 0, g.grid_height - h))
            c0 = int(np.clip(round(col - (w - 1) / 2), 0, g.grid_width - w))
        return r0, c0, h, w

    ca = cb = None
    if sample.positive and len(sample.pts_a):
        i = int(rng.integers(len(sample.pts_a)))
        ca = sample.a.geometry.pixel_to_cell(sample.pts_a[i : i + 1])[0]
        cb = sample.b.geometry.pixel_to_cell(sample.pts_b[i : i + 1])[0]
    a = replace(sample.a, window=window(sample.a, ca))
    b = replace(sample.b, window=window(sample.b, cb))
    return replace(sample, a=a, b=b)


def _inside(xy: np.ndarray, geometry: ImageGeometry) -> np.ndarray:
    return (xy[:, 0] >= 0) & (xy[:, 1] >= 0) & (xy[:, 0] < geometry.width) & (xy[:, 1] < geometry.height)


def _subset(scene: SfmScene, n: int) -> SfmScene:
    """At most n images, taken from the pairs with the most shared points (keeps pairs available)."""
    keep: list[str] = []
    for p in sorted(scene.pairs, key=lambda p: -p.n_shared):
        for name in (p.a, p.b):
            if name not in keep and len(keep) < n:
                keep.append(name)
    images = {k: scene.images[k] for k in keep}
    pairs = [p for p in scene.pairs if p.a in images and p.b in images]
    return SfmScene(scene.name, images, pairs)


def _cells(view: View, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) in the view's window of the cell nearest to each point (original pixels), and
    whether that cell lies inside the window."""
    g = view.geometry
    cr = np.rint(g.pixel_to_cell(pts)).astype(np.int64)
    col = cr[:, 0].clip(0, g.grid_width - 1)
    row = cr[:, 1].clip(0, g.grid_height - 1)
    r0, c0, h, w = view.grid
    row, col = row - r0, col - c0
    return row, col, (row >= 0) & (row < h) & (col >= 0) & (col < w)


def collate(samples: list[PairSample], data: CoarseTrainData | None = None, with_features: bool = True) -> dict:
    """Tensors for a batch: padded features and masks, F, cell centres, GT cell matches, labels.

    Views with a window are cropped to it. Flat cell indices of ``matches`` (row * width + col) use the
    padded grid width of the batch, as the losses expect; GT matches outside a window are dropped.
    """
    out: dict = {"samples": samples, "positive": torch.tensor([s.positive for s in samples])}
    if with_features:
        out["feat_a"], out["mask_a"] = stack_padded([s.a.crop(data.features(s.a.key)) for s in samples])
        out["feat_b"], out["mask_b"] = stack_padded([s.b.crop(data.features(s.b.key)) for s in samples])
    ha = max(s.a.grid[2] for s in samples)
    wa = max(s.a.grid[3] for s in samples)
    hb = max(s.b.grid[2] for s in samples)
    wb = max(s.b.grid[3] for s in samples)
    n = len(samples)
    xy_a = torch.zeros(n, ha, wa, 2, dtype=torch.float64)
    xy_b = torch.zeros(n, hb, wb, 2, dtype=torch.float64)
    k = max([len(s.pts_a) for s in samples] + [1])
    matches = torch.full((n, k, 2), -1, dtype=torch.long)
    for i, s in enumerate(samples):
        xa, xb = s.a.crop_xy(), s.b.crop_xy()
        xy_a[i, : xa.shape[0], : xa.shape[1]] = torch.from_numpy(np.ascontiguousarray(xa))
        xy_b[i, : xb.shape[0], : xb.shape[1]] = torch.from_numpy(np.ascontiguousarray(xb))
        if len(s.pts_a):
            ra, ca, ina = _cells(s.a, s.pts_a)
            rb, cb, inb = _cells(s.b, s.pts_b)
            keep = ina & inb
            m = int(keep.sum())
            matches[i, :m, 0] = torch.from_numpy(ra[keep] * wa + ca[keep])
            matches[i, :m, 1] = torch.from_numpy(rb[keep] * wb + cb[keep])
    out.update(F=torch.from_numpy(np.stack([s.F for s in samples])), xy_a=xy_a, xy_b=xy_b, matches=matches)
    return out
