"""Where the project finds data it does not ship: ../shared beside the checkout, or env vars."""

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


def shared_dir() -> Path:
    return Path(os.environ.get("COLMAP_GUIDED_SHARED", REPO_ROOT.parent / "shared"))


def shared_data_dir() -> Path:
    """Real photo sets (see ../shared/data/README.md). Override with COLMAP_GUIDED_DATA."""
    return Path(os.environ.get("COLMAP_GUIDED_DATA", shared_dir() / "data"))
