"""Where the project finds data it does not ship (weights, photo sets: env vars, or ../shared beside
a source checkout) and keeps its caches."""

import os
from pathlib import Path

# the checkout; site-packages for an installed package
REPO_ROOT = Path(__file__).resolve().parent.parent


def shared_dir() -> Path:
    """$COLMAP_GUIDED_SHARED; else ../shared beside a source checkout (pyproject.toml in REPO_ROOT,
    an editable install too). An installed package looks nowhere else (beside site-packages is no
    project's folder): it gets the path ``$COLMAP_GUIDED_SHARED``, which does not exist and names
    what to set."""
    in_checkout = (REPO_ROOT / "pyproject.toml").is_file()
    default = REPO_ROOT.parent / "shared" if in_checkout else "$COLMAP_GUIDED_SHARED"
    return Path(os.environ.get("COLMAP_GUIDED_SHARED", default))


def shared_data_dir() -> Path:
    """Real photo sets (see ../shared/data/README.md). Override with COLMAP_GUIDED_DATA."""
    return Path(os.environ.get("COLMAP_GUIDED_DATA", shared_dir() / "data"))


def cache_dir(kind: str) -> Path:
    """Where the package keeps caches it can rebuild (never inside the installed package or the
    repository): $COLMAP_GUIDED_CACHE/<kind>, default ~/.cache/colmap_guided/<kind>
    (XDG_CACHE_HOME honoured)."""
    root = (
        os.environ.get("COLMAP_GUIDED_CACHE")
        or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "colmap_guided"
    )
    return Path(root) / kind


def package_files(distribution: str) -> dict[str, Path]:
    """{file name: path} of an installed distribution (its metadata: nothing imported); {} without
    it."""
    from importlib import metadata

    try:
        return {f.name: Path(f.locate()) for f in metadata.files(distribution) or []}
    except metadata.PackageNotFoundError:
        return {}


def load_file_module(name: str, path: Path):
    """The Python file ``path`` executed as module ``name`` (registered in sys.modules, once),
    without importing the package it ships in."""
    import importlib.util
    import sys

    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]
