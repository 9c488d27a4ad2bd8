"""Shared fixtures: one rendered synthetic scene per test session (exact ground-truth cameras)."""

import os
from pathlib import Path

import pytest

from colmap_guided.paths import shared_data_dir


@pytest.fixture(scope="session")
def synthetic_scene(tmp_path_factory):
    from colmap_guided.synthetic import render_scene

    return render_scene(tmp_path_factory.mktemp("synthetic") / "scene", num_images=8, seed=0)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    root = shared_data_dir()
    if not root.is_dir():
        pytest.skip(f"real photo sets not found at {root} (set COLMAP_GUIDED_DATA)")
    return root


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tests that call the coarse network directly run it as match_database does on CPU (one torch
    thread, CoarseMatcher num_threads=1): faster on shared cores; restored for the other test
    modules."""
    from colmap_guided.matchers.base import scoped_torch_threads

    with scoped_torch_threads(1):
        yield


@pytest.fixture(scope="session")
def chromium():
    """The page tests' browser: skipped without one; CI installs it (.ci/run), so there a missing
    one fails."""
    from recon_scripts.evaluation.screenshot import find_chromium

    if find_chromium() is None:
        message = "Chromium is not installed (Debian: apt-get install chromium)"
        pytest.fail(message) if os.environ.get("CI") else pytest.skip(message)


@pytest.fixture(scope="session")
def two_buildings(synthetic_scene, tmp_path_factory):
    """One folder with the synthetic scene's 8 views and 6 of another building's 7 (named other_*),
    reconstructed with raw SIFT: two models. Returns (result, workspace, other building's scene)."""
    import shutil

    from colmap_guided.reconstruct import reconstruct
    from colmap_guided.synthetic import render_scene

    root = tmp_path_factory.mktemp("two_buildings")
    other = render_scene(root / "other", num_images=7, seed=7)
    images = root / "scene" / "images"
    shutil.copytree(synthetic_scene.image_dir, images)
    for name in other.names[:6]:
        shutil.copy(other.image_dir / name, images / f"other_{name}")
    result = reconstruct(images.parent, output=root / "out", matcher="raw")
    return result, root / "out", other
