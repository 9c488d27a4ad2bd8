"""The frozen-backbone feature cache of the training views (HDF5, rebuilt when missing; it lives in
~/.cache/colmap_guided or $COLMAP_GUIDED_CACHE, never in the repository)."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np


class FeatureCache:
    """HDF5 file of frozen-backbone features, one float16 (C, gh, gw) dataset per view key.

    ``put_many`` opens, writes and closes the file for each chunk, so that a run killed while
    computing loses at most the current chunk; everything read is kept in memory (a few hundred MB
    for all training views at 400 px).
    """

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._memory: dict[str, np.ndarray] = {}
        self._keys: set[str] | None = None

    def keys(self) -> set[str]:
        if self._keys is None:
            self._keys = set()
            if self.path.exists():
                with h5py.File(self.path, "r") as f:
                    f.visit(
                        lambda name: (
                            self._keys.add(name) if isinstance(f[name], h5py.Dataset) else None
                        )
                    )
        return self._keys

    def __contains__(self, key: str) -> bool:
        return key in self._memory or key in self.keys()

    def put_many(self, items: dict[str, np.ndarray]) -> None:
        with h5py.File(self.path, "a") as f:
            for key, features in items.items():
                if key in f:
                    del f[key]
                f.create_dataset(key, data=features.astype(np.float16))
                self._memory[key] = features.astype(np.float16)
                self.keys().add(key)

    def get(self, key: str) -> np.ndarray:
        if key not in self._memory:
            with h5py.File(self.path, "r") as f:
                self._memory[key] = f[key][()]
        return self._memory[key]

    def load_all(self, keys) -> None:
        """Read many entries in one opening of the file."""
        missing = [k for k in keys if k not in self._memory]
        if missing:
            with h5py.File(self.path, "r") as f:
                for k in missing:
                    self._memory[k] = f[k][()]
