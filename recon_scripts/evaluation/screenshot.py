"""Render OUTPUT/report.html in headless Chromium and save a screenshot PNG (checks the page really
renders).

    python -m recon_scripts.evaluation.screenshot OUTPUT/report.html [--out shot.png]
        [--size 1200,1600]
    python -m recon_scripts.evaluation.screenshot --demo /tmp/demo_scene --photo view_007.jpg
        --size 1400,1600 --out docs/report_demo.png

``--demo DIR`` first makes the README's demo: the synthetic scene (12 views), a manifest that marks
every third view "historical" (those photos toned sepia, as old prints are), and a view of another
building (the synthetic scene of another seed) that cannot register; then reconstructs it with the
default matcher.

Chromium comes from Debian (`apt-get install chromium`); the page is opened from the file system
with the network off, so the screenshot also proves the page needs nothing from outside
(images are embedded). Prints the screenshot path; exit status 1 with a one-line message when no
browser is installed, when the page wrote to the browser's console (the report's own scripts never
do: a message is an error) or when its 3D view shows nothing but its background.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from urllib.parse import quote

from recon_scripts import script_parser

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
# a console message in Chromium's log: [pid:tid:time:INFO:CONSOLE:line] "text", source: url (line)
CONSOLE = re.compile(r":CONSOLE(?::\d+)?\] (.*)$", re.M)
VIEW_BACKGROUND = (0x1D, 0x1F, 0x24)  # #model-view's background in assets/report.css


def find_chromium() -> str | None:
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


def screenshot(
    html_path: Path,
    out_png: Path,
    size: tuple[int, int] = (1200, 1600),
    timeout: float = 120.0,
    photo: str | None = None,
) -> Path:
    """Screenshot of ``html_path`` (a local file) at ``size`` pixels, with the 3D view showing
    ``photo``; raises RuntimeError when it fails or the page wrote to the console."""
    browser = find_chromium()
    if browser is None:
        raise RuntimeError(
            "No Chromium found: install it (Debian: apt-get "
            "install chromium) to check the page renders."
        )
    html_path, out_png = Path(html_path).resolve(), Path(out_png).resolve()
    if not html_path.is_file():
        raise RuntimeError(
            f"No page at {html_path}: run `python -m colmap_guided reconstruct` first."
        )
    out_png.parent.mkdir(parents=True, exist_ok=True)
    out_png.unlink(missing_ok=True)
    with tempfile.TemporaryDirectory(prefix="chromium-profile-") as profile:
        cmd = [
            browser,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
            "--enable-logging=stderr",
            "--v=0",
            f"--user-data-dir={profile}",
            f"--screenshot={out_png}",
            f"--window-size={size[0]},{size[1]}",
            html_path.as_uri() + (f"#photo={quote(photo, safe='')}" if photo else ""),
        ]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if not out_png.is_file() or out_png.stat().st_size == 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise RuntimeError(
            f"Chromium wrote no screenshot (exit {proc.returncode}): {' | '.join(tail)}"
        )
    console = CONSOLE.findall(proc.stderr or "")
    if console:
        raise RuntimeError(
            f"{html_path.name} wrote to the browser's console: {' | '.join(console)}"
        )
    return out_png


def view_pixels(png: Path) -> int | None:
    """Pixels of the screenshot's 3D view that are not its background (points, frusta, labels);
    None where the screenshot shows no 3D view."""
    import numpy as np
    from PIL import Image

    shot = np.asarray(Image.open(png).convert("RGB")).astype(int)
    background = np.abs(shot - np.array(VIEW_BACKGROUND)).sum(axis=2) < 6
    if background.sum() < 50_000:  # no canvas of the view's size on screen
        return None
    rows, cols = np.nonzero(background)
    view = shot[rows.min() : rows.max() + 1, cols.min() : cols.max() + 1]
    return int((np.abs(view - np.array(VIEW_BACKGROUND)).sum(axis=2) > 60).sum())


def make_demo(scene_dir: Path) -> Path:
    """The demo scene with eras and one photo of another building, reconstructed; returns its
    report.html."""
    import json

    import numpy as np
    from PIL import Image

    import colmap_guided  # noqa: F401 - before pycolmap (see colmap_guided/__init__.py)
    from colmap_guided.reconstruct import reconstruct
    from colmap_guided.synthetic import render_scene

    scene_dir = Path(scene_dir)
    info = render_scene(scene_dir, num_images=12, width=1024, height=768)
    eras = {name: "historical" if i % 3 == 1 else "modern" for i, name in enumerate(info.names)}
    for name, era in eras.items():
        if era == "historical":  # a sepia print: luminance mapped between dark brown and cream
            grey = (
                np.asarray(Image.open(info.image_dir / name).convert("L"), np.float32)[:, :, None]
                / 255
            )
            toned = (1 - grey) * np.array([40, 28, 18]) + grey * np.array([238, 222, 190])
            Image.fromarray(toned.astype(np.uint8)).save(info.image_dir / name, quality=90)
    other = render_scene(
        scene_dir.with_name(scene_dir.name + "_other"), num_images=2, width=1024, height=768, seed=7
    )
    (info.image_dir / "other_building.jpg").write_bytes(
        (other.image_dir / other.names[0]).read_bytes()
    )
    eras["other_building.jpg"] = "historical"
    (scene_dir / "manifest.json").write_text(
        json.dumps({"images": [{"name": n, "era": e} for n, e in eras.items()]}, indent=1)
    )
    return Path(reconstruct(scene_dir, overwrite=True)["html_report_path"])


def small_png(path: Path, max_bytes: int = 300_000) -> Path:
    """Re-save a screenshot with fewer colours until it is under ``max_bytes`` (for the README)."""
    from PIL import Image

    image = Image.open(path).convert("RGB")
    for colors in (256, 128, 64):
        if path.stat().st_size <= max_bytes:
            break
        image.quantize(colors, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(
            path, optimize=True
        )
    return path


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("html", type=Path, nargs="?", help="a report.html (not with --demo)")
    parser.add_argument(
        "--demo",
        type=Path,
        default=None,
        help="make the demo scene in this folder, reconstruct it and take its screenshot",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="PNG path (default: next to the page, report_screenshot.png)",
    )
    parser.add_argument("--size", default="1400,1000", help="window width,height in pixels")
    parser.add_argument(
        "--photo",
        default=None,
        help="show this photo in the 3D view (the page opened as report.html#photo=NAME)",
    )
    args = parser.parse_args(argv)
    if (args.html is None) == (args.demo is None):
        parser.error("pass a report.html or --demo DIR")
    width, height = (int(v) for v in args.size.split(","))
    try:
        html = make_demo(args.demo) if args.demo else args.html
        out = args.out or Path(html).with_name(Path(html).stem + "_screenshot.png")
        shot = screenshot(html, out, (width, height), photo=args.photo)
        if view_pixels(shot) == 0:
            raise RuntimeError(f"the 3D view of {html} shows nothing (screenshot: {shot})")
        print(small_png(shot))
    except (RuntimeError, subprocess.TimeoutExpired) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
