"""Render OUTPUT/report.html in headless Chromium and save a screenshot PNG (checks the page really renders).

    python recon_scripts/render_report_screenshot.py OUTPUT/report.html [--out shot.png] [--size 1200,1600]

Chromium comes from Debian (`apt-get install chromium`); the page is opened from the file system with the
network off, so the screenshot also proves the page needs nothing from outside (images are embedded).
Prints the screenshot path; exit status 1 with a one-line message when no browser is installed.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_chromium() -> str | None:
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


def screenshot(html_path: Path, out_png: Path, size: tuple[int, int] = (1200, 1600), timeout: float = 120.0) -> Path:
    """Screenshot of ``html_path`` (a local file) at ``size`` pixels; raises RuntimeError when it fails."""
    browser = find_chromium()
    if browser is None:
        raise RuntimeError("No Chromium found: install it (Debian: apt-get install chromium) to check the page renders.")
    html_path, out_png = Path(html_path).resolve(), Path(out_png).resolve()
    if not html_path.is_file():
        raise RuntimeError(f"No page at {html_path}: run `python -m colmap_guided reconstruct` first.")
    out_png.parent.mkdir(parents=True, exist_ok=True)
    out_png.unlink(missing_ok=True)
    with tempfile.TemporaryDirectory(prefix="chromium-profile-") as profile:
        cmd = [
            browser,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
            f"--user-data-dir={profile}",
            f"--screenshot={out_png}",
            f"--window-size={size[0]},{size[1]}",
            html_path.as_uri(),
        ]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if not out_png.is_file() or out_png.stat().st_size == 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise RuntimeError(f"Chromium wrote no screenshot (exit {proc.returncode}): {' | '.join(tail)}")
    return out_png


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("html", type=Path)
    parser.add_argument("--out", type=Path, default=None, help="PNG path (default: next to the page, report_screenshot.png)")
    parser.add_argument("--size", default="1200,1600", help="window width,height in pixels")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.split(","))
    out = args.out or Path(args.html).with_name(Path(args.html).stem + "_screenshot.png")
    try:
        print(screenshot(args.html, out, (width, height)))
    except (RuntimeError, subprocess.TimeoutExpired) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
