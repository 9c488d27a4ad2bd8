"""What the scale benchmark measures besides time: the load average, RSS once a second, and the
verified pairs of a database."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path


def load() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


class RssSampler:
    """RSS of this process (and its children) once a second, in a thread."""

    def __init__(self, period: float = 1.0):
        import psutil

        self.proc, self.samples, self.stop = psutil.Process(), [], threading.Event()
        self.t0, self.period = time.time(), period
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def rss(self) -> int:
        total = self.proc.memory_info().rss
        for child in self.proc.children(recursive=True):
            try:
                total += child.memory_info().rss
            except Exception:  # noqa: BLE001 - a child that ended meanwhile
                pass
        return total

    def run(self):
        while not self.stop.is_set():
            self.samples.append((round(time.time() - self.t0, 1), self.rss() >> 20))
            self.stop.wait(self.period)

    def close(self) -> list:
        self.stop.set()
        self.thread.join()
        return self.samples


def verified_pairs(db: Path, min_inliers: int = 1) -> set[tuple[int, int]]:
    """(image_id_a, image_id_b) of the pairs of ``db`` with at least ``min_inliers`` inliers."""
    import pycolmap

    from colmap_guided import database as dbio

    with dbio.open_database(db) as d:
        return {
            pycolmap.pair_id_to_image_pair(pair_id)
            for pair_id, geometry in zip(*d.read_two_view_geometries())
            if len(geometry.inlier_matches) >= min_inliers
        }
