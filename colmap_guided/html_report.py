"""report.html: one self-contained page (images embedded as base64) a historian can open and read.

    write_html_report(path, report, panels)   # report: the dict of report.json
    panels = match_panels({"guided": db_a, "raw": db_b}, image_path)   # raw vs guided on the same pairs

It shows the registered ratio (all images and per era), a plot, the images that were not registered and
the ones that were skipped (with the reason), and drawings of the verified (inlier) matches of a few pairs.
A panel is ``(title, image_a, image_b, matches)``: images as paths or uint8 RGB arrays, ``matches`` an
(M, 4) array of x_a, y_a, x_b, y_b in COLMAP pixel coordinates (pixel centre = +0.5, EXIF rotation not
applied, as ``images.read_image``).

    python -m colmap_guided report OUTPUT [--compare raw=OTHER_OUTPUT/database.db]   # rewrite the page
"""

from __future__ import annotations

import base64
import datetime
import html
import io
from pathlib import Path

import numpy as np

from . import database as dbio
from . import images
from .log import logger

MAX_LINES = 150  # match lines drawn per pair (an even subset beyond)
Panel = tuple  # (title: str, image_a: Path | np.ndarray, image_b: Path | np.ndarray, matches: (M, 4) ndarray)

CSS = """
body { font-family: Georgia, 'Times New Roman', serif; margin: 2em auto; max-width: 1100px; color: #222; background: #fdfcf8; }
h1 { font-size: 1.7em; margin-bottom: 0.2em; } h2 { border-bottom: 1px solid #ccb; padding-bottom: 0.2em; margin-top: 1.6em; }
.sub { color: #666; margin-top: 0; }
.big { font-size: 2.4em; font-weight: bold; color: #2d5f2e; }
table { border-collapse: collapse; margin: 0.5em 0; } td, th { border: 1px solid #ddd; padding: 0.25em 0.7em; text-align: left; }
th { background: #f1efe6; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
.grid { display: flex; flex-wrap: wrap; gap: 8px; } .grid figure { margin: 0; width: 168px; font-size: 0.75em; word-break: break-all; }
.grid img { max-width: 160px; max-height: 160px; border: 1px solid #ccc; display: block; }
figure.pair { margin: 1em 0; } figure.pair img { max-width: 100%; border: 1px solid #ccc; }
.warn { color: #8a3b12; } .muted { color: #888; }
"""


def _data_uri(png_or_jpeg: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(png_or_jpeg).decode('ascii')}"


def _encode_jpeg(rgb: np.ndarray, quality: int = 85) -> str:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb)).save(buf, format="JPEG", quality=quality)
    return _data_uri(buf.getvalue(), "image/jpeg")


def _figure_png(fig, photo: bool = False) -> str:
    """The figure as a data URI: PNG for plots, JPEG for photo drawings (ten times smaller)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches=None if photo else "tight")
    plt.close(fig)
    if not photo:
        return _data_uri(buf.getvalue(), "image/png")
    from PIL import Image

    return _encode_jpeg(np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB")), 88)


def _thumbnail(image, max_side: int) -> tuple[np.ndarray, float, float]:
    if isinstance(image, np.ndarray):
        import cv2

        h, w = image.shape[:2]
        s = min(1.0, max_side / max(h, w))
        size = (max(1, round(w * s)), max(1, round(h * s)))
        rgb = image if image.ndim == 3 else np.repeat(image[:, :, None], 3, axis=2)
        return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA), size[0] / w, size[1] / h
    return images.read_thumbnail(image, max_side)


def draw_matches(image_a, image_b, matches: np.ndarray, max_side: int = 560, max_lines: int = MAX_LINES) -> str:
    """Side-by-side drawing of ``matches`` ((M, 4) COLMAP coordinates) as an embedded PNG data URI."""
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
    return _figure_png(fig, photo=True)


def match_panels(databases: dict[str, Path], image_path: Path, num_pairs: int = 3, pairs: list[tuple[str, str]] | None = None) -> list[Panel]:
    """Verified matches of a few pairs in each database ({label: database.db}), the same pairs in all.

    Pairs: ``pairs`` if given, else the ``num_pairs`` pairs with the most inliers in the first database.
    """
    labels = list(databases)
    if not labels:
        return []
    with dbio.open_database(databases[labels[0]]) as db:
        by_id = {image.image_id: image.name for image in db.read_all_images()}
        if pairs is None:
            pair_ids, counts = db.read_two_view_geometry_num_inliers()
            ranked = sorted(zip(counts, pair_ids), key=lambda t: (-t[0], t[1]))
            pairs = []
            for count, pair_id in ranked[:num_pairs]:
                if count <= 0:
                    break
                id_a, id_b = pair_id_to_image_ids(pair_id)
                pairs.append((by_id[id_a], by_id[id_b]))
    panels = []
    for a, b in pairs:
        for label in labels:
            with dbio.open_database(databases[label]) as db:
                named = dbio.images_by_name(db)
                if a not in named or b not in named:
                    continue
                ia, ib = named[a], named[b]
                inliers = db.read_two_view_geometry(ia.image_id, ib.image_id).inlier_matches if db.exists_two_view_geometry(ia.image_id, ib.image_id) else np.zeros((0, 2))
                inliers = np.asarray(inliers, np.int64).reshape(-1, 2)
                ka = np.asarray(db.read_keypoints(ia.image_id))[:, :2]
                kb = np.asarray(db.read_keypoints(ib.image_id))[:, :2]
            xy = np.concatenate([ka[inliers[:, 0]], kb[inliers[:, 1]]], axis=1) if len(inliers) else np.zeros((0, 4))
            panels.append((f"{label}: {a} \u2194 {b} \u2014 {len(inliers)} verified matches", Path(image_path) / a, Path(image_path) / b, xy))
    return panels


def pair_id_to_image_ids(pair_id: int) -> tuple[int, int]:
    import pycolmap

    id_a, id_b = pycolmap.pair_id_to_image_pair(pair_id)
    return int(id_a), int(id_b)


def ratio_plot(report: dict) -> str:
    """Bars: registered / not registered / skipped images, for all images and per era."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    model = report["model"]
    skipped = [name for name in (report.get("skipped_images") or {}) if name in set(model.get("unregistered_images") or [])]
    # Skipped photos are among the unregistered ones: drawn apart, not twice.
    rows = [("all images", model["num_registered"], model["num_images"] - model["num_registered"] - len(skipped), len(skipped))]
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
            ax.text(reg[i] + unreg[i] + skip[i] + 0.02 * max(1, (reg + unreg + skip).max()), i, f"{100 * reg[i] / total:.0f} % registered", va="center", fontsize=9)
    ax.set_yticks(y, labels)
    ax.invert_yaxis()
    ax.set_xlabel("images")
    ax.set_xlim(0, 1.35 * max(1, (reg + unreg + skip).max()))
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.55 if len(rows) == 1 else -0.25), ncol=3, fontsize=8, frameon=False)
    ax.spines[["top", "right"]].set_visible(False)
    return _figure_png(fig)


def _thumb_grid(names: list[str], image_path: Path, reasons: dict[str, str] | None = None, limit: int = 60) -> str:
    items = []
    for name in names[:limit]:
        caption = html.escape(name) + (f"<br><span class='warn'>{html.escape(reasons[name])}</span>" if reasons and name in reasons else "")
        try:
            thumb, _, _ = images.read_thumbnail(Path(image_path) / name, 160)
            img = f"<img src='{_encode_jpeg(thumb, 80)}' alt='{html.escape(name)}'>"
        except Exception:  # noqa: BLE001 - an unreadable photo is listed without a picture
            img = "<div class='muted'>(no preview)</div>"
        items.append(f"<figure>{img}<figcaption>{caption}</figcaption></figure>")
    more = f"<p class='muted'>... and {len(names) - limit} more (see report.json).</p>" if len(names) > limit else ""
    return f"<div class='grid'>{''.join(items)}</div>{more}"


def render_html(report: dict, panels: list[Panel] | None = None, thumbnails: bool = True) -> str:
    model = report["model"]
    image_path = Path(report.get("image_path", "."))
    esc = html.escape
    matcher = report.get("matcher", {})
    matcher_name = matcher.get("name", "?") if isinstance(matcher, dict) else str(matcher)
    out = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>Reconstruction report: {esc(str(report.get('scene', '')))}</title><style>{CSS}</style></head><body>",
        f"<h1>{esc(str(report.get('scene', 'Reconstruction')))}</h1>",
        f"<p class='sub'>{esc(matcher_name)} matching, COLMAP incremental mapping &middot; {datetime.datetime.now():%Y-%m-%d %H:%M} &middot; photos: {esc(str(image_path))}</p>",
        "<h2>Registered images</h2>",
        f"<p><span class='big'>{100 * model['registered_ratio']:.0f}&nbsp;%</span> &nbsp; {model['num_registered']} of {model['num_images']} images are placed in the largest 3D model"
        + (f" ({model['num_models']} models in all)" if model.get("num_models", 1) > 1 else "") + ".</p>",
        "<table><tr><th>images</th><th>registered</th><th>ratio</th></tr>",
        f"<tr><td>all</td><td class='num'>{model['num_registered']}/{model['num_images']}</td><td class='num'>{100 * model['registered_ratio']:.0f} %</td></tr>",
    ]
    for era, r in (report.get("eras") or {}).items():
        out.append(f"<tr><td>{esc(era)}</td><td class='num'>{r['num_registered']}/{r['num_images']}</td><td class='num'>{100 * r['registered_ratio']:.0f} %</td></tr>")
    out.append("</table>")
    out.append(f"<img src='{ratio_plot(report)}' alt='registered images per era'>")
    out.append(
        f"<p>3D points: {model['num_points3D']} &middot; mean track length {model['mean_track_length']:.2f} &middot; "
        f"mean reprojection error {model['mean_reprojection_error']:.2f} px</p>"
    )
    timings = report.get("timings") or {}
    if timings:
        out.append("<p class='muted'>Time: " + ", ".join(f"{esc(k)} {v:.1f} s" for k, v in timings.items()) + "</p>")

    unregistered = model.get("unregistered_images") or []
    skipped = report.get("skipped_images") or {}
    skipped = skipped if isinstance(skipped, dict) else dict.fromkeys(skipped, "unreadable")
    unregistered = [n for n in unregistered if n not in skipped]
    out.append(f"<h2>Images not registered ({len(unregistered)})</h2>")
    if unregistered:
        out.append("<p>These photos were read but could not be placed in the model: too few matches with the others (a different view, era or landmark).</p>")
        out.append(_thumb_grid(unregistered, image_path) if thumbnails else "<ul>" + "".join(f"<li>{esc(n)}</li>" for n in unregistered) + "</ul>")
    else:
        out.append("<p>None.</p>")
    if skipped:
        out.append(f"<h2 class='warn'>Skipped images ({len(skipped)})</h2><table><tr><th>image</th><th>why, and what to do</th></tr>")
        out.extend(f"<tr><td>{esc(n)}</td><td>{esc(r)}</td></tr>" for n, r in skipped.items())
        out.append("</table>")

    out.append("<h2>Matches of a few pairs</h2>")
    if panels:
        out.append("<p>Lines join the same point seen in both photos (verified matches: they agree with one camera geometry).</p>")
        for title, image_a, image_b, matches in panels:
            try:
                uri = draw_matches(image_a, image_b, matches)
            except Exception as err:  # noqa: BLE001 - one unreadable pair must not lose the page
                logger.warning("Could not draw %s (%s)", title, err)
                continue
            shown = f" ({MAX_LINES} drawn)" if len(matches) > MAX_LINES else ""
            out.append(f"<figure class='pair'><figcaption>{esc(title)}{shown}</figcaption><img src='{uri}' alt='{esc(title)}'></figure>")
    else:
        out.append("<p>No pair was verified.</p>")
    database = report.get("database") or {}
    if database:
        out.append("<h2>Details</h2><table>")
        out.extend(f"<tr><td>{esc(str(k))}</td><td class='num'>{esc(str(v))}</td></tr>" for k, v in database.items())
        out.append("</table>")
    for key in ("database_path", "sparse_path", "report_path"):
        if report.get(key):
            out.append(f"<p class='muted'>{esc(key.replace('_', ' '))}: {esc(str(report[key]))}</p>")
    out.append("</body></html>")
    return "\n".join(out)


def write_html_report(path: Path, report: dict, panels: list[Panel] | None = None) -> Path:
    """Write the page atomically (a partial file never replaces a good one)."""
    path = Path(path)
    tmp = path.with_suffix(".html.partial")
    tmp.write_text(render_html(report, panels), encoding="utf-8")
    tmp.replace(path)
    return path


def rewrite_report(output: Path, compare: dict[str, Path] | None = None, num_pairs: int = 3) -> Path:
    """report.html again from OUTPUT/report.json, optionally with the same pairs from other databases."""
    import json

    output = Path(output)
    report_path = output / "report.json"
    if not report_path.is_file():
        raise FileNotFoundError(f"No report.json in {output}: run `python -m colmap_guided reconstruct` first.")
    result = json.loads(report_path.read_text(encoding="utf-8"))
    label = (result.get("matcher") or {}).get("name", "this run")
    databases = {label: Path(result.get("database_path", output / "database.db")), **(compare or {})}
    for name, db in databases.items():
        if not Path(db).is_file():
            raise FileNotFoundError(f"No database for {name!r} at {db}: pass --compare LABEL=PATH/database.db.")
    panels = match_panels(databases, Path(result["image_path"]), num_pairs)
    return write_html_report(output / "report.html", result, panels)
