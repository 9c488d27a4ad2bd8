"""The synthetic landmark: its layout (hall, tower, annex, stone blocks, plaza, field, tree line),
the cameras around it, and ``render_scene`` writing photos, depth maps and the ground-truth COLMAP
model."""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

from colmap_guided.conf import merge_conf
from colmap_guided.log import logger
from colmap_guided.workspace import Workspace

from . import textures
from .render import Polygon, Texture, make_texture, render_image

default_conf = {
    "focal_factor": 1.1,  # focal length in pixels / image width
    "arc_step_deg": 14.0,  # azimuth step between consecutive cameras
    # Varied distance, height and aim keep the cameras off a pure orbit around one point: an orbit
    # is a critical motion for self-calibration, and COLMAP's focal lengths and rotations drift
    # on it.
    "radius": (20.0, 28.0),  # camera distance from the hall's centre, metres
    "camera_height": (1.5, 7.0),  # metres above the ground
    "target_jitter": 2.0,  # metres of random offset of the look-at point
    "max_roll_deg": 3.0,
    "supersample": 2,
    "jpeg_quality": 92,
    # write camera make/model and the focal length (35 mm equivalent) like a camera does
    "exif": True,
    "noise_sigma": 1.2,  # sensor noise, grey levels
    "texels_per_m": 100.0,  # texture resolution of the buildings
    # the hall's length and width, metres; the tower (half as wide as the hall) stands through its
    # west gable, the annex (1 m shorter than half the hall) against its south wall
    "hall_size": (12.0, 8.0),
}


@dataclass
class SceneInfo:
    """Where a rendered scene lies and its ground truth (poses map world to camera: x_cam = R x +
    t)."""

    image_dir: Path
    gt_dir: Path
    depth_dir: Path
    names: list[str]
    K: np.ndarray
    width: int
    height: int
    cam_from_world: dict[str, tuple[np.ndarray, np.ndarray]]

    def depth(self, name: str) -> np.ndarray:
        """Depth map of one image (metres along the optical axis, 0 where unknown)."""
        return np.load(self.depth_dir / f"{Path(name).stem}.npy")


_UP = np.array([0.0, 0.0, 1.0])
_STONE = (0.7, 0.66, 0.6)


def _wall(p0, p1, height: float, tex: Texture, shade: float, gable: float | None = None) -> Polygon:
    """A vertical wall on the ground from p0 to p1 (x, y), facing right of p0 -> p1, so walls listed
    counter-clockwise seen from above face outwards; ``gable`` adds an apex at that height
    mid-wall."""
    p0, p1 = np.array([*p0, 0.0]), np.array([*p1, 0.0])
    length = float(np.linalg.norm(p1 - p0))
    top = gable if gable is not None else height
    verts = [(0, top - height), (length, top - height), (length, top), (0, top)]
    if gable is not None:
        verts.insert(1, (length / 2, 0.0))
    return Polygon(p0 + top * _UP, (p1 - p0) / length, -_UP, np.array(verts, float), tex, shade)


def _roof_face(eave0, eave1, high, tex: Texture, shade_of, triangle: bool) -> Polygon:
    """A roof face above the eave eave0 -> eave1 (counter-clockwise seen from above) rising to
    ``high``: the ridge end above eave1 (a rectangle) or the apex (a triangle)."""
    a, b, c = (np.array(p, float) for p in (eave0, eave1, high))
    length = float(np.linalg.norm(b - a))
    u = (b - a) / length
    up_slope = c - a - ((c - a) @ u) * u
    rise = float(np.linalg.norm(up_slope))
    v = -up_slope / rise  # texture rows run down the slope from the ridge
    if triangle:
        verts = [(float((c - a) @ u), 0.0), (length, rise), (0.0, rise)]
    else:
        verts = [(0.0, 0.0), (length, 0.0), (length, rise), (0.0, rise)]
    poly = Polygon(a + up_slope, u, v, np.array(verts, float), tex)
    poly.shade = shade_of(poly.normal)
    return poly


def _flat_top(
    x0: float, y0: float, x1: float, y1: float, z: float, tex: Texture, shade: float
) -> Polygon:
    """A horizontal rectangle facing up."""
    verts = np.array([(0, 0), (x1 - x0, 0), (x1 - x0, y1 - y0), (0, y1 - y0)], float)
    return Polygon(
        np.array([x0, y1, z]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0]), verts, tex, shade
    )


def _box_walls(box: tuple, height: float, make_tex, shade_of, gables=(None,) * 4) -> list[Polygon]:
    """The four walls (south, east, north, west) of an axis-aligned box (x0, y0, x1, y1) standing
    on the ground, each with an apex at its ``gables`` height if given."""
    x0, y0, x1, y1 = box
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    walls = []
    for p0, p1, gable in zip(corners, corners[1:] + corners[:1], gables):
        length = math.dist(p0, p1)
        normal = np.array([p1[1] - p0[1], p0[0] - p1[0], 0.0]) / length
        tex = make_tex(length, gable or height, height)
        walls.append(_wall(p0, p1, height, tex, shade_of(normal), gable))
    return walls


class _Materials:
    """The sun's shading and the textures of one scene, drawn from ``rng`` in the order built."""

    def __init__(
        self, rng: np.random.Generator, ppm: float, repeated: bool, style: int | None = None
    ):
        self.rng, self.ppm = rng, ppm
        sun_az = rng.uniform(0, 2 * np.pi)
        self.sun = np.array([np.cos(sun_az) * 0.75, np.sin(sun_az) * 0.75, 0.66])
        self.motif = None
        if repeated:  # the style's window where given; the rest of the scene is drawn as without
            motif_seed = rng.integers(2**32)
            motif_rng = np.random.default_rng(motif_seed if style is None else style)
            self.motif = textures.window_motif(motif_rng, ppm)
        self.up_shade = self.shade_of(_UP)

    def shade_of(self, normal: np.ndarray) -> float:
        """Brightness of a face with this outward normal."""
        return float(0.55 + 0.5 * max(0.0, normal @ self.sun) + 0.1 * normal[2])

    def facade(self, width: float, height: float, eave: float) -> Texture:
        """A building facade (windows up to the eave)."""
        return make_texture(
            textures.facade(self.rng, width, height, eave, self.ppm, self.motif), self.ppm
        )

    def roof(self, width: float, height: float) -> Texture:
        """Roof tiles."""
        return make_texture(textures.roof(self.rng, width, height, self.ppm), self.ppm)

    def stone_block(self, width: float, height: float, _eave: float) -> Texture:
        """Masonry of a stone block's side."""
        image = textures.masonry(
            self.rng, int(height * self.ppm), int(width * self.ppm), self.ppm, (0.5, 0.3), _STONE
        )
        return make_texture(image, self.ppm)

    def plaster(self, rows: int, cols: int, colour, stains: float) -> Texture:
        """Plaster (or gravel) of a flat top."""
        image = textures.plaster(self.rng, rows, cols, self.ppm, colour, stains=stains)
        return make_texture(image, self.ppm)


def _hall(m: _Materials, hx: float, hy: float) -> list[Polygon]:
    """Hall: 2 ``hx`` x 2 ``hy`` m (12 x 8), eaves at 6.5 m, ridge along x at 9.5 m, gables east
    and west."""
    eave, ridge = 6.5, 9.5
    walls = _box_walls((-hx, -hy, hx, hy), eave, m.facade, m.shade_of, (None, ridge, None, ridge))
    slope = math.hypot(hy, ridge - eave)
    south = _roof_face(
        (-hx, -hy, eave), (hx, -hy, eave), (hx, 0, ridge), m.roof(2 * hx, slope), m.shade_of, False
    )
    north = _roof_face(
        (hx, hy, eave), (-hx, hy, eave), (-hx, 0, ridge), m.roof(2 * hx, slope), m.shade_of, False
    )
    return [*walls, south, north]


def _tower(m: _Materials, west: float, side: float) -> list[Polygon]:
    """Tower through the west gable at x = ``west``: ``side`` x ``side`` m (4), 11 m, pyramid
    roof up to 14 m."""
    tx0, ty0, tx1, ty1, th = west - 0.75 * side, -side / 2, west + side / 4, side / 2, 11.0
    polys = _box_walls((tx0, ty0, tx1, ty1), th, m.facade, m.shade_of)
    apex = ((tx0 + tx1) / 2, (ty0 + ty1) / 2, th + 3.0)
    ring = [(tx0, ty0, th), (tx1, ty0, th), (tx1, ty1, th), (tx0, ty1, th)]
    for p0, p1 in zip(ring, ring[1:] + ring[:1]):
        polys.append(_roof_face(p0, p1, apex, m.roof(side, 0.925 * side), m.shade_of, True))
    return polys


def _flat_topped_box(
    m: _Materials, box: tuple, height: float, walls, top_shape: tuple, top_colour, stains: float
) -> list[Polygon]:
    """An axis-aligned box (x0, y0, x1, y1) with ``walls`` textures and a flat plaster top."""
    polys = _box_walls(box, height, walls, m.shade_of)
    top = m.plaster(*top_shape, top_colour, stains)
    return [*polys, _flat_top(*box, height, top, m.up_shade)]


def _stone_blocks(m: _Materials) -> list[Polygon]:
    """Three stone blocks at random on the plaza."""
    polys = []
    for _ in range(3):
        ang, dist = m.rng.uniform(0, 2 * np.pi), m.rng.uniform(10.5, 12.5)
        cx, cy = dist * np.cos(ang), dist * np.sin(ang)
        s, bh = m.rng.uniform(0.5, 0.8), m.rng.uniform(0.8, 1.8)
        side = int(2 * s * m.ppm)
        box = (cx - s, cy - s, cx + s, cy + s)
        polys += _flat_topped_box(m, box, bh, m.stone_block, (side, side), _STONE, 0.4)
    return polys


def _ground(m: _Materials, size: float, tile: float) -> list[Polygon]:
    """The ground: a ``size`` square in ``tile`` squares (each picks its own mip level)."""
    macro, detail = textures.ground(m.rng, size, plaza_radius=14.0)
    macro_tex = make_texture(macro, 1024 / size)
    detail_tex = make_texture(detail, 2048 / 24.0, wrap=True)
    tiles = []
    for x in np.arange(-size / 2, size / 2, tile):
        for y in np.arange(-size / 2, size / 2, tile):
            ground = _flat_top(-size / 2, -size / 2, size / 2, size / 2, 0.0, macro_tex, m.up_shade)
            a, b = x + size / 2, size / 2 - y - tile
            ground.vertices = np.array([(a, b), (a + tile, b), (a + tile, b + tile), (a, b + tile)])
            ground.detail = detail_tex
            tiles.append(ground)
    return tiles


def _tree_line(m: _Materials, half: float) -> list[Polygon]:
    """A 12 m tree line around the square ``half`` metres from the centre, facing inwards."""
    edge = [(-half, -half), (-half, half), (half, half), (half, -half)]  # clockwise
    return [
        _wall(p0, p1, 12.0, make_texture(textures.treeline(m.rng, 2 * half, 12.0, 10.0), 10.0), 0.8)
        for p0, p1 in zip(edge, edge[1:] + edge[:1])
    ]


def build_scene(
    seed: int = 0,
    repeated: bool = False,
    texels_per_m: float = 100.0,
    style: int | None = None,
    hall_size: tuple[float, float] = (12.0, 8.0),
) -> list[Polygon]:
    """The polygons of the scene: hall, tower, annex, stone blocks, ground and tree line.
    ``style``: the seed of the repeated window (None: the scene's own): scenes of one style and
    other ``hall_size`` are two buildings of one architect."""
    m = _Materials(np.random.default_rng(seed), texels_per_m, repeated, style)
    hx, hy = hall_size[0] / 2, hall_size[1] / 2
    polys = _hall(m, hx, hy) + _tower(m, -hx, hy)
    # the annex on the south side, with a gravel roof
    annex = (1.5, 0.5 - 2 * hy, 0.5 + hx, -hy)
    polys += _flat_topped_box(m, annex, 3.5, m.facade, (400, 600), (0.5, 0.5, 0.48), 0.5)
    size = 120.0  # the ground's side; the tree line stands 2 m inside its edge
    return polys + _stone_blocks(m) + _ground(m, size, 10.0) + _tree_line(m, size / 2 - 2)


def _cameras(
    rng: np.random.Generator, num_images: int, conf: dict
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Poses on an arc around the hall, looking at it with jitter in distance, height, aim and
    roll."""
    start = rng.uniform(0, 2 * np.pi)
    poses = []
    for i in range(num_images):
        az = start + math.radians(conf["arc_step_deg"]) * (i + rng.uniform(-0.15, 0.15))
        r = rng.uniform(*conf["radius"])
        center = np.array([r * np.cos(az), r * np.sin(az), rng.uniform(*conf["camera_height"])])
        target = np.array([0.0, 0.0, 4.0]) + rng.uniform(-1, 1, 3) * conf["target_jitter"]
        z = (target - center) / np.linalg.norm(target - center)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        roll = math.radians(rng.uniform(-1, 1) * conf["max_roll_deg"])
        c, s = math.cos(roll), math.sin(roll)
        R = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) @ np.stack([x, y, z])
        poses.append((R, -R @ center))
    return poses


def render_scene(
    out_dir: str | Path,
    num_images: int = 8,
    width: int = 640,
    height: int = 480,
    seed: int = 0,
    repeated: bool = False,
    conf: dict | None = None,
    style: int | None = None,
) -> SceneInfo:
    """Render the scene into ``out_dir`` (images/, ground_truth/, depth/) and return its
    SceneInfo; ``repeated``, ``style``: ``build_scene``'s."""
    if num_images < 2:
        raise ValueError(f"num_images must be at least 2, got {num_images}.")
    if width < 32 or height < 32:
        raise ValueError(f"Image size {width}x{height} is too small; use at least 32x32 pixels.")
    conf = merge_conf(default_conf, conf, "synthetic scene")
    workspace = Workspace.claim(out_dir, "synthetic", flag="OUT_DIR")
    image_dir, gt_dir, depth_dir = workspace.record("images", "ground_truth", "depth")
    out_dir = workspace.path
    for d in (image_dir, gt_dir, depth_dir):
        d.mkdir(parents=True, exist_ok=True)
    names = [f"view_{i:03d}.jpg" for i in range(num_images)]
    # from an earlier, larger render
    for stale in [*image_dir.glob("view_*.jpg"), *depth_dir.glob("view_*.npy")]:
        if stale.stem not in {Path(n).stem for n in names}:
            stale.unlink()
    tic = time.perf_counter()
    polygons = build_scene(seed, repeated, conf["texels_per_m"], style, conf["hall_size"])
    logger.debug("Built %d textured polygons in %.2f s.", len(polygons), time.perf_counter() - tic)
    f = conf["focal_factor"] * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    poses = _cameras(np.random.default_rng([seed, 1]), num_images, conf)
    tic = time.perf_counter()
    for i, (name, (R, t)) in enumerate(zip(names, poses)):
        # per image: a shorter render gives the same views
        noise_rng = np.random.default_rng([seed, 2, i])
        image, depth = render_image(polygons, K, R, t, width, height, conf, noise_rng)
        _write_jpeg(image_dir / name, image, conf["jpeg_quality"], f if conf["exif"] else None)
        np.save(depth_dir / f"{Path(name).stem}.npy", depth)
    seconds = time.perf_counter() - tic
    logger.info(
        "Rendered %d images of %dx%d in %.1f s into %s.",
        num_images,
        width,
        height,
        seconds,
        out_dir,
    )
    _write_model(gt_dir, K, width, height, names, poses)
    return SceneInfo(image_dir, gt_dir, depth_dir, names, K, width, height, dict(zip(names, poses)))


def _write_jpeg(path: Path, image: np.ndarray, quality: int, focal: float | None) -> None:
    """Save RGB as JPEG; with ``focal`` (pixels) add the EXIF tags from which COLMAP reads a focal
    length prior (35 mm equivalent over the diagonal) and groups the images into one camera."""
    exif = Image.Exif()
    if focal is not None:
        exif[0x010F], exif[0x0110] = "colmap_guided", "synthetic"  # Make, Model
        diagonal_35mm = math.hypot(36.0, 24.0)
        exif.get_ifd(0x8769)[0xA405] = round(focal / math.hypot(*image.shape[:2]) * diagonal_35mm)
    Image.fromarray(image).save(path, quality=quality, exif=exif)


def _write_model(
    path: Path, K: np.ndarray, width: int, height: int, names: list[str], poses
) -> None:
    """Write the ground truth as a COLMAP text model (cameras, rigs, frames, images; no points)."""
    rec = pycolmap.Reconstruction()
    params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    camera = pycolmap.Camera(
        model="PINHOLE", width=width, height=height, params=params, camera_id=1
    )
    rec.add_camera_with_trivial_rig(camera)
    for image_id, (name, (R, t)) in enumerate(zip(names, poses), start=1):
        image = pycolmap.Image(name=name, camera_id=1, image_id=image_id)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
    rec.write_text(str(path))


def transfer_points(
    info: SceneInfo, src: str, dst: str, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth correspondences: map pixels (N x 2, COLMAP convention) of ``src`` into ``dst``.

    Uses the depth of ``src`` (nearest pixel) and the poses; ``valid`` is False where the depth is
    unknown (sky, occlusion edges), a point lies outside either image or is hidden in ``dst`` (depth
    test, 2 %).
    """
    points = np.asarray(points, np.float64).reshape(-1, 2)
    depth_src, depth_dst = info.depth(src), info.depth(dst)
    z = _lookup(depth_src, points).astype(np.float64)
    rays = np.concatenate([points, np.ones((len(points), 1))], 1) @ np.linalg.inv(info.K).T
    (R_s, t_s), (R_d, t_d) = info.cam_from_world[src], info.cam_from_world[dst]
    world = (rays * z[:, None] - t_s) @ R_s
    cam = world @ R_d.T + t_d
    proj = cam @ info.K.T
    out = proj[:, :2] / np.where(np.abs(proj[:, 2:]) > 1e-12, proj[:, 2:], 1e-12)
    seen = _lookup(depth_dst, out)
    valid = (z > 0) & (cam[:, 2] > 0) & (seen > 0) & (np.abs(seen - cam[:, 2]) < 0.02 * cam[:, 2])
    return out, valid


def _lookup(depth: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Depth of the pixels containing the points, 0 for points outside the image."""
    h, w = depth.shape
    inside = (points[:, 0] >= 0) & (points[:, 0] < w) & (points[:, 1] >= 0) & (points[:, 1] < h)
    cols = np.clip(np.floor(points[:, 0]), 0, w - 1).astype(int)
    rows = np.clip(np.floor(points[:, 1]), 0, h - 1).astype(int)
    return np.where(inside, depth[rows, cols], 0)


def load_scene(out_dir: str | Path) -> SceneInfo:
    """The SceneInfo of a scene rendered earlier into ``out_dir``."""
    out_dir = Path(out_dir)
    rec = load_ground_truth(out_dir / "ground_truth")
    images = sorted(rec.images.values(), key=lambda im: im.name)
    camera = rec.cameras[images[0].camera_id]
    poses = {
        im.name: (im.cam_from_world().rotation.matrix(), im.cam_from_world().translation)
        for im in images
    }
    return SceneInfo(
        out_dir / "images",
        out_dir / "ground_truth",
        out_dir / "depth",
        [im.name for im in images],
        camera.calibration_matrix(),
        camera.width,
        camera.height,
        poses,
    )


def load_ground_truth(
    gt: SceneInfo | pycolmap.Reconstruction | str | Path,
) -> pycolmap.Reconstruction:
    """The ground-truth model of a rendered scene (its SceneInfo or ground_truth folder), or ``gt``
    itself."""
    if isinstance(gt, pycolmap.Reconstruction):
        return gt
    path = Path(gt.gt_dir if isinstance(gt, SceneInfo) else gt)
    if not path.is_dir():
        raise FileNotFoundError(
            f"No ground-truth model at {path}; render one with render_scene() first."
        )
    return pycolmap.Reconstruction(str(path))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description="Render the synthetic landmark scene with its ground truth."
    )
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--num_images", type=int, default=8)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--repeated", action="store_true", help="periodic window grid on every facade"
    )
    args = parser.parse_args(argv)
    try:
        info = render_scene(
            args.out_dir, args.num_images, args.width, args.height, args.seed, args.repeated
        )
    except ValueError as err:
        logger.error("%s", err)
        raise SystemExit(2) from None
    print(f"{len(info.names)} images in {info.image_dir}, ground truth in {info.gt_dir}")
