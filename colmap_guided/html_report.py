"""report.html: one self-contained page (images embedded as base64) a historian can open and read.

    write_html_report(path, report, panels)  # report: the dict of report.json
    panels = match_panels({"guided": db_a, "raw": db_b},
                          image_path)  # raw vs guided on the same pairs

It shows the registered ratio, the largest model in 3D (points and cameras, ``model_view``), a map
of where the photos were taken from (north up in metres, with each photo's latitude and longitude,
where ``georeference`` placed the model on the Earth), the ratio per era, each photo that was not
registered with the stage where it dropped out and why (``report.explain_unregistered``), the
photos placed later by ``localize`` (localized.json beside report.json), and drawings of the
verified matches of a few pairs. A panel is ``(title, image_a, image_b, matches)``: images as
paths or uint8 RGB arrays, ``matches`` an (M, 4) array of x_a, y_a, x_b, y_b in COLMAP pixel
coordinates (pixel centre = +0.5, EXIF rotation not applied, as ``images.read_image``).

    python -m colmap_guided report OUTPUT
        [--compare raw=OTHER_OUTPUT/database.db]   # rewrite the page
"""

from __future__ import annotations

import argparse
import datetime
import html
import inspect
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from . import database as dbio
from . import embed, geoframe, images, model_view
from .cards import PANELS, colmap_names, renamed
from .log import add_verbosity_flags, logger
from .workspace import read_marker

MAX_LINES = 150  # match lines drawn per pair (an even subset beyond)
# (title: str, image_a: Path | np.ndarray, image_b: Path | np.ndarray, matches: (M, 4) ndarray)
Panel = tuple

CSS = embed.asset("report.css")  # the page's style sheet, the 3D view's included


def _thumbnail(image, max_side: int) -> tuple[np.ndarray, float, float]:
    if isinstance(image, np.ndarray):
        h, w = image.shape[:2]
        s = min(1.0, max_side / max(h, w))
        size = (max(1, round(w * s)), max(1, round(h * s)))
        rgb = image if image.ndim == 3 else np.repeat(image[:, :, None], 3, axis=2)
        return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA), size[0] / w, size[1] / h
    return images.read_thumbnail(image, max_side)


def draw_matches(
    image_a, image_b, matches: np.ndarray, max_side: int = 560, max_lines: int = MAX_LINES
) -> str:
    """Side-by-side drawing of ``matches`` ((M, 4) COLMAP coordinates) as an embedded PNG data
    URI."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ta, sxa, sya = _thumbnail(image_a, max_side)
    tb, sxb, syb = _thumbnail(image_b, max_side)
    gap = 10
    height = max(ta.shape[0], tb.shape[0])
    canvas = np.full((height, ta.shape[1] + gap + tb.shape[1], 3), 255, np.uint8)
    canvas[: ta.shape[0], : ta.shape[1]] = ta
    canvas[: tb.shape[0], ta.shape[1] + gap :] = tb
    matches = np.asarray(matches, np.float64).reshape(-1, 4)
    if len(matches) > max_lines:  # an even subset, always the same for the same matches
        matches = matches[np.linspace(0, len(matches) - 1, max_lines).round().astype(int)]
    fig = plt.figure(figsize=(canvas.shape[1] / 100, canvas.shape[0] / 100), dpi=100)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(canvas, interpolation="nearest")
    if len(matches):
        # COLMAP x (pixel centre at +0.5) -> thumbnail pixel-centre coordinates used by imshow.
        xa, ya = matches[:, 0] * sxa - 0.5, matches[:, 1] * sya - 0.5
        xb, yb = matches[:, 2] * sxb - 0.5 + ta.shape[1] + gap, matches[:, 3] * syb - 0.5
        colors = plt.cm.viridis(np.linspace(0, 1, len(matches)))
        for i in range(len(matches)):
            ax.plot([xa[i], xb[i]], [ya[i], yb[i]], "-", color=colors[i], linewidth=0.7, alpha=0.8)
        ax.scatter(np.r_[xa, xb], np.r_[ya, yb], s=3, c=np.r_[colors, colors], linewidths=0)
    ax.set_xlim(-0.5, canvas.shape[1] - 0.5)
    ax.set_ylim(canvas.shape[0] - 0.5, -0.5)
    ax.axis("off")
    return embed.figure_uri(fig, photo=True)


def match_panels(
    databases: dict[str, Path],
    image_path: Path,
    num_pairs: int = 3,
    pairs: list[tuple[str, str]] | None = None,
) -> list[Panel]:
    """Verified matches of a few pairs in each database ({label: database.db}), the same pairs in
    all.

    Pairs: ``pairs`` if given, else the ``num_pairs`` pairs with the most inliers in the first
    database.
    """
    labels = list(databases)
    if not labels:
        return []
    with dbio.open_database(databases[labels[0]]) as db:
        by_id = dbio.image_names(db)
        if pairs is None:
            ranked = sorted(dbio.pair_inlier_counts(db).items(), key=lambda t: (-t[1], t[0]))
            pairs = [
                (by_id[id_a], by_id[id_b])
                for (id_a, id_b), count in ranked[:num_pairs]
                if count > 0
            ]
    panels = []
    for a, b in pairs:
        for label in labels:
            with dbio.open_database(databases[label]) as db:
                named = dbio.images_by_name(db)
                if a not in named or b not in named:
                    continue
                ia, ib = named[a], named[b]
                geometry = dbio.read_two_view_geometry(db, ia.image_id, ib.image_id)
                inliers = np.asarray(
                    geometry.inlier_matches if geometry is not None else np.zeros((0, 2)), np.int64
                ).reshape(-1, 2)
                ka = dbio.read_keypoints(db, ia.image_id)[:, :2]
                kb = dbio.read_keypoints(db, ib.image_id)[:, :2]
            xy = (
                np.concatenate([ka[inliers[:, 0]], kb[inliers[:, 1]]], axis=1)
                if len(inliers)
                else np.zeros((0, 4))
            )
            panels.append(
                (
                    f"{label}: {a} \u2194 {b} \u2014 {len(inliers)} verified matches",
                    Path(image_path) / a,
                    Path(image_path) / b,
                    xy,
                )
            )
    return panels


def ratio_plot(report: dict) -> str:
    """Bars: registered / not registered / skipped images, for all images and per era."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    model = report["model"]
    skipped = [
        name
        for name in (report.get("skipped_images") or {})
        if name in set(model.get("unregistered_images") or [])
    ]
    # Skipped photos are among the unregistered ones: drawn apart, not twice.
    rows = [
        (
            "all images",
            model["num_registered"],
            model["num_images"] - model["num_registered"] - len(skipped),
            len(skipped),
        )
    ]
    for era, r in (report.get("eras") or {}).items():
        rows.append((era, r["num_registered"], r["num_images"] - r["num_registered"], 0))
    labels = [r[0] for r in rows]
    reg, unreg, skip = (np.array([r[i] for r in rows], float) for i in (1, 2, 3))
    fig, ax = plt.subplots(figsize=(7, 0.6 + 0.55 * len(rows)))
    y = np.arange(len(rows))
    ax.barh(y, reg, color="#3b7d3c", label="registered")
    ax.barh(y, unreg, left=reg, color="#d9a441", label="not registered")
    ax.barh(y, skip, left=reg + unreg, color="#a23b2a", label="skipped (unreadable)")
    for i in range(len(rows)):
        total = reg[i] + unreg[i] + skip[i]
        if total:
            ax.text(
                reg[i] + unreg[i] + skip[i] + 0.02 * max(1, (reg + unreg + skip).max()),
                i,
                f"{100 * reg[i] / total:.0f} % registered",
                va="center",
                fontsize=9,
            )
    ax.set_yticks(y, labels)
    ax.invert_yaxis()
    ax.set_xlabel("images")
    ax.set_xlim(0, 1.35 * max(1, (reg + unreg + skip).max()))
    ax.legend(
        loc="upper center",
        bbox_to_anchor=(0.5, -0.55 if len(rows) == 1 else -0.25),
        ncol=3,
        fontsize=8,
        frameon=False,
    )
    ax.spines[["top", "right"]].set_visible(False)
    return embed.figure_uri(fig)


STAGE_WORDS = {
    "reading": "reading the file",
    "features": "finding details",
    "matching": "matching with other photos",
    "mapping": "placing it in the model",
}


def _why_table(report: dict, image_path: Path, thumbnails: bool) -> list[str]:
    """Each photo that is not in the model: its thumbnail, the stage where it dropped out, why, and
    what to do."""
    esc = html.escape
    skipped = report.get("skipped_images") or {}
    skipped = skipped if isinstance(skipped, dict) else dict.fromkeys(skipped, "unreadable")
    why = dict(report.get("unregistered") or {})
    for name, reason in skipped.items():  # a report.json written before the explanations
        why.setdefault(
            name,
            {
                "stage": "reading",
                "reason": f"The file could not be used: {reason}.",
                "suggestion": "",
            },
        )
    # a photo in another model is that model's (listed above), not a failure
    elsewhere = {n for m in (report.get("models") or [])[1:] for n in m["images"]}
    names = [n for n in report["model"].get("unregistered_images") or [] if n not in elsewhere]
    names += [n for n in why if n not in names]
    out = [f"<h2>Photos in no model, and why ({len(names)})</h2>"]
    if not names:
        return out + ["<p>None: every photo is in a model.</p>"]
    out.append(
        "<table class='why'><tr><th></th><th>photo</th>"
        "<th>dropped out at</th><th>why</th><th>what to do</th></tr>"
    )
    for i, name in enumerate(names):
        entry = why.get(
            name,
            {
                "stage": "",
                "reason": "Too few matches with the other "
                "photos (a different view, era or landmark).",
                "suggestion": "",
            },
        )
        shown = thumbnails and i < 60 and entry["stage"] != "reading"
        img = _img(_file(report, image_path, name), shown)
        stage = STAGE_WORDS.get(entry["stage"], entry["stage"])
        cls = " class='warn'" if entry["stage"] == "reading" else ""
        out.append(
            f"<tr><td>{img}</td><td>{esc(name)}</td><td{cls}>{esc(stage)}</td>"
            f"<td>{esc(entry['reason'])}</td><td>{esc(entry['suggestion'])}</td></tr>"
        )
    out.append("</table>")
    return out


def _localized_file(report: dict) -> dict:
    """localized.json beside report.json (``localize``), {} when there is none."""
    import json

    path = (
        Path(report["report_path"]).with_name("localized.json")
        if report.get("report_path")
        else None
    )
    try:
        return dict(json.loads(path.read_text(encoding="utf-8"))) if path else {}
    except (OSError, ValueError, AttributeError, TypeError):
        return {}


def _localized(report: dict) -> list[dict]:
    """The entries of localized.json, [] when there is none."""
    return list(_localized_file(report).get("photos", []))


def _posed(report: dict) -> list[dict]:
    """The entries of localized.json drawn in the 3D view: placed or uncertain, with a pose."""
    shown = ("placed", "uncertain")
    return [e for e in _localized(report) if e.get("status") in shown and "qvec_wxyz" in e]


def _localized_into(report: dict) -> int:
    """The index N of the model sparse/N that ``localize`` placed its photos in."""
    name = Path(_localized_file(report).get("model") or "0").name
    return int(name) if name.isdigit() else 0


def _file(report: dict, image_path: Path, name: str) -> Path:
    """A photo's file: a collage panel (``panels/...`` in the report) is in the workspace."""
    panel = Path(report.get("report_path") or ".").parent / name
    return panel if name.startswith(PANELS + "/") and panel.is_file() else image_path / name


def _img(path: Path, thumbnails: bool, side: int = 120) -> str:
    if not thumbnails:
        return ""
    try:
        return (
            f"<img src='{embed.encode_jpeg(images.read_thumbnail(path, side)[0], 75)}' "
            f"alt='{html.escape(path.name)}'>"
        )
    except Exception:  # noqa: BLE001 - a photo moved away since the run is listed without a picture
        return ""


def _localized_table(report: dict, image_path: Path, thumbnails: bool) -> list[str]:
    """Each photo of ``localize``: its thumbnail, the verdict, pose numbers and the model photo it
    matched best."""
    entries = _localized(report)
    if not entries:
        return []
    esc = html.escape
    placed = sum(e.get("status") == "placed" for e in entries)
    out = [
        f"<h2>Photos localized in the model ({placed} of {len(entries)} placed)</h2>",
        (
            "<p>Photos added later with <code>localize</code>: where each was taken from, "
            "found by matching it with the model's photos (results in localized.json).</p>"
        ),
        (
            "<table class='why'><tr><th></th><th>photo</th><th>result</th>"
            "<th>inliers</th><th>focal length</th><th>position (model units)</th>"
            "<th>latitude, longitude</th><th>heading</th>"
            "<th>best-matched model photo</th><th></th></tr>"
        ),
    ]
    for i, entry in enumerate(entries):
        photo = Path(entry.get("photo", ""))
        best = (entry.get("matched_images") or [{}])[0]
        centre = entry.get("centre")
        cls = "" if entry.get("status") == "placed" else " class='warn'"
        cells = [
            _img(photo, thumbnails and i < 60),
            esc(photo.name),
            f"<span{cls}>{esc(entry.get('confidence', ''))}</span>",
            str(entry.get("num_inliers", "")),
            f"{entry['focal_length']:.0f} px" if entry.get("focal_length") else "",
            ", ".join(f"{c:.2f}" for c in centre) if centre else "",
            _lat_lon(entry) if "latitude" in entry else "",
            f"{entry['heading']:.0f}&deg;" if "heading" in entry else "",
            f"{esc(best['image'])} ({best['matches']} matches)" if best else "",
            _img(image_path / best["image"], thumbnails and i < 60) if best else "",
        ]
        out.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    out.append("</table>")
    return out


def _lat_lon(place: dict) -> str:
    """ "55.704700, 13.193400" linked to OpenStreetMap at that point."""
    text = f"{place['latitude']:.6f}, {place['longitude']:.6f}"
    return f"<a href='{html.escape(geoframe.osm_url(place))}'>{text}</a>"


def _geo_table(geo: dict) -> list[str]:
    """Each photo's latitude and longitude (a link to OpenStreetMap there), altitude, heading."""
    out = [
        "<p>Each photo's camera on the Earth (georeference: "
        f"{sum(c['used'] for c in geo['controls'])} control photos, "
        f"{geo['rms_m']:.2f} m RMS; Google Earth: geo/cameras.kml, QGIS: "
        "geo/cameras.geojson).</p>",
        "<table><tr><th>photo</th><th>latitude, longitude</th><th>altitude (m)</th>"
        "<th>heading (&deg; from north)</th></tr>",
    ]
    for name, cam in geo["cameras"].items():
        out.append(
            f"<tr><td>{html.escape(name)}</td><td>{_lat_lon(cam)}</td>"
            f"<td class='num'>{cam['altitude']:.1f}</td>"
            f"<td class='num'>{cam['heading']:.0f}</td></tr>"
        )
    return out + ["</table>"]


def _load_model(report: dict):
    """The largest model (sparse/0) of a report, or None."""
    path = Path(report.get("sparse_path") or "") / "0"
    if not report.get("sparse_path") or not (
        (path / "images.bin").is_file() or (path / "images.txt").is_file()
    ):
        return None
    import pycolmap

    return pycolmap.Reconstruction(str(path))


def _cards_table(report: dict, image_path: Path, thumbnails: bool) -> list[str]:
    """Scanned cards: the picture kept (green) and the panels cut out (orange, numbered), and the
    repeated prints."""
    cards, prints = report.get("cards") or {}, report.get("repeated_prints") or {}
    if not cards and not prints:
        return []
    esc = html.escape
    out = [
        "<h2>Scanned cards</h2><p>Keypoints are kept only on the picture (green): not on the "
        "card's border, caption or publisher's mark. The pictures of a collage card (orange) "
        "are mapped as photos of their own.</p><table>",
    ]
    for name, card in cards.items():
        figure = ""
        if thumbnails:
            try:
                thumb, sx, sy = images.read_thumbnail(_file(report, image_path, name), 240)
                thumb = thumb.copy()  # (drawn on)
                boxes = [card["picture"]] + [p["box"] for p in card.get("panels", [])]
                for k, (x0, y0, x1, y1) in enumerate(boxes):
                    colour = (0, 170, 0) if k == 0 else (255, 140, 0)
                    corners = (int(x0 * sx), int(y0 * sy)), (int(x1 * sx) - 1, int(y1 * sy) - 1)
                    cv2.rectangle(thumb, *corners, colour, 2)
                    if k:
                        cv2.putText(
                            thumb,
                            str(k),
                            corners[0][:1] + (corners[0][1] + 14,),
                            cv2.FONT_HERSHEY_SIMPLEX,
                            0.5,
                            colour,
                            2,
                        )
                figure = f"<img src='{embed.encode_jpeg(thumb, 80)}' alt='{esc(name)}'>"
            except Exception:  # noqa: BLE001 - a photo moved away since the run
                figure = ""
        if card.get("panels"):
            what = f"{len(card['panels'])} pictures: " + ", ".join(
                f"{k} {esc(p['name'].rsplit('/', 1)[-1])} "
                + ("(placed)" if p["registered"] else "(not placed)")
                for k, p in enumerate(card["panels"], 1)
            )
        else:
            what = f"{card.get('keypoints_masked', 0)} keypoints removed outside the picture"
        out.append(f"<tr><td>{figure}</td><td>{esc(name)}</td><td>{what}</td></tr>")
    for name, evidence in prints.items():
        out.append(
            f"<tr><td>{_img(_file(report, image_path, name), thumbnails)}</td><td>{esc(name)}</td>"
            "<td>same "
            f"picture as {esc(evidence['same_picture_as'])}: mapped once</td></tr>"
        )
    out.append("</table>")
    return out


def render_html(
    report: dict, panels: list[Panel] | None = None, thumbnails: bool = True, reconstruction=None
) -> str:
    """The page. ``reconstruction``: the largest pycolmap.Reconstruction (default: read from
    report's sparse_path/0)."""
    image_path = Path(report.get("image_path", "."))
    rec, eras, geo = _page_model(report, reconstruction)
    out = _header(report, image_path)
    if rec is not None and rec.num_reg_images():
        others = _other_models(report)
        out += _model_section(rec, eras, geo, image_path if thumbnails else None, others)
    out += _models_table(report) + _splits_table(report) + _joins_table(report)
    out += _ratio_section(report)
    out += _why_table(report, image_path, thumbnails)
    out += _localized_table(report, image_path, thumbnails)
    out += _cards_table(report, image_path, thumbnails)
    out += _panels_section(panels)
    out += _details_section(report)
    out.append("</body></html>")
    # the 3D view names its cameras as the model does: a panel by its name in the report
    return renamed("\n".join(out), colmap_names(report))


def _page_model(report: dict, reconstruction) -> tuple:
    """The model drawn (localized cameras added, in ENU metres where georeferenced), each photo's
    era, and the georeference (or None)."""
    from .report import read_manifest

    rec = reconstruction if reconstruction is not None else _load_model(report)
    eras = read_manifest(Path(report["manifest_path"])) if report.get("manifest_path") else {}
    localized = _posed(report) if _localized_into(report) == 0 else []
    # the localized photos' cameras, in their colour
    if rec is not None and rec.num_reg_images() and localized:
        rec, names = model_view.with_cameras(rec, localized)
        model_eras = {rec.images[i].name: "photo" for i in rec.reg_image_ids()}
        eras = {**model_eras, **eras, **dict.fromkeys(names, "localized")}
    geo = geoframe.load(Path(report["report_path"]).parent) if report.get("report_path") else None
    if rec is not None and geo is not None:  # shown in east-north-up metres
        rec = pycolmap.Reconstruction(rec)
        rec.transform(geo[0].sim3d())
    return rec, eras, geo


def _header(report: dict, image_path: Path) -> list[str]:
    """The page's head, title, matcher line and the registered ratio in large."""
    model = report["model"]
    esc = html.escape
    matcher = report.get("matcher", {})
    matcher_name = matcher.get("name", "?") if isinstance(matcher, dict) else str(matcher)
    return [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>Reconstruction report: {esc(str(report.get('scene', '')))}"
        f"</title><style>\n{CSS}</style></head><body>",
        f"<h1>{esc(str(report.get('scene', 'Reconstruction')))}</h1>",
        f"<p class='sub'>{esc(matcher_name)} matching, COLMAP incremental mapping &middot; "
        f"{datetime.datetime.now():%Y-%m-%d %H:%M} &middot; photos: {esc(str(image_path))}</p>",
        f"<p><span class='big'>{100 * model['registered_ratio']:.0f}&nbsp;%</span> "
        f"&nbsp; {model['num_registered']} of {model['num_images']} images are "
        "placed in the largest 3D model"
        + (f" ({model['num_models']} models in all)" if model.get("num_models", 1) > 1 else "")
        + ".</p>",
    ]


def _other_models(report: dict) -> list[tuple[int, pycolmap.Reconstruction]]:
    """The workspace's models after the largest (sparse/1, ...), as the report lists them; the one
    ``localize`` placed photos in with their cameras."""
    root, into = Path(report.get("sparse_path") or ""), _localized_into(report)
    out = []
    for m in (report.get("models") or [])[1 : 1 + model_view.MAX_OTHER_MODELS]:
        if (root / str(m["index"]) / "images.bin").is_file():
            rec = pycolmap.Reconstruction(str(root / str(m["index"])))
            if m["index"] == into:
                rec = model_view.with_cameras(rec, _posed(report))[0]
            out.append((m["index"], rec))
    return out


def _models_table(report: dict) -> list[str]:
    """Every model: a building, or a part of one; its photos, points and model check."""
    models = report.get("models") or []
    if len(models) < 2:
        return []
    esc = html.escape
    out = [
        f"<h2>The models ({len(models)})</h2><p>Photos that matched each other but no photo of "
        "another group make a model of their own: usually another building, or another side of "
        "one. Each is a result (in the 3D view's list, in its folder with points3D.ply and COLMAP "
        "text; <code>localize</code> and <code>georeference</code> take <code>--model N</code>)."
        "</p><table><tr><th>model</th><th>photos</th><th>3D points</th><th>model check</th>"
        "<th>photos in it</th></tr>",
    ]
    for m in models:
        names = ", ".join(m["images"][:8]) + (" ..." if len(m["images"]) > 8 else "")
        check = (
            "<td>passes</td>"
            if m["passes_check"]
            else f"<td class='warn'>{len(m['problems'])} problem(s)</td>"
        )
        out.append(
            f"<tr><td>{esc(m['path'])}</td><td class='num'>{m['num_registered']}</td>"
            f"<td class='num'>{m['num_points3D']}</td>{check}<td>{esc(names)}</td></tr>"
        )
    return out + ["</table>"]


def _splits_table(report: dict) -> list[str]:
    """Each model cut in two: the photos of each side, and the evidence."""
    cuts = (report.get("database") or {}).get("splits") or []
    if not cuts:
        return []
    out = [
        f"<h2>Models cut in two ({len(cuts)})</h2><p>A model whose two sides put most of their "
        "points well in front of what the other side's photos see there is two places that look "
        "alike (a repeated facade, one architect's windows) mapped as one: each side is a model "
        "of its own.</p><table><tr><th>photos of each side</th><th>points well in front / at "
        "the depth seen</th></tr>",
    ]
    for cut in cuts:
        sides = " | ".join(
            html.escape(", ".join(p[:4]) + (" ..." if len(p) > 4 else "")) for p in cut["photos"]
        )
        evidence = f"{cut['conflicts']} / {cut['agreements']}"
        out.append(f"<tr><td>{sides}</td><td class='num'>{evidence}</td></tr>")
    return out + ["</table>"]


def _joins_table(report: dict) -> list[str]:
    """Each two models tried for joining: their photos, the cross pairs matched and verified, and
    whether they were joined, or why not."""
    tries = (report.get("database") or {}).get("joins") or []
    if not tries:
        return []
    joined = sum(t["joined"] for t in tries)
    out = [
        f"<h2>Joining models ({len(tries)} tried, {joined} joined)</h2><p>Two models whose photos "
        "look alike: their most similar photos across them matched; where those pairs verify on "
        "several photos of each, the models are merged, and the merge is kept only where it "
        "passes the model check and its two parts agree on what their photos see (two buildings "
        "of one style stay two).</p><table><tr><th>models (photos)</th><th>pairs matched now / "
        "verified</th><th>joined</th></tr>",
    ]
    for t in tries:
        models = " and ".join(f"sparse/{k} ({n})" for k, n in zip(t["models"], t["photos"]))
        result = "yes" if t["joined"] else f"no: {html.escape(t.get('why', ''))}"
        out.append(
            f"<tr><td>{models}</td><td class='num'>{t['matched']} / {t['verified']}</td>"
            f"<td>{result}</td></tr>"
        )
    return out + ["</table>"]


def _model_section(rec, eras: dict, geo, photos: Path | None, others=()) -> list[str]:
    """The 3D view (``others``: the other models, in its picker) and the map of the largest model's
    camera positions (with their latitudes where georeferenced); ``photos``: the folder for the
    view's thumbnails, or None."""
    enu = geo is not None
    out = [
        f"<h2>The 3D model{f's ({1 + len(others)}: pick one)' if others else ''}</h2>",
        model_view.view_html(rec, eras, photos, enu=enu, others=others),
        f"<h2>Where the photos were taken from{' (the largest model)' if others else ''}</h2>",
        "<p>Seen from above: the points of the model, each photo's "
        "position (dot) and the direction it looks in (arrow)"
        + (f", north up, in metres from {_lat_lon(geo[1]['origin'])}.</p>" if enu else ".</p>"),
        f"<img src='{model_view.photo_map(rec, eras, enu)}' alt='map of the camera positions'>",
    ]
    return out + _geo_table(geo[1]) if enu else out


def _ratio_section(report: dict) -> list[str]:
    """Registered images, all and per era (table and bars), model figures and timings."""
    model = report["model"]
    esc = html.escape
    out = [
        "<h2>Registered images</h2>",
        "<table><tr><th>images</th><th>registered</th><th>ratio</th></tr>",
        f"<tr><td>all</td><td class='num'>{model['num_registered']}/{model['num_images']}</td>"
        f"<td class='num'>{100 * model['registered_ratio']:.0f} %</td></tr>",
    ]
    for era, r in (report.get("eras") or {}).items():
        out.append(
            f"<tr><td>{esc(era)}</td><td class='num'>{r['num_registered']}/{r['num_images']}</td>"
            f"<td class='num'>{100 * r['registered_ratio']:.0f} %</td></tr>"
        )
    out.append("</table>")
    out.append(f"<img src='{ratio_plot(report)}' alt='registered images per era'>")
    out.append(
        f"<p>3D points: {model['num_points3D']} &middot; mean track "
        f"length {model['mean_track_length']:.2f} &middot; mean "
        f"reprojection error {model['mean_reprojection_error']:.2f} px</p>"
    )
    timings = report.get("timings") or {}
    if timings:
        out.append(
            "<p class='muted'>Time: "
            + ", ".join(f"{esc(k)} {v:.1f} s" for k, v in timings.items())
            + "</p>"
        )
    return out


def _panels_section(panels: list[Panel] | None) -> list[str]:
    """The drawings of the verified matches of a few pairs."""
    out = ["<h2>Matches of a few pairs</h2>"]
    if not panels:
        return out + ["<p>No pair was verified.</p>"]
    out.append(
        "<p>Lines join the same point seen in both photos (verified "
        "matches: they agree with one camera geometry).</p>"
    )
    for title, image_a, image_b, matches in panels:
        try:
            uri = draw_matches(image_a, image_b, matches)
        except Exception as err:  # noqa: BLE001 - one unreadable pair must not lose the page
            logger.warning("Could not draw %s (%s)", title, err)
            continue
        shown = f" ({MAX_LINES} drawn)" if len(matches) > MAX_LINES else ""
        out.append(
            f"<figure class='pair'><figcaption>{html.escape(title)}{shown}</figcaption>"
            f"<img src='{uri}' alt='{html.escape(title)}'></figure>"
        )
    return out


def _details_section(report: dict) -> list[str]:
    """The database's figures and the paths of what the run wrote."""
    esc = html.escape
    out = []
    database = report.get("database") or {}
    if database:
        out.append("<h2>Details</h2><table>")
        out.extend(
            f"<tr><td>{esc(str(k))}</td><td class='num'>{esc(str(v))}</td></tr>"
            for k, v in database.items()
        )
        out.append("</table>")
    exports = report.get("exports") or {}
    paths = {
        **{k: report.get(k) for k in ("database_path", "sparse_path", "report_path")},
        "points (PLY, for MeshLab or CloudCompare)": exports.get("ply"),
        "model in COLMAP's text format": exports.get("text"),
    }
    out.extend(
        f"<p class='muted'>{esc(key.replace('_', ' '))}: {esc(str(value))}</p>"
        for key, value in paths.items()
        if value
    )
    return out


def write_html_report(
    path: Path, report: dict, panels: list[Panel] | None = None, reconstruction=None
) -> Path:
    """Write the page atomically (a partial file never replaces a good one)."""
    path = Path(path)
    tmp = path.with_suffix(".html.partial")
    tmp.write_text(render_html(report, panels, reconstruction=reconstruction), encoding="utf-8")
    tmp.replace(path)
    return path


def rewrite_report(
    output: Path, compare: dict[str, Path] | None = None, num_pairs: int = 3
) -> Path:
    """report.html again from OUTPUT/report.json, optionally with the same pairs from other
    databases."""
    import json

    output = Path(output)
    report_path = output / "report.json"
    if not report_path.is_file():
        raise FileNotFoundError(
            f"No report.json in {output}: run `python -m colmap_guided reconstruct` first."
        )
    if (read_marker(output) or {}).get(
        "kind"
    ) != "reconstruct":  # report.html there is not ours to replace
        raise ValueError(
            f"{output} is not a workspace written by `reconstruct`: "
            "pass the folder of a run's report.json."
        )
    result = json.loads(report_path.read_text(encoding="utf-8"))
    label = (result.get("matcher") or {}).get("name", "this run")
    databases = {
        label: Path(result.get("database_path", output / "database.db")),
        **(compare or {}),
    }
    for name, db in databases.items():
        if not Path(db).is_file():
            raise FileNotFoundError(
                f"No database for {name!r} at {db}: pass --compare LABEL=PATH/database.db."
            )
    panels = match_panels(databases, Path(result["image_path"]), num_pairs)
    return write_html_report(output / "report.html", result, panels)


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "report",
        help="write OUTPUT/report.html again from report.json, e.g. with raw vs guided matches",
    )
    parser.add_argument(
        "output", type=Path, help="workspace of a reconstruct run (holds report.json)"
    )
    parser.add_argument(
        "--compare",
        action="append",
        default=[],
        metavar="LABEL=DATABASE",
        help="also draw the same pairs from this database (repeatable)",
    )
    parser.add_argument(
        "--num_pairs",
        type=int,
        default=inspect.signature(rewrite_report).parameters["num_pairs"].default,
        help="pairs drawn: those with the most inliers (default: %(default)s)",
    )
    add_verbosity_flags(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    compare = {}
    for item in args.compare:
        label, sep, path = item.partition("=")
        if not sep or not label or not path:
            raise ValueError(
                f"--compare {item!r}: write LABEL=PATH/database.db, "
                "e.g. --compare raw=out_raw/database.db"
            )
        compare[label] = Path(path)
    print(rewrite_report(args.output, compare, args.num_pairs))
