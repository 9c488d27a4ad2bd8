"""Shared fixtures: one rendered synthetic scene per test session (exact ground-truth cameras)."""

from pathlib import Path

import pytest
import torch

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
    """As CoarseMatcher does on CPU (num_threads=1); restored for the other test modules."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
