"""Where the project finds data it does not ship: ../shared beside the checkout, or env vars."""

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


def shared_dir() -> Path:
    return Path(os.environ.get("COLMAP_GUIDED_SHARED", REPO_ROOT.parent / "shared"))


def shared_data_dir() -> Path:
    """Real photo sets (see ../shared/data/README.md). Override with COLMAP_GUIDED_DATA."""
    return Path(os.environ.get("COLMAP_GUIDED_DATA", shared_dir() / "data"))


def cache_dir(kind: str) -> Path:
    """Where the package keeps caches it can rebuild (never inside the installed package or the
    repository): $COLMAP_GUIDED_CACHE/<kind>, default ~/.cache/colmap_guided/<kind> (XDG_CACHE_HOME honoured)."""
    root = os.environ.get("COLMAP_GUIDED_CACHE") or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "colmap_guided"
    return Path(root) / kind
