"""Matching throughput per executor: the same retrieval pairs matched by 1 and 2 threads, a private
Ray instance of 1 and 2 CPUs and two Ray nodes of one CPU each on this machine."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from recon_scripts.scale.measure import load

RAY_ENV = ("HOME", "RAY_TMPDIR", "RAY_worker_niceness")


def _ray_start(args: list[str], env: dict) -> subprocess.Popen:
    """``ray start ARGS --block`` in its own process group, its output discarded."""
    return subprocess.Popen(
        [str(Path(sys.executable).with_name("ray")), "start", *args, "--block"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        preexec_fn=os.setpgrp,
    )


def _ray_nodes(root: Path, port: int) -> tuple[str, list]:
    """A head node and a second node, one CPU each, on this machine (``ray start --block``, own
    process groups)."""
    env = {
        **os.environ,
        "HOME": str(root),
        "RAY_TMPDIR": str(root),
        "OMP_NUM_THREADS": "1",
        "RAY_worker_niceness": "0",
    }
    head = ["--head", "--num-cpus", "1", "--port", str(port), "--include-dashboard", "false"]
    procs = [_ray_start(head, env)]
    address = f"127.0.0.1:{port}"
    time.sleep(10)
    procs.append(_ray_start(["--address", address, "--num-cpus", "1"], env))
    return address, procs


def _stop_nodes(procs: list, root: Path) -> None:
    """Stop what ``_ray_nodes`` started: its two ``ray start --block`` processes (which stop their
    own daemons), then any process still running from this benchmark's Ray folder (by pid)."""
    import psutil

    for p in reversed(procs):
        try:
            os.killpg(p.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    for p in procs:
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
    time.sleep(2)
    for proc in psutil.process_iter(["pid", "cmdline"]):
        if any(str(root) in part for part in proc.info["cmdline"] or []):
            print("  stopping leftover Ray process", proc.info["pid"], flush=True)
            proc.kill()


def _connect(address: str) -> None:
    """``ray.init`` on the nodes at ``address`` once both have joined (30 tries, 2 s apart)."""
    import ray

    for _ in range(30):
        try:
            ray.init(address=address, log_to_driver=False, configure_logging=False)
        except Exception as err:  # noqa: BLE001 - the second node may still be joining
            print("  waiting for the Ray nodes:", err, flush=True)
            time.sleep(2)
            continue
        if ray.cluster_resources().get("CPU", 0) >= 2:
            break
        ray.shutdown()
        time.sleep(2)
    nodes = [
        (nd["NodeManagerAddress"], nd["Resources"].get("CPU")) for nd in ray.nodes() if nd["Alive"]
    ]
    print("  nodes:", nodes, flush=True)


def _first_pairs(work: Path, num_pairs: int) -> Path:
    """WORK/pairs.txt: the first ``num_pairs`` (by name) of the retrieval pairs that the match
    stage selected for the set."""
    import pycolmap

    from colmap_guided import database as dbio
    from colmap_guided.pairs import write_pairs

    pairs_file = work / "pairs.txt"
    if not pairs_file.exists():
        with dbio.open_database(work.parent / "retrieval" / "database.db") as db:
            names = {im.image_id: im.name for im in db.read_all_images()}
            pairs = sorted(
                tuple(sorted((names[a], names[b])))
                for a, b in map(pycolmap.pair_id_to_image_pair, db.read_all_matches()[0])
            )
        write_pairs(pairs_file, pairs[:num_pairs])
    return pairs_file


def _match_once(
    work: Path, images: Path, pairs_file: Path, label: str, executor: str, workers: int
) -> tuple[dict, dict]:
    """One configuration on a fresh copy of the set's database: its row, and its matches
    {(name_a, name_b): matches}."""
    from colmap_guided import database as dbio
    from colmap_guided.match import match_database
    from colmap_guided.matchers import get_matcher
    from colmap_guided.pairs import read_pairs

    db = work / f"{label}.db"
    db.unlink(missing_ok=True)
    shutil.copy(work.parent / "database.db", db)
    matcher = get_matcher("guided", {"workers": workers})
    before = load()
    stats = match_database(db, images, str(pairs_file), matcher, executor=executor)
    row = {
        "config": label,
        "executor": executor,
        "workers": stats["executor"]["workers"],
        "pairs": stats["num_pairs"],
        "match_time": stats["match_time"],
        "pairs_per_s": stats["num_pairs"] / stats["match_time"],
        "load_before": before,
        "load_after": load(),
    }
    with dbio.open_database(db) as d:
        ims = dbio.images_by_name(d)
        matches = {
            (a, b): dbio.read_pair_matches(d, ims[a].image_id, ims[b].image_id).tolist()
            for a, b in read_pairs(pairs_file, list(ims))
        }
    db.unlink()
    return row, matches


def _round(r: int, one, root: Path, port: int, procs: list) -> None:
    """Round ``r`` of every configuration, each run by ``one(label, executor, workers)``; the Ray
    nodes it starts are in ``procs`` until it has stopped them."""
    import ray

    one(f"local_1_r{r}", "local", 1)
    one(f"local_2_r{r}", "local", 2)
    for cpus in (1, 2):
        t = time.time()
        ray.init(
            address="local",
            num_cpus=cpus,
            include_dashboard=False,
            log_to_driver=False,
            configure_logging=False,
        )
        print(f"  private Ray ({cpus} CPU) up in {time.time() - t:.1f} s", flush=True)
        one(f"ray_private_{cpus}_r{r}", "ray", 1)
        ray.shutdown()
    address, nodes = _ray_nodes(root, port)
    procs += nodes
    _connect(address)
    one(f"ray_2nodes_r{r}", "ray", 1)
    ray.shutdown()
    _stop_nodes(procs, root)
    procs.clear()


def match_executors(work: Path, images: Path, num_pairs: int, rounds: int, port: int) -> list:
    """A row per configuration and round (pairs/s, loads, same matches as the first local run) of
    the first ``num_pairs`` retrieval pairs of the set, matched anew by each."""
    import ray

    pairs_file = _first_pairs(work, num_pairs)
    root = Path(tempfile.mkdtemp(prefix="rayb", dir="/tmp"))
    saved = {k: os.environ.get(k) for k in RAY_ENV}
    # one session and niceness for all: Ray's default nice +15 starved workers 4x beside other jobs
    os.environ.update(HOME=str(root), RAY_TMPDIR=str(root), RAY_worker_niceness="0")
    rows, matches, procs = [], {}, []

    def one(label: str, executor: str, workers: int):
        row, matches[label] = _match_once(work, images, pairs_file, label, executor, workers)
        rows.append(row)
        row["same_matches_as_local_1"] = matches[label] == matches[rows[0]["config"]]
        print(row, flush=True)

    try:
        for r in range(rounds):
            _round(r, one, root, port, procs)
    finally:
        if ray.is_initialized():
            ray.shutdown()
        if procs:
            _stop_nodes(procs, root)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        shutil.rmtree(root, ignore_errors=True)
    return rows
