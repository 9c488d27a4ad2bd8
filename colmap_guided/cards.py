"""The anatomy of a scanned picture postcard: where the photo is, how many photos it holds, and
which scans are prints of one picture.

A scan of a card is more than its photo: a uniform paper border, a caption band with printed text,
a publisher's mark in a margin. Keypoints there match the same printed text and borders on other
cards of the same publisher and never belong to the landmark. Collage cards hold several views
separated by gutters of the card's paper colour: each view was taken from its own viewpoint, with
its own camera. And two scans of one picture (the same negative printed twice, or a crop of it)
share one viewpoint: they are not two views.

- ``find_layout``: the picture rectangle of a scan and the panels of a collage, from the paper
  colour of the scan's outer ring (a uniform ring = a card border; an ordinary photo has none and
  keeps every pixel);
- ``split_collages``: each panel of a collage card cropped into the workspace
  (``WORKSPACE/panels/<card>_p<k>.jpg``) and mapped as a photo of its own, in place of the card;
- ``mask_keypoints``: keypoints off the border and caption band of single-picture cards, whose
  camera is centred on the picture (a caption band shifts it off the scan's centre); a caption
  printed over the photo itself stays;
- ``repeated_prints``: verified pairs whose inliers a similarity transform explains nearly all,
  covering much of one picture: one print of the group is mapped, the others are reported as
  the same picture.
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import cv2
import numpy as np

from . import database as dbio
from . import images
from .conf import merge_conf
from .log import logger

PANELS = "panels"  # the workspace folder of the panels cut from collage cards
default_conf = {
    "enabled": True,  # find borders, captions and collage panels of scanned cards
    "analysis_size": 1000,  # longer side (px) of the copy a layout is found on
    # a card border: the scan's outer ring within this Lab distance of its median colour (median
    # over the ring); ordinary photos have no such ring
    "max_ring_spread": 8.0,
    # paper: within this Lab distance of the border colour (3x the ring's spread, at least the
    # first, at most the second)
    "paper_tolerance": (10.0, 25.0),
    "min_panel_area": 0.005,  # a picture covers at least this share of the card
    # keypoints closer than this share of the longer side to a picture's edge go too (their patch
    # is half paper)
    "edge_margin": 0.005,
    # a row or column of a collage's gutter: at least this share of it is paper
    "gutter_share": 0.4,
    "gutter_tolerance": 30.0,  # a gutter's pixels: within this Lab distance of the paper
    "max_gutter_width": 0.05,  # a gutter is at most this share of the split side
    "min_part": 0.12,  # each side of a gutter is at least this share of the split side
    # a repeated print: a similarity transform explains at least this share of the pair's
    # verified inliers, within max_print_error of the second picture's diagonal ...
    "min_print_inlier_ratio": 0.9,
    "max_print_error": 0.004,
    "min_print_inliers": 50,
    # ... and the inliers cover this share of one picture (two photos of a distant landmark
    # from one spot fit a similarity too, over their shared part only: 0.32 on sacre_coeur_hloc)
    "min_print_cover": 0.5,
}

Box = tuple[int, int, int, int]  # x0, y0, x1, y1 in the scan's pixels (x1, y1 exclusive)


@dataclasses.dataclass
class Layout:
    """A scan's picture rectangle and, for a collage, its panels (both in the scan's pixels)."""

    size: tuple[int, int]  # width, height
    picture: Box
    panels: list[Box]
    border: bool  # the scan has a card border of uniform paper

    @property
    def whole(self) -> bool:
        """No border, caption or panel: every pixel is the picture."""
        return self.picture == (0, 0, *self.size) and len(self.panels) < 2

    def to_dict(self) -> dict:
        return {
            "size": list(self.size),
            "picture": list(self.picture),
            "panels": [list(p) for p in self.panels],
        }


def check_conf(conf: dict | None) -> dict:
    return merge_conf(default_conf, conf, "card")


def paper_colour(lab: np.ndarray, conf: dict) -> tuple[np.ndarray, float] | None:
    """(Lab colour, tolerance) of the card's paper from the scan's outer ring; None when the ring
    is not uniform on every side (an ordinary photo, or a print trimmed to its picture)."""
    h, w = lab.shape[:2]
    r = max(2, round(0.01 * max(h, w)))
    sides = [lab[:r].reshape(-1, 3), lab[-r:].reshape(-1, 3)]
    sides += [lab[:, :r].reshape(-1, 3), lab[:, -r:].reshape(-1, 3)]
    ring = np.concatenate(sides)
    colour = np.median(ring, axis=0)
    spread = float(np.median(np.linalg.norm(ring - colour, axis=1)))
    if spread > conf["max_ring_spread"]:
        return None
    low, high = conf["paper_tolerance"]
    tolerance = float(np.clip(3 * spread, low, high))
    # paper on every side: a photo with a uniform sky and a dark foreground is not a card
    paper = sorted(np.mean(np.linalg.norm(s - colour, axis=1) < tolerance) for s in sides)
    if paper[0] < 0.5 or paper[1] < 0.6:  # (one side may carry a caption or a scanner's shadow)
        return None
    return colour, tolerance


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of the runs of True in a 1-D bool array."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flags.astype(np.int8), [0]])))
    return list(zip(edges[::2], edges[1::2]))


def _gutters(gutter: np.ndarray, axis: int, conf: dict) -> list[tuple[int, int]]:
    """Gutters across a crop: thin runs of rows (axis 0) or columns (axis 1) mostly of paper
    colour (``gutter``) standing out from the rows or columns beside them (a light sky does not:
    its neighbours are as light), with pictures on both sides."""
    profile = gutter.mean(axis=1 - axis)
    n = len(profile)
    k = max(2, round(0.01 * n))
    runs = []
    for start, end in _runs(profile >= conf["gutter_share"]):
        if runs and start - runs[-1][1] < conf["max_gutter_width"] * n / 2:  # a frame line in it
            start = runs.pop()[0]
        runs.append((start, end))
    out = []
    for start, end in runs:
        if end - start > conf["max_gutter_width"] * n or min(start, n - end) < conf["min_part"] * n:
            continue
        beside = np.concatenate(
            [profile[start - k - 2 : start - 2], profile[end + 2 : end + k + 2]]
        )
        if profile[start:end].max() - beside.max() >= 0.2:
            out.append((start, end))
    return out


def _split(
    gutter: np.ndarray, texture: np.ndarray, box: Box, conf: dict, depth: int = 0
) -> list[Box]:
    """Recursive XY-cut of ``box`` along its gutters (``_gutters``)."""
    x0, y0, x1, y1 = box
    if depth < 4 and x1 > x0 and y1 > y0:
        for axis in (0, 1):
            crop = (slice(y0, y1), slice(x0, x1))
            gutters = _gutters(gutter[crop], axis, conf)
            if not gutters:
                continue
            cuts = [0] + [c for g in gutters for c in g] + [(y1 - y0, x1 - x0)[axis]]
            parts = [
                (x0, y0 + a, x1, y0 + b) if axis == 0 else (x0 + a, y0, x0 + b, y1)
                for a, b in zip(cuts[::2], cuts[1::2])
            ]
            if all(_textured(texture, part, 0.15) for part in parts):  # (not paper round an oval)
                return [p for part in parts for p in _split(gutter, texture, part, conf, depth + 1)]
    return [_trim(gutter, box, conf)]


def _trim(paper: np.ndarray, box: Box, conf: dict) -> Box:
    """``box`` without the rows and columns of paper along its edges."""
    x0, y0, x1, y1 = box
    crop = paper[y0:y1, x0:x1]
    rows = np.flatnonzero(crop.mean(axis=1) < conf["gutter_share"])
    cols = np.flatnonzero(crop.mean(axis=0) < conf["gutter_share"])
    if not len(rows) or not len(cols):
        return box
    # a few pixels at most: the paper the smoothing blurred in, not a light sky along an edge
    dx, dy = (round(0.015 * n) for n in crop.shape[::-1])
    return (
        x0 + min(int(cols[0]), dx),
        y0 + min(int(rows[0]), dy),
        x1 - min(crop.shape[1] - 1 - int(cols[-1]), dx),
        y1 - min(crop.shape[0] - 1 - int(rows[-1]), dy),
    )


def _textured(texture: np.ndarray, box: Box, share: float = 0.3) -> bool:
    """A picture has detail over much of it; bare paper has not."""
    x0, y0, x1, y1 = box
    return bool(x1 > x0 and y1 > y0 and texture[y0:y1, x0:x1].mean() >= share)


def _caption_box(lab: np.ndarray, box: Box) -> bool:
    """A printed caption's box: long and narrow, most of it one flat colour."""
    x0, y0, x1, y1 = box
    if 0.5 < (x1 - x0) / max(1, y1 - y0) < 2:
        return False
    pixels = lab[y0:y1, x0:x1].reshape(-1, 3)
    return bool(np.mean(np.linalg.norm(pixels - np.median(pixels, axis=0), axis=1) < 20) >= 0.6)


def _upright(box: Box) -> bool:
    """Not a lettering band: a picture's sides are within 1:4."""
    return 0.25 <= (box[2] - box[0]) / max(1, box[3] - box[1]) <= 4


def _area(box: Box) -> int:
    return (box[2] - box[0]) * (box[3] - box[1])


def _merge_overlapping(boxes: list[Box]) -> list[Box]:
    """Boxes that overlap merged into their union (one picture cut in pieces by a light line)."""
    boxes = list(boxes)
    merged = True
    while merged:
        merged = False
        for i, a in enumerate(boxes):
            for j in range(i + 1, len(boxes)):
                b = boxes[j]
                overlap = max(0, min(a[2], b[2]) - max(a[0], b[0])) * max(
                    0, min(a[3], b[3]) - max(a[1], b[1])
                )
                if overlap > 0.25 * min(_area(a), _area(b)):  # (tilted neighbours touch corners)
                    boxes[i] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return boxes


def _is_picture(own: np.ndarray) -> bool:
    """A picture is a rectangle, upright or slightly turned: its mask (``own``, cropped to its
    box) fills its convex hull, or the bands along the box's sides (a coat of arms or a lettering
    does neither)."""
    h, w = own.shape
    if not _upright((0, 0, w, h)):
        return False
    hull = cv2.contourArea(cv2.convexHull(cv2.findNonZero(own.astype(np.uint8))))
    dy, dx = max(1, round(0.08 * h)), max(1, round(0.08 * w))
    bands = [own[:dy], own[-dy:], own[:, :dx], own[:, -dx:]]
    return own.sum() >= 0.9 * hull or float(np.mean([b.mean() for b in bands])) >= 0.45


def layout_of(rgb: np.ndarray, conf: dict | None = None) -> tuple[list[Box], bool]:
    """(picture boxes, has a border) of an RGB scan, in its own pixels (``find_layout`` for a
    file)."""
    conf = check_conf(conf)
    h, w = rgb.shape[:2]
    whole = [(0, 0, w, h)]
    lab = cv2.GaussianBlur(cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab).astype(np.float32), (0, 0), 2.5)
    paper = paper_colour(lab, conf)
    if paper is None:
        return whole, False
    colour, tolerance = paper
    like = np.linalg.norm(lab - colour, axis=2) < tolerance
    # gutters are a few pixels wide, darker than paper where the halftone bleeds: unsmoothed,
    # with a wider tolerance
    sharp = cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab).astype(np.float32)
    gutter = np.linalg.norm(sharp - colour, axis=2) < conf["gutter_tolerance"]
    light = sharp[..., 0]
    mean = cv2.blur(light, (5, 5))
    texture = cv2.blur(light * light, (5, 5)) - mean * mean > 16  # local std above 4 levels
    # the border: paper connected to the scan's edge (not a white wall inside the picture)
    count, labels = cv2.connectedComponents(like.astype(np.uint8), connectivity=4)
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    border = np.isin(labels, edge[edge > 0])  # (label 0: not paper)
    region = (~border).astype(np.uint8)
    # (eroded: the white frames of neighbouring panels may touch)
    r = max(1, round(0.004 * max(h, w)))
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(cv2.erode(region, kernel), 8)
    regions = [
        (max(0, int(x) - r), max(0, int(y) - r), min(w, int(x + bw) + r), min(h, int(y + bh) + r))
        for i, (x, y, bw, bh, area) in enumerate(stats)
        if i
        and area >= conf["min_panel_area"] * w * h
        and _is_picture(labels[y : y + bh, x : x + bw] == i)
    ]
    boxes = [p for box in _merge_overlapping(regions) for p in _split(gutter, texture, box, conf)]
    # detail over 3/10 of a picture, 1/10 of one filling most of the card (a smooth print): a
    # small flat patch in a faded photo is no picture
    boxes = [
        b
        for b in boxes
        if _area(b) >= conf["min_panel_area"] * w * h
        and _upright(b)
        and _textured(texture, b, 0.1 if _area(b) >= 0.4 * w * h else 0.3)
        and not _caption_box(sharp, b)
    ]
    if not boxes:
        return whole, True
    # reading order: rows of panels top to bottom, left to right within a row
    boxes.sort(key=lambda b: (round(b[1] / (0.1 * h)), b[0]))
    return boxes, True


def find_layout(path: Path, conf: dict | None = None) -> Layout:
    """The ``Layout`` of the photo at ``path`` (found on a copy of ``analysis_size``)."""
    conf = check_conf(conf)
    width, height = images.image_size(path)
    rgb = images.read_image(path, 2 * conf["analysis_size"])  # (a large JPEG decoded reduced)
    scale = min(1.0, conf["analysis_size"] / max(rgb.shape[:2]))
    # area averaging keeps a gutter of a few pixels visible
    thumb = cv2.resize(rgb, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    sx, sy = thumb.shape[1] / width, thumb.shape[0] / height
    boxes, border = layout_of(thumb, conf)
    full = [
        (
            max(0, int(np.floor(x0 / sx))),
            max(0, int(np.floor(y0 / sy))),
            min(width, int(np.ceil(x1 / sx))),
            min(height, int(np.ceil(y1 / sy))),
        )
        for x0, y0, x1, y1 in boxes
    ]
    if not border:
        full = [(0, 0, width, height)]
    picture = (
        min(b[0] for b in full),
        min(b[1] for b in full),
        max(b[2] for b in full),
        max(b[3] for b in full),
    )
    return Layout((width, height), picture, full if len(full) > 1 else [], border)


def find_layouts(image_path: Path, names: list[str], conf: dict) -> dict[str, Layout]:
    """{name: Layout} of the photos that are more than their picture (a border or panels); an
    unreadable photo is left to the image checks."""
    out = {}
    if not conf["enabled"]:
        return out
    for name in names:
        try:
            layout = find_layout(Path(image_path) / name, conf)
        except (ValueError, OSError):
            continue
        if not layout.whole:
            out[name] = layout
    if out:
        logger.info(
            "%d scanned card(s) with a border or caption band, %d of them with several pictures.",
            len(out),
            sum(bool(layout.panels) for layout in out.values()),
        )
    return out


def panel_name(card: str, k: int) -> str:
    """The file name of panel ``k`` (from 1) of collage ``card``, after both."""
    return f"{Path(card).with_suffix('').as_posix().replace('/', '_')}_p{k}.jpg"


def split_collages(
    image_path: Path, workspace: Path, names: list[str], layouts: dict[str, Layout]
) -> tuple[list[str], dict[str, list[str]]]:
    """``names`` with every collage card replaced by its panels, and {card: its panels' names}.

    Each panel is cropped from the scan into ``workspace/panels`` (never beside the photos) and
    named, as COLMAP names an image, by its path relative to ``image_path``: it is read from there
    like any photo, with a camera of its own."""
    folder = Path(workspace) / PANELS
    out, panels = [], {}
    for name in names:
        layout = layouts.get(name)
        if layout is None or not layout.panels:
            out.append(name)
            continue
        folder.mkdir(exist_ok=True)
        rgb = None
        panels[name] = []
        for k, (x0, y0, x1, y1) in enumerate(layout.panels, 1):
            path = folder / panel_name(name, k)
            if not path.exists():  # (a rerun keeps the crops that its database was made from)
                rgb = images.read_image(Path(image_path) / name) if rgb is None else rgb
                tmp = path.with_name(path.name + ".partial.jpg")
                cv2.imwrite(str(tmp), rgb[y0:y1, x0:x1, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
                os.replace(tmp, path)
            panels[name].append(Path(os.path.relpath(path, Path(image_path))).as_posix())
        out += panels[name]
    return out, panels


def mask_keypoints(database_path: Path, layouts: dict[str, Layout], conf: dict) -> dict[str, int]:
    """Remove the keypoints outside the picture of every single-picture card in the database
    (border, caption band, publisher's mark); {name: keypoints removed}. Run before matching: a
    photo whose keypoints all lie in its picture is left as it is, so a rerun changes nothing."""
    removed: dict[str, int] = {}
    todo = {name: layout for name, layout in layouts.items() if not layout.panels}
    if not todo:
        return removed
    with dbio.open_database(database_path) as db:
        by_name = dbio.images_with_keypoints(db, descriptors=True)
        centre_cameras(db, {n: layout for n, layout in todo.items() if n in by_name})
        kept = {}
        for name, layout in todo.items():
            if name not in by_name:
                continue
            image_id = by_name[name].image_id
            keypoints = dbio.read_keypoints(db, image_id)
            margin = conf["edge_margin"] * max(layout.size)
            x0, y0, x1, y1 = layout.picture
            inside = in_box(keypoints[:, :2], (x0 + margin, y0 + margin, x1 - margin, y1 - margin))
            if not inside.all():
                descriptors, kind = dbio.read_descriptors(db, image_id)
                kept[image_id] = (keypoints[inside], descriptors[inside], kind)
                removed[name] = int((~inside).sum())
    if kept:
        dbio.replace_features(database_path, kept)
        logger.info(
            "Removed %d keypoints on the borders and captions of %d card(s).",
            sum(removed.values()),
            len(removed),
        )
    return removed


def centre_cameras(db, layouts: dict[str, Layout]) -> None:
    """The camera of each card (its own; a shared one is left alone) gets its principal point at
    the picture's centre, and without an EXIF focal length COLMAP's prior for the picture's size:
    the scan's centre is not the photo's (a caption band shifts it), and mapping keeps the
    principal point fixed."""
    images_by_name = dbio.images_by_name(db)
    users: dict[int, int] = {}
    for image in images_by_name.values():
        users[image.camera_id] = users.get(image.camera_id, 0) + 1
    for name, layout in layouts.items():
        camera_id = images_by_name[name].camera_id
        if users[camera_id] > 1:
            continue
        camera = dbio.read_camera(db, camera_id)
        x0, y0, x1, y1 = layout.picture
        if (camera.principal_point_x, camera.principal_point_y) == ((x0 + x1) / 2, (y0 + y1) / 2):
            continue
        camera.principal_point_x, camera.principal_point_y = (x0 + x1) / 2, (y0 + y1) / 2
        if not camera.has_prior_focal_length:
            camera.focal_length = 1.2 * max(x1 - x0, y1 - y0)  # COLMAP's prior, for the picture
        dbio.update_camera(db, camera)


def in_box(xy: np.ndarray, box: Box) -> np.ndarray:
    """Which points (COLMAP's pixel convention: a pixel's centre at +0.5) lie in ``box``."""
    x0, y0, x1, y1 = box
    return (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)


def print_fit(xy_a: np.ndarray, xy_b: np.ndarray, size_a: tuple, size_b: tuple, conf: dict) -> dict:
    """How well one similarity transform (scale, turn, shift: a rescan, a crop) maps the matched
    points ``xy_a`` onto ``xy_b``: its inliers (within ``max_print_error`` of picture b's
    diagonal), their share, and the share of the pictures they cover (the larger)."""
    threshold = conf["max_print_error"] * float(np.hypot(*size_b))
    model, inliers = cv2.estimateAffinePartial2D(
        xy_a.astype(np.float32),
        xy_b.astype(np.float32),
        method=cv2.RANSAC,
        ransacReprojThreshold=threshold,
        maxIters=2000,
        confidence=0.999,
    )
    if model is None:
        return {"inliers": 0, "inlier_ratio": 0.0, "cover": 0.0}
    inliers = inliers.ravel().astype(bool)
    cover = max(
        cv2.contourArea(cv2.convexHull(xy[inliers].astype(np.float32))) / (size[0] * size[1])
        if inliers.sum() >= 3
        else 0.0
        for xy, size in ((xy_a, size_a), (xy_b, size_b))
    )
    return {
        "inliers": int(inliers.sum()),
        "inlier_ratio": round(float(inliers.mean()), 3),
        "cover": round(float(cover), 3),
    }


def is_same_print(fit: dict, conf: dict) -> bool:
    """One print twice: the similarity explains nearly all verified inliers over much of a
    picture. Two views of a planar facade from two places need a perspective homography and
    fail."""
    return (
        fit["inliers"] >= conf["min_print_inliers"]
        and fit["inlier_ratio"] >= conf["min_print_inlier_ratio"]
        and fit["cover"] >= conf["min_print_cover"]
    )


def print_fits(database_path: Path, conf: dict) -> tuple[list[tuple[str, str, dict]], dict]:
    """(``print_fit`` of every verified pair with at least ``min_print_inliers`` inliers, as
    (name a, name b, fit); {name: verified inliers with all others})."""
    fits, support = [], {}
    with dbio.open_database(database_path) as db:
        names = dbio.image_names(db)
        inliers = dbio.read_verified_inliers(db)
        sizes = {}
        for image in dbio.images_by_name(db).values():
            camera = dbio.read_camera(db, image.camera_id)
            sizes[image.image_id] = (camera.width, camera.height)
        keypoints: dict[int, np.ndarray] = {}
        for (id_a, id_b), matches in inliers.items():
            for image_id in (id_a, id_b):
                support[names[image_id]] = support.get(names[image_id], 0) + len(matches)
            if len(matches) < conf["min_print_inliers"]:
                continue
            for image_id in (id_a, id_b):
                if image_id not in keypoints:
                    keypoints[image_id] = dbio.read_keypoints(db, image_id)[:, :2]
            xy_a, xy_b = keypoints[id_a][matches[:, 0]], keypoints[id_b][matches[:, 1]]
            fit = print_fit(xy_a, xy_b, sizes[id_a], sizes[id_b], conf)
            fits.append((names[id_a], names[id_b], fit))
    return fits, support


def repeated_prints(database_path: Path, conf: dict) -> dict[str, dict]:
    """{photo: {"same_picture_as": representative, fit}} for every verified pair that is one
    print twice (``is_same_print``), grouped: each group keeps as representative its photo with
    the most verified inliers to the others; the rest share its viewpoint, so they are no
    independent evidence and are left out of mapping."""
    if not conf["enabled"]:
        return {}
    fits, support = print_fits(database_path, conf)
    pairs = [(a, b, fit) for a, b, fit in fits if is_same_print(fit, conf)]
    if not pairs:
        return {}
    # groups: connected components of the same-print pairs
    group = {name: name for pair in pairs for name in pair[:2]}

    def root(name: str) -> str:
        while group[name] != name:
            name = group[name]
        return name

    for a, b, _ in pairs:
        group[root(a)] = root(b)
    members: dict[str, list[str]] = {}
    for name in group:
        members.setdefault(root(name), []).append(name)
    evidence = {frozenset((a, b)): e for a, b, e in pairs}
    out = {}
    for names_in in members.values():
        keep = max(sorted(names_in), key=lambda n: support.get(n, 0))
        for name in sorted(names_in):
            if name != keep:
                found = evidence.get(frozenset((name, keep))) or next(
                    e for pair, e in evidence.items() if name in pair
                )
                out[name] = {"same_picture_as": keep, **found}
                logger.info("%s is the same picture as %s: left out of mapping.", name, keep)
    return out


def card_report(
    layouts: dict[str, Layout],
    panels: dict[str, list[str]],
    masked: dict[str, int],
    prints: dict[str, dict],
    registered: set[str],
) -> dict:
    """report.json's part on cards: per card its picture rectangle, and the keypoints removed
    outside it or its panels (each a photo of its own, and whether it was registered); per
    repeated print the picture it repeats and the evidence."""
    out: dict = {"cards": {}, "repeated_prints": {}}
    for name, layout in layouts.items():
        entry = layout.to_dict()
        if layout.panels:
            entry["panels"] = [
                {"name": panel, "box": list(box), "registered": panel in registered}
                for panel, box in zip(panels.get(name, []), layout.panels)
            ]
        else:
            entry["keypoints_masked"] = masked.get(name, 0)
        out["cards"][name] = entry
    out["repeated_prints"] = prints
    return out


def colmap_names(report: dict) -> dict[str, str]:
    """{the name COLMAP reads a collage panel by (its path from the photo folder, which climbs out
    of it): the panel's name in the report and the page, its path inside the workspace}."""
    panels = [p["name"] for c in (report.get("cards") or {}).values() for p in c.get("panels", [])]
    workspace = Path(report.get("report_path") or ".").parent
    out = {}
    for name in panels:
        shown = f"{PANELS}/{Path(name).name}"
        read = os.path.relpath(workspace / shown, Path(report.get("image_path") or "."))
        out[Path(read).as_posix()] = shown
    return out


def renamed(x, names: dict[str, str]):
    """``x`` (a report, a page) with each key of ``names`` replaced by its value, in every list,
    key and sentence."""
    if not names:
        return x
    pattern = re.compile("|".join(map(re.escape, sorted(names, key=len, reverse=True))))

    def rename(x):
        if isinstance(x, str):
            return pattern.sub(lambda m: names[m[0]], x)
        if isinstance(x, dict):
            return {rename(k): rename(v) for k, v in x.items()}
        if isinstance(x, list):
            return [rename(v) for v in x]
        return x

    return rename(x)


def explain_prints(prints: dict[str, dict], registered: set[str]) -> dict[str, dict]:
    """report.explain_unregistered's entry of each repeated print left out of mapping."""
    out = {}
    for name, evidence in prints.items():
        same = evidence["same_picture_as"]
        pose = "it has the pose of" if same in registered else "neither is placed, like"
        out[name] = {
            "stage": "repeated print",
            "reason": f"The same picture as {same} (another print or a crop of it: "
            f"{evidence['inlier_ratio']:.0%} of the verified matches fit one scaling): one "
            f"viewpoint, mapped once; {pose} {same}.",
            "suggestion": "Nothing to do; to map it as a photo of its own, remove the other "
            "print from the folder.",
        }
    return out
