"""Dependency floors: pyproject.toml's are versions the suite runs on; an older pycolmap is refused
on import."""

import re
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest

import colmap_guided

ROOT = Path(__file__).resolve().parents[1]


def test_the_installed_dependencies_meet_the_floors():
    tomllib = pytest.importorskip("tomllib")
    requirement = pytest.importorskip("packaging.requirements").Requirement
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = [
        requirement(r)
        for r in project["dependencies"] + sum(project["optional-dependencies"].values(), [])
    ]
    floors = {r.name: r for r in reqs if r.name != "colmap_guided"}
    assert str(floors["pycolmap"].specifier) == f">={colmap_guided.MIN_PYCOLMAP}"
    for name, req in floors.items():
        try:
            installed = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue  # an optional extra not installed here
        assert req.specifier.contains(installed, prereleases=True), (
            f"{name} {installed} is below {req}"
        )


def test_an_older_pycolmap_is_refused_on_import_in_one_line():
    code = (
        "from importlib import metadata; metadata.version = "
        "lambda name: '4.1.0'; import colmap_guided"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    last = run.stderr.strip().splitlines()[-1]
    assert run.returncode != 0
    assert re.fullmatch(
        r"ImportError: colmap_guided needs pycolmap >= 4\.2\.1, found 4\.1\.0: pip install .*", last
    )
