"""Pairs files and workspace paths: what a user writes by hand must be read as meant."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from colmap_guided.pairs import exhaustive_pairs, read_pairs, write_pairs
from colmap_guided.reconstruct import resolve_paths


def test_exhaustive_pairs_are_all_unordered_pairs():
    pairs = exhaustive_pairs(["c.jpg", "a.jpg", "b.jpg"])
    assert pairs == [("a.jpg", "b.jpg"), ("a.jpg", "c.jpg"), ("b.jpg", "c.jpg")]


def test_pairs_file_with_spaces_duplicates_and_comments(tmp_path):
    names = ["old photo 1.jpg", "old photo 2.jpg", "sub/new.jpg"]
    path = tmp_path / "pairs.txt"
    path.write_text(
        "# my pairs\nold photo 1.jpg old photo 2.jpg\nold photo 2.jpg\told photo 1.jpg\n"
        "\nsub/new.jpg old photo 1.jpg\nsub/new.jpg sub/new.jpg\n",
        encoding="utf-8",
    )
    assert read_pairs(path, names) == [
        ("old photo 1.jpg", "old photo 2.jpg"),
        ("sub/new.jpg", "old photo 1.jpg"),
    ]
    out = tmp_path / "out.txt"
    write_pairs(out, read_pairs(path, names))
    assert read_pairs(out, names) == read_pairs(path, names)


def test_pairs_file_naming_an_unknown_image_is_refused(tmp_path):
    path = tmp_path / "pairs.txt"
    path.write_text("a.jpg z.jpg\n")
    with pytest.raises(ValueError, match=r"pairs.txt:1: image 'z.jpg' is not in"):
        read_pairs(path, ["a.jpg", "b.jpg"])


def test_workspace_is_never_inside_the_photo_folder(tmp_path):
    (tmp_path / "scene" / "images").mkdir(parents=True)
    image_path, output = resolve_paths(tmp_path / "scene", None, None)
    assert (
        image_path == (tmp_path / "scene" / "images").resolve()
        and output == (tmp_path / "scene" / "colmap_guided").resolve()
    )
    # A bare folder of photos: the workspace goes beside it, not into it.
    (tmp_path / "photos").mkdir()
    image_path, output = resolve_paths(tmp_path / "photos", None, None)
    assert output == (tmp_path / "photos_colmap_guided").resolve()
    with pytest.raises(ValueError, match="is inside .*whose files are only read"):
        resolve_paths(tmp_path / "photos", None, tmp_path / "photos" / "out")


def test_caches_live_outside_the_package_and_the_repository(monkeypatch, tmp_path):
    from colmap_guided import paths
    from recon_scripts.evaluation import two_view

    monkeypatch.delenv("COLMAP_GUIDED_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert (
        paths.cache_dir("train_features") == tmp_path / "xdg" / "colmap_guided" / "train_features"
    )
    monkeypatch.setenv("COLMAP_GUIDED_CACHE", str(tmp_path / "mine"))
    assert paths.cache_dir("evaluation") == tmp_path / "mine" / "evaluation"
    package = Path(paths.__file__).resolve().parent
    for root in (paths.REPO_ROOT, package):
        assert root not in two_view.DEFAULT_CACHE.resolve().parents


def test_an_installed_package_finds_shared_data_only_through_the_environment(tmp_path):
    """paths.py copied into a site-packages layout (no pyproject.toml above the package): the
    ../shared beside site-packages is not the project's; the variable is; a checkout keeps its
    ../shared."""
    from colmap_guided import paths

    site = tmp_path / "site-packages"
    (site / "colmap_guided").mkdir(parents=True)
    (site / "colmap_guided" / "__init__.py").write_text("")
    shutil.copy(paths.__file__, site / "colmap_guided" / "paths.py")
    (tmp_path / "shared" / "data").mkdir(parents=True)
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("COLMAP_GUIDED_SHARED", "COLMAP_GUIDED_DATA")
    }
    code = "from colmap_guided import paths\nprint(paths.shared_data_dir())"
    env["PYTHONPATH"] = str(site)  # the copy, before the checkout on the path

    def data_dir(**extra) -> Path:
        run = [sys.executable, "-c", code]
        out = subprocess.run(
            run, env={**env, **extra}, cwd=tmp_path, capture_output=True, text=True, check=True
        )
        return Path(out.stdout.strip())

    assert not (tmp_path / data_dir()).exists()
    assert data_dir(COLMAP_GUIDED_SHARED=str(tmp_path / "mine")) == tmp_path / "mine" / "data"
    (site / "pyproject.toml").write_text("")
    assert data_dir() == tmp_path / "shared" / "data"
