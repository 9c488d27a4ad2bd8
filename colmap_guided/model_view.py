"""The model in report.html: an interactive 3D view of the points and cameras, and a map of the
photos.

    frame = ground_frame(rec)  # up = the photos' up direction (or east-north-up), origin, scale
    html = view_html(rec, eras, image_path)  # <canvas> + its data + a small viewer script
    uri = photo_map(rec, eras)  # PNG data URI: camera positions and directions from above

The viewer is our own (a canvas 2D point splatter with a depth buffer, ~100 lines of JavaScript in
assets/model_view.js), not plotly's offline HTML: plotly would add ~3.5 MB of script to every page
and WebGL, which headless or old browsers may lack; a 2D canvas works everywhere, offline, and a
page with 30,000 points stays under a megabyte. Points are stored as uint16 coordinates (6 bytes)
and RGB (3 bytes), base64 in a JSON block.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import numpy as np
import pycolmap

from . import embed
from .geometry import image_rays, photo_up
from .images import read_thumbnail

MAX_POINTS = 30000  # points drawn in the 3D view; a larger model is shown by an even random sample
MAX_THUMBS = 300  # cameras that show their photo on hover (160 px JPEGs, ~6 KB each), all models
# the other models in the view's picker: the largest ones, each with at most a quarter of the points
MAX_OTHER_MODELS = 20
FRUSTUM = 0.07  # frustum depth in units of the model's radius
# amber / blue: visible on dark and light; red: photos placed later by `localize`
ERA_COLORS = {"historical": "#f0a030", "modern": "#3a8ee6", "localized": "#e03c31"}
# for a model without eras, or other era names
OTHER_COLORS = ("#3a8ee6", "#e05a8a", "#4fb86b", "#a070e0")


def era_colors(eras: dict[str, str], names: list[str]) -> dict[str, str]:
    """Colour of each era present among ``names`` ("photo" when there is no manifest)."""
    present = sorted({eras.get(name, "photo") for name in names})
    others = iter(OTHER_COLORS)
    return {era: ERA_COLORS.get(era) or next(others, "#888888") for era in present}


def ground_frame(
    rec: pycolmap.Reconstruction, enu: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """(origin, axes (3, 3) rows x, y, up, radius): a frame with z up in which the model is shown.
    ``enu``: the model is in east-north-up metres (georeferenced): x east, y north, z up.

    Up is the photos' up direction (``geometry.photo_up``: photos are taken upright); when they
    disagree (scans rotated by 90 degrees) it is the normal of the camera centres' best plane. x is
    the points' main horizontal direction (PCA); the origin is the median point, the radius the
    95th (points) or 90th (cameras) percentile of their distances to it, whichever is larger.
    """
    images = [rec.images[i] for i in rec.reg_image_ids()]
    centres = np.array([im.projection_center() for im in images]).reshape(-1, 3)
    xyz = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    rotations = [im.cam_from_world().rotation.matrix() for im in images]
    up = np.array([0.0, 0.0, 1.0]) if enu else photo_up(rotations)
    if up is None and len(centres) >= 3:
        mean = -np.mean([R[1] for R in rotations], axis=0)  # image y points down
        normal = np.linalg.svd(centres - centres.mean(axis=0))[2][2]
        up = normal if normal @ mean >= 0 else -normal
    up = np.array([0.0, 0.0, 1.0]) if up is None else up / max(np.linalg.norm(up), 1e-12)
    origin = (
        np.median(xyz, axis=0)
        if len(xyz)
        else (centres.mean(axis=0) if len(centres) else np.zeros(3))
    )
    flat = (xyz if len(xyz) >= 2 else centres) - origin
    flat = flat - np.outer(flat @ up, up)
    x = (
        np.linalg.svd(flat, full_matrices=False)[2][0]
        if len(flat) >= 2 and not enu
        else np.array([1.0, 0.0, 0.0])
    )
    x = x - (x @ up) * up
    if np.linalg.norm(x) < 1e-9:  # degenerate: any horizontal direction
        x = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    axes = np.stack([x, np.cross(up, x), up])
    # The photos (a few, far out) count as much as the points: the first view shows them all.
    dist = [
        np.percentile(np.linalg.norm(p - origin, axis=1), q)
        for p, q in ((xyz, 95), (centres, 90))
        if len(p)
    ]
    radius = float(max(max(dist, default=1.0), 1e-9))
    return origin, axes, radius


def _cameras(rec: pycolmap.Reconstruction, origin, axes, radius) -> list[dict]:
    """Per registered image: name, centre and the 4 far corners of its frustum, in the display
    frame."""
    out = []
    for image_id in sorted(rec.reg_image_ids(), key=lambda i: rec.images[i].name):
        image = rec.images[image_id]
        camera = rec.cameras[image.camera_id]
        pose = image.cam_from_world()
        rot, t = pose.rotation.matrix(), np.asarray(pose.translation)
        corners = np.array(
            [[0, 0], [camera.width, 0], [camera.width, camera.height], [0, camera.height]],
            np.float64,
        )
        rays = np.c_[image_rays(camera, corners), np.ones(4)]
        rays *= FRUSTUM * radius / np.linalg.norm(rays, axis=1).max()
        world = (rays - t) @ rot  # R^T (p - t)
        out.append(
            {
                "name": image.name,
                "c": _to_view(image.projection_center(), origin, axes, radius),
                "f": _to_view(world, origin, axes, radius),
            }
        )
    return out


def _to_view(points, origin, axes, radius) -> list:
    return np.round((np.asarray(points) - origin) @ axes.T / radius, 4).tolist()


def view_data(
    rec: pycolmap.Reconstruction,
    eras: dict[str, str] | None = None,
    image_path: Path | None = None,
    max_points: int = MAX_POINTS,
    enu: bool = False,
    max_thumbs: int = MAX_THUMBS,
) -> dict:
    """What the viewer draws (and what a test reads back): points, cameras, eras and the display
    frame; the first ``max_thumbs`` cameras carry their photo."""
    eras = eras or {}
    origin, axes, radius = ground_frame(rec, enu)
    ids = np.array(sorted(rec.points3D), np.int64)
    if len(ids) > max_points:  # an even random sample, the same for the same model
        ids = np.sort(np.random.default_rng(0).choice(ids, max_points, replace=False))
    xyz = np.array([rec.points3D[i].xyz for i in ids]).reshape(-1, 3)
    rgb = np.array([rec.points3D[i].color for i in ids], np.uint8).reshape(-1, 3)
    view = (xyz - origin) @ axes.T / radius
    lo = view.min(axis=0) if len(view) else np.zeros(3)
    step = np.maximum((view.max(axis=0) - lo) / 65535, 1e-9) if len(view) else np.ones(3)
    quant = np.round((view - lo) / step).astype("<u2")
    cameras = _cameras(rec, origin, axes, radius)
    for i, cam in enumerate(cameras):
        cam["era"] = eras.get(cam["name"], "photo")
        cam["thumb"] = None
        if image_path is not None and i < max_thumbs:
            try:
                cam["thumb"] = embed.encode_jpeg(
                    read_thumbnail(Path(image_path) / cam["name"], 160)[0], 75
                )
            except Exception:  # noqa: BLE001
                # a photo moved away since the run: the camera stays, without preview
                pass
    centre = np.mean([c["c"][:2] for c in cameras], axis=0) if cameras else np.zeros(2)
    return {
        "num_points_total": rec.num_points3D(),
        "num_points_shown": len(ids),
        "points": base64.b64encode(quant.tobytes()).decode("ascii"),
        "colors": base64.b64encode(rgb.tobytes()).decode("ascii"),
        "quant": {"lo": lo.tolist(), "step": step.tolist()},
        "frame": {"origin": origin.tolist(), "axes": axes.tolist(), "radius": radius},
        "cameras": cameras,
        "colors_by_era": era_colors(eras, [c["name"] for c in cameras]),
        # First view: from where most photos were taken, a little above.
        "yaw": float(np.arctan2(centre[0], centre[1]) + np.pi)
        if np.linalg.norm(centre) > 1e-6
        else -0.6,
        # The eye's distance to the centre: beyond the farthest camera, so that every camera is in
        # front of it.
        "dist": float(max(3.0, 1.5 * max((np.linalg.norm(c["c"]) for c in cameras), default=0.0))),
    }


def decode_points(data: dict) -> np.ndarray:
    """World coordinates of the points a page shows (the inverse of view_data's encoding)."""
    quant = np.frombuffer(base64.b64decode(data["points"]), "<u2").reshape(-1, 3).astype(np.float64)
    view = quant * np.array(data["quant"]["step"]) + np.array(data["quant"]["lo"])
    frame = data["frame"]
    return view * frame["radius"] @ np.array(frame["axes"]) + np.array(frame["origin"])


# Orbit (drag), zoom (wheel), pan (shift-drag), hover/click a camera for its photo
# (or page.html#photo=NAME). Points go through a depth buffer into an ImageData
# (no sort, fast for 100k); frusta and labels on top.
VIEW_JS = embed.asset("model_view.js")


def _json(data: dict) -> str:
    """Strict JSON for a <script> block: a NaN fails here, where it is made, not in the browser
    (JSON.parse refuses it)."""
    return json.dumps(data, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")


def view_html(
    rec: pycolmap.Reconstruction,
    eras: dict[str, str] | None = None,
    image_path: Path | None = None,
    max_points: int = MAX_POINTS,
    enu: bool = False,
    others: list[tuple[int, pycolmap.Reconstruction]] = (),
) -> str:
    """The 3D view: a legend, the canvas, its data (JSON) and the viewer script; nothing loaded from
    outside. ``others``: the workspace's other models (index, model), offered by a picker, each in
    its own frame."""
    models = [(0, rec, max_points, enu), *((k, m, max_points // 4, False) for k, m in others)]
    blocks, thumbs = [], MAX_THUMBS
    for k, model, points, in_enu in models[: 1 + MAX_OTHER_MODELS]:
        data = view_data(model, eras, image_path, points, in_enu, max(thumbs, 0))
        thumbs -= len(data["cameras"])
        data["label"] = f"sparse/{k}: {len(data['cameras'])} photos"
        data["legend"] = f"{len(data['cameras'])} cameras:" + "".join(
            f"<i style='background:{color}'></i>{html.escape(era)}"
            for era, color in data["colors_by_era"].items()
        )
        shown, total = data["num_points_shown"], data["num_points_total"]
        data["note"] = (
            f"all {total:,} points"
            if shown == total
            else f"{shown:,} of the {total:,} points (an even sample, to keep the page small)"
        )
        blocks.append(data)
    picker = (
        "<select id='model-pick' title='the model shown'>"
        + "".join(
            f"<option value='{i}'>{html.escape(d['label'])}</option>" for i, d in enumerate(blocks)
        )
        + "</select> "
        if len(blocks) > 1
        else ""
    )
    scripts = "".join(
        f"<script type='application/json' id='model-data{f'-{i}' if i else ''}'>{_json(d)}</script>"
        for i, d in enumerate(blocks)
    )
    return (
        "<p class='legend'><span class='model-buttons'>"
        "<button id='model-home'>Reset view</button><button id='model-top'>From above</button>"
        f"</span>{picker}<span id='model-legend'>{blocks[0]['legend']}</span></p>"
        "<div id='model-box'><canvas id='model-view'></canvas><div id='model-tip'></div></div>"
        f"<p class='muted'>Showing <span id='model-note'>{blocks[0]['note']}</span>, coloured "
        "from the photos. Drag to turn, wheel to zoom, shift-drag to move, double-click to reset; "
        f"point at a camera (or click it) to see its photo.</p>{scripts}"
        f"<script>\n{VIEW_JS}</script>"
    )


def photo_map(
    rec: pycolmap.Reconstruction, eras: dict[str, str] | None = None, enu: bool = False
) -> str:
    """Top-down map (PNG data URI): points in grey-scale of their colour, each camera's position and
    viewing direction. ``enu``: the model is in east-north-up metres; the map is drawn north up
    with metres from the frame's origin on its axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    eras = eras or {}
    origin, axes, radius = ground_frame(rec, enu)
    origin = np.zeros(3) if enu else origin
    xyz = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    rgb = np.array([p.color for p in rec.points3D.values()], np.float64).reshape(-1, 3) / 255
    if len(xyz) > 50000:
        keep = np.random.default_rng(0).choice(len(xyz), 50000, replace=False)
        xyz, rgb = xyz[keep], rgb[keep]
    ground = (xyz - origin) @ axes.T
    images = sorted((rec.images[i] for i in rec.reg_image_ids()), key=lambda im: im.name)
    centres = (np.array([im.projection_center() for im in images]).reshape(-1, 3) - origin) @ axes.T
    dirs = np.array([im.viewing_direction() for im in images]).reshape(-1, 3) @ axes.T
    colors = era_colors(eras, [im.name for im in images])
    fig, ax = plt.subplots(figsize=(7.5, 6.5))
    ax.scatter(ground[:, 0], ground[:, 1], s=4 if len(ground) < 5000 else 1.5, c=rgb, linewidths=0)
    arrow = 0.25 * radius
    for era, color in colors.items():
        sel = np.array([eras.get(im.name, "photo") == era for im in images], bool)
        flat = dirs[sel, :2] / np.maximum(
            np.linalg.norm(dirs[sel, :2], axis=1, keepdims=True), 1e-9
        )
        ax.quiver(
            centres[sel, 0],
            centres[sel, 1],
            flat[:, 0] * arrow,
            flat[:, 1] * arrow,
            color=color,
            angles="xy",
            scale_units="xy",
            scale=1,
            width=0.004,
        )
        ax.scatter(
            centres[sel, 0],
            centres[sel, 1],
            s=30,
            color=color,
            edgecolors="#222",
            linewidths=0.6,
            label=era,
            zorder=3,
        )
    if len(images) <= 40:
        for im, c in zip(images, centres):
            ax.annotate(
                Path(im.name).stem,
                c[:2],
                xytext=(4, 4),
                textcoords="offset points",
                fontsize=7,
                color="#333",
            )
    both = np.concatenate([ground[:, :2], centres[:, :2]]) if len(ground) else centres[:, :2]
    lo = np.minimum(np.percentile(both, 1, axis=0), centres[:, :2].min(axis=0, initial=np.inf))
    hi = np.maximum(np.percentile(both, 99, axis=0), centres[:, :2].max(axis=0, initial=-np.inf))
    pad = 0.08 * (hi - lo).max()
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    if enu:
        ax.set_xlabel("east (m)")
        ax.set_ylabel("north (m)")
        ax.grid(True, linewidth=0.4, alpha=0.5)
    else:
        ax.set_xticks([])
        ax.set_yticks([])
    ax.legend(loc="upper right", fontsize=8, frameon=True)
    return embed.figure_uri(fig)


def with_cameras(
    rec: pycolmap.Reconstruction, posed: list[dict]
) -> tuple[pycolmap.Reconstruction, list[str]]:
    """A copy of ``rec`` with the camera of each entry of ``posed`` (localized.json's, named by
    its photo's path, no points), for the 3D view and the map; and their names."""
    shown = pycolmap.Reconstruction(rec)
    for entry in posed:
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
    return shown, [entry["photo"] for entry in posed]
