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
    """RSS of this process or process ``pid`` (and its children) once a second, in a thread."""

    def __init__(self, period: float = 1.0, pid: int | None = None):
        import psutil

        self.proc, self.samples, self.stop = psutil.Process(pid), [], threading.Event()
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
        import psutil

        while not self.stop.is_set():
            try:
                self.samples.append((round(time.time() - self.t0, 1), self.rss() >> 20))
            except psutil.Error:  # the process ended
                return
            self.stop.wait(self.period)

    def close(self) -> list:
        self.stop.set()
        self.thread.join()
        return self.samples


def run_measured(cmd: list[str], env: dict, timeout: float, log: Path) -> dict:
    """``cmd`` in a fresh process (its output to ``log``), measured: its exit code (None: killed
    after ``timeout`` s), wall and CPU s, the peak RSS of its largest process (``ru_maxrss``, exact)
    and of its process tree (summed, sampled once a second), load before and after."""
    import subprocess

    result = {"load_before": load(), "start": time.strftime("%H:%M:%S", time.gmtime())}
    t0 = time.time()
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT)
    sampler = RssSampler(pid=proc.pid)
    timer = threading.Timer(timeout, proc.kill)
    timer.start()
    # wait4 rather than wait: the rusage of this one child (and what it waited for)
    _, status, usage = os.wait4(proc.pid, 0)
    timer.cancel()
    proc.returncode = os.waitstatus_to_exitcode(status)
    samples = sampler.close()
    killed = proc.returncode < 0 and time.time() - t0 >= timeout
    return {
        **result,
        "returncode": None if killed else proc.returncode,
        "wall": time.time() - t0,
        "cpu": usage.ru_utime + usage.ru_stime,
        "peak_rss_mb": usage.ru_maxrss >> 10,
        "peak_tree_rss_mb": max((mb for _, mb in samples), default=0),
        "load_after": load(),
    }


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
