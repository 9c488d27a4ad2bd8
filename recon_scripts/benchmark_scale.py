"""Scale: time per stage, pairs, registered images and peak memory vs N photos.

    python -m recon_scripts scale sets=[]    # the photo pool only (once, ~5 min)
    python -m recon_scripts scale sets=1000 pairs=retrieval
    python -m recon_scripts scale sets="50 200" pairs="retrieval exhaustive"
    python -m recon_scripts scale sets="50 200 1000" mappers="global hierarchical incremental"
    python -m recon_scripts scale_executors sets=200 num_pairs=160

Photos: the 437 photos of the 20 training scenes of ../shared/data/train pooled (long side <=
1024 px; symlinked, never copied) and 563 photos of 24 landmarks rendered by
``colmap_guided.synthetic`` (1024x768, seeds 1000-1023, 24 views each on an arc around the landmark,
the last landmark 11): no photo twice. The set of N photos is the first N of the scenes in a fixed
order (training and rendered scenes alternating, whole scenes, the last one cut), so a smaller set
is a prefix of the larger ones.

Every stage (extract, match = select + match, verify, map) runs in a fresh process under ``nice``,
with one torch/BLAS thread per worker: its wall and CPU time, peak RSS (``ru_maxrss``), load average
before and after and, for the match stage, the RSS every second and the most images held at once are
written to WORK/n<N>/<pairs>/<stage>.json. A stage with its JSON is skipped: a killed benchmark
resumes, and a run with other mappers maps the databases already matched. Everything is under WORK
(default outputs/benchmark_scale, git-ignored); nothing is written next to the photos. The summary:
Markdown tables (printed, WORK/report.md) and WORK/scale.png.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from colmap_guided.paths import shared_data_dir
from recon_scripts.bench import Benchmark

SYNTHETIC = {"scenes": 24, "views": 24, "width": 1024, "height": 768, "seed": 1000}
POOL_SIZE = 1000


def load() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


# -- the photo pool -------------------------------------------------------------------------------


def _render(args):
    from colmap_guided.synthetic import render_scene

    out, views, seed = args
    if not (Path(out) / "ground_truth" / "images.txt").exists():
        render_scene(out, views, SYNTHETIC["width"], SYNTHETIC["height"], seed=seed)
    return out


def make_pool(out: Path, workers: int = 2) -> list[dict]:
    """Scenes in pool order: [{'name', 'kind', 'files': [abs paths]}]; rendered scenes under
    OUT/synthetic."""
    if (out / "pool.json").exists():
        return json.loads((out / "pool.json").read_text())
    train = shared_data_dir() / "train"
    from colmap_guided.features import list_images

    real = [
        {
            "name": f"t_{p.name}",
            "kind": "train",
            "files": [str(p / "images" / n) for n in list_images(p / "images")],
        }
        for p in sorted(train.iterdir())
        if (p / "images").is_dir()
    ]
    left = POOL_SIZE - sum(len(s["files"]) for s in real)
    jobs = []
    for i in range(SYNTHETIC["scenes"]):
        views = min(SYNTHETIC["views"], left)
        if views < 2:
            break
        jobs.append(
            (str(out / "synthetic" / f"s_{SYNTHETIC['seed'] + i}"), views, SYNTHETIC["seed"] + i)
        )
        left -= views
    from multiprocessing import Pool

    with Pool(workers) as pool:
        for done in pool.imap(_render, jobs):
            print("rendered", done, flush=True)
    synth = [
        {
            "name": Path(o).name,
            "kind": "synthetic",
            "files": [str(Path(o) / "images" / f"view_{v:03d}.jpg") for v in range(n)],
        }
        for o, n, _ in jobs
    ]
    random.Random(0).shuffle(real)
    random.Random(1).shuffle(synth)
    scenes = []
    for i in range(max(len(real), len(synth))):
        scenes += [
            s
            for s in (real[i] if i < len(real) else None, synth[i] if i < len(synth) else None)
            if s
        ]
    (out / "pool.json").write_text(json.dumps(scenes, indent=1))
    return scenes


def photo_set(out: Path, n: int) -> Path:
    """OUT/n<N>/images: symlinks <scene>/<file> to the first ``n`` photos of the pool."""
    images = out / f"n{n}" / "images"
    if images.is_dir():
        return images
    tmp = images.with_name("images.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    left = n
    for scene in json.loads((out / "pool.json").read_text()):
        for f in scene["files"][:left]:
            (tmp / scene["name"]).mkdir(parents=True, exist_ok=True)
            (tmp / scene["name"] / Path(f).name).symlink_to(f)
        left -= min(left, len(scene["files"]))
        if not left:
            break
    if left:
        raise SystemExit(f"The pool holds fewer than {n} photos")
    tmp.rename(images)
    return images


# -- one stage in its own process -----------------------------------------------------------------


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


def stage_main(args) -> None:
    """Runs one stage (this process) and writes its JSON."""
    from colmap_guided import database as dbio
    from colmap_guided import features, mapping, report
    from colmap_guided.log import set_verbosity
    from colmap_guided.match import match_database

    set_verbosity(quiet=True)
    run_dir, images = Path(args.run_dir), Path(args.images)
    db = run_dir / "database.db"
    result = {
        "stage": args.stage,
        "load_before": load(),
        "start": time.strftime("%H:%M:%S", time.gmtime()),
    }
    sampler = RssSampler()
    result["rss_start_mb"] = sampler.rss() >> 20
    t0, c0 = time.time(), time.process_time()
    if args.stage == "extract":
        stats = features.extract_features(db, images, features.list_images(images))
        result["skipped"] = len(stats["skipped"])
    elif args.stage == "match":
        stats = match_database(db, images, args.pairs, "guided", num_neighbors=args.k)
        result.update(
            num_pairs=stats["num_pairs"],
            select_time=stats["pairs"]["time"],
            match_time=stats["match_time"],
            verify_time=stats["verify_time"],
            num_verified_pairs=stats["num_verified_pairs"],
            memory=stats.get("memory"),
            executor=stats.get("executor"),
        )
    elif args.stage == "map":
        models = mapping.run_mapping(
            db, images, run_dir / f"sparse_{args.mapper}", {"mapper": args.mapper}
        )
        names = features.list_images(images)
        registered = {rec.images[i].name for rec in models.values() for i in rec.reg_image_ids()}
        result.update(
            mapper=args.mapper,
            num_models=len(models),
            largest=report.model_statistics(models, names)["num_registered"],
            registered=len(registered),
            registered_train=sum(n.startswith("t_") for n in registered),
            registered_synthetic=sum(n.startswith("s_") for n in registered),
            num_images=len(names),
            images_in_verified_pairs=_in_verified_pairs(db),
        )
    result["wall"] = time.time() - t0
    ru_self, ru_kids = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    result["cpu"] = time.process_time() - c0 + ru_kids.ru_utime + ru_kids.ru_stime
    result["peak_rss_mb"] = ru_self.ru_maxrss >> 10
    result["rss_samples"] = sampler.close()
    result["load_after"] = load()
    out = Path(args.result)
    out.with_suffix(".partial").write_text(json.dumps(result, indent=1))
    out.with_suffix(".partial").rename(out)
    del dbio


def _verified_pairs(db: Path) -> set:
    import pycolmap

    from colmap_guided import database as dbio

    with dbio.open_database(db) as d:
        return {
            pycolmap.pair_id_to_image_pair(pair_id)
            for pair_id, geometry in zip(*d.read_two_view_geometries())
            if len(geometry.inlier_matches) > 0
        }


def _in_verified_pairs(db: Path) -> int:
    import pycolmap

    from colmap_guided import database as dbio

    with dbio.open_database(db) as d:
        ids = set()
        for pair_id, geometry in zip(*d.read_two_view_geometries()):
            if len(geometry.inlier_matches) >= 15:
                ids.update(pycolmap.pair_id_to_image_pair(pair_id))
        return len(ids)


def run_stage(
    stage: str, run_dir: Path, images: Path, result: Path, timeout: float, **extra
) -> dict | None:
    if result.exists():
        return json.loads(result.read_text())
    cmd = [
        "nice",
        "-n",
        "5",
        sys.executable,
        "-m",
        __name__ if __name__ != "__main__" else "recon_scripts.benchmark_scale",
        "_stage",
        stage,
        "--run_dir",
        str(run_dir),
        "--images",
        str(images),
        "--result",
        str(result),
    ] + [a for k, v in extra.items() for a in (f"--{k}", str(v))]
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "MKL_NUM_THREADS": "1",
        "OPENBLAS_NUM_THREADS": "1",
        # the stage imports recon_scripts from this checkout, wherever it was started
        "PYTHONPATH": os.pathsep.join(
            filter(None, [str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH")])
        ),
    }
    print(
        f"[{time.strftime('%H:%M:%S', time.gmtime())}] "
        f"{stage} {run_dir.name} {extra} (load {load()})",
        flush=True,
    )
    try:
        proc = subprocess.run(cmd, env=env, timeout=timeout)
    except subprocess.TimeoutExpired:
        print(f"  timed out after {timeout:.0f} s", flush=True)
        return None
    if proc.returncode != 0:
        print(f"  failed (exit {proc.returncode})", flush=True)
        return None
    r = json.loads(result.read_text())
    print(
        f"  {r['wall']:.0f} s wall, {r['cpu']:.0f} s CPU, peak RSS "
        f"{r['peak_rss_mb']} MB, load {r['load_before']} -> {r['load_after']}",
        flush=True,
    )
    return r


class ScaleBenchmark(Benchmark):
    name = "scale"
    default_conf = {
        "sets": [50, 200, 1000],  # N photos, each set a prefix of the next
        "work": "outputs/benchmark_scale",
        "pairs": ["retrieval"],  # and/or exhaustive
        "k": 10,  # retrieval: neighbours per photo
        "mappers": ["global"],
        "timeout": 3 * 3600,  # seconds per extract / match stage
        "map_timeout": 1800,  # seconds per mapping
    }
    resume = True

    def run(self) -> dict:
        self.out = Path(self.conf["work"]).resolve()
        self.out.mkdir(parents=True, exist_ok=True)
        self.conf["work"] = str(self.out)
        make_pool(self.out)
        return super().run()

    def folder(self, n) -> str:
        return f"n{n}"

    def images(self, n, work):
        return photo_set(self.out, n)

    def configs(self):
        c = self.conf
        return {mode: {"mode": mode, "k": c["k"], "mappers": c["mappers"]} for mode in c["pairs"]}

    def prepare(self, n, images, work):
        return {
            "extract": run_stage(
                "extract", work, images, work / "extract.json", self.conf["timeout"]
            )
        }

    def run_config(self, n, images, prepared, label, config, out):
        if prepared["extract"] is None:
            return {"failed": "extract"}
        if not (out / "database.db").exists():
            shutil.copy(out.parent / "database.db", out / "database.partial.db")
            (out / "database.partial.db").rename(out / "database.db")
        timeout, k = self.conf["timeout"], config["k"]
        if run_stage("match", out, images, out / "match.json", timeout, pairs=label, k=k) is None:
            return {"failed": "match"}
        for mapper in config["mappers"]:
            result = out / f"map_{mapper}.json"
            run_stage("map", out, images, result, self.conf["map_timeout"], mapper=mapper)
        return {
            "stages": sorted(p.stem for p in out.glob("*.json") if p.stem not in ("conf", "result"))
        }

    def progress(self, results, n, label):
        return f"N={n} {label}: {results[n][label]}"

    def summarize(self, results):
        return report(self.out, self.conf["sets"], self.conf["k"])


# -- executors: throughput per worker -------------------------------------------------------------


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
    ray_bin = str(Path(sys.executable).with_name("ray"))
    procs = [
        subprocess.Popen(
            [
                ray_bin,
                "start",
                "--head",
                "--num-cpus",
                "1",
                "--port",
                str(port),
                "--include-dashboard",
                "false",
                "--block",
            ],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=os.setpgrp,
        )
    ]
    address = f"127.0.0.1:{port}"
    time.sleep(10)
    procs.append(
        subprocess.Popen(
            [ray_bin, "start", "--address", address, "--num-cpus", "1", "--block"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=os.setpgrp,
        )
    )
    return address, procs


def _stop_nodes(procs: list, root: Path) -> None:
    """Stop what ``_ray_nodes`` started: its two ``ray start --block`` processes (which stop their
    own daemons), then any process still running from this benchmark's Ray folder (by pid)."""
    import signal

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


class ScaleExecutors(ScaleBenchmark):
    """Matching throughput per worker: threads (1, 2), a private Ray (1, 2 CPUs), 2 Ray nodes.

    The same retrieval pairs of a set that `scale` matched, matched from scratch by each
    configuration: pairs/s and the ratio per added worker, and whether the matches are the same.
    """

    name = "scale_executors"
    default_conf = {
        "sets": [200],  # N of a set that `scale` matched with retrieval pairs
        "work": "outputs/benchmark_scale",
        "num_pairs": 160,  # pairs matched per configuration
        "rounds": 1,
        "port": 6391,
    }
    resume = False

    def configs(self):
        c = self.conf
        return {"executors": {k: c[k] for k in ("num_pairs", "rounds", "port")}}

    def prepare(self, n, images, work):
        return {}

    def progress(self, results, n, label):
        return f"N={n}: {len(results[n][label]['rows'])} configurations"

    def summarize(self, results):
        return "\n".join(
            executors_table([r for res in results.values() for r in res["executors"]["rows"]])
        )

    def run_config(self, n, images, prepared, label, config, work):
        return {"rows": match_executors(work, images, **config)}


def match_executors(work: Path, images: Path, num_pairs: int, rounds: int, port: int) -> list:
    import ray

    from colmap_guided import database as dbio
    from colmap_guided.match import match_database
    from colmap_guided.matchers import get_matcher
    from colmap_guided.pairs import read_pairs, write_pairs

    base = work.parent / "database.db"
    pairs_file = work / "pairs.txt"
    # the first retrieval pairs of the N-photo set (the match stage's selection)
    if not pairs_file.exists():
        src = work.parent / "retrieval" / "database.db"
        import pycolmap

        with dbio.open_database(src) as db:
            names = {im.image_id: im.name for im in db.read_all_images()}
            pairs = sorted(
                tuple(sorted((names[a], names[b])))
                for a, b in map(pycolmap.pair_id_to_image_pair, db.read_all_matches()[0])
            )
        write_pairs(pairs_file, pairs[:num_pairs])
    root = Path(tempfile.mkdtemp(prefix="rayb", dir="/tmp"))
    saved = {k: os.environ.get(k) for k in ("HOME", "RAY_TMPDIR", "RAY_worker_niceness")}
    # Same session (one scheduler autogroup) and the same niceness for every configuration: Ray's
    # default nice +15 for workers starved them 4x beside the other processes of this shared
    # machine.
    os.environ.update(HOME=str(root), RAY_TMPDIR=str(root), RAY_worker_niceness="0")
    rows, dumps = [], {}

    def one(label: str, executor: str, workers: int):
        db = work / f"{label}.db"
        db.unlink(missing_ok=True)
        shutil.copy(base, db)
        matcher = get_matcher("guided", {"workers": workers})
        before = load()
        stats = match_database(db, images, str(pairs_file), matcher, executor=executor)
        w = stats["executor"]["workers"]
        rows.append(
            {
                "config": label,
                "executor": executor,
                "workers": w,
                "pairs": stats["num_pairs"],
                "match_time": stats["match_time"],
                "pairs_per_s": stats["num_pairs"] / stats["match_time"],
                "load_before": before,
                "load_after": load(),
            }
        )
        with dbio.open_database(db) as d:
            ims = dbio.images_by_name(d)
            dumps[label] = {
                (a, b): dbio.read_pair_matches(d, ims[a].image_id, ims[b].image_id).tolist()
                for a, b in read_pairs(pairs_file, list(ims))
            }
        rows[-1]["same_matches_as_local_1"] = dumps[label] == dumps[rows[0]["config"]]
        print(rows[-1], flush=True)
        db.unlink()

    procs = []
    try:
        for r in range(rounds):
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
            address, procs = _ray_nodes(root, port)
            for attempt in range(30):
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
            print(
                "  nodes:",
                [
                    (nd["NodeManagerAddress"], nd["Resources"].get("CPU"))
                    for nd in ray.nodes()
                    if nd["Alive"]
                ],
                flush=True,
            )
            one(f"ray_2nodes_r{r}", "ray", 1)
            ray.shutdown()
            _stop_nodes(procs, root)
            procs = []
    finally:
        if ray.is_initialized():
            ray.shutdown()
        if procs:
            _stop_nodes(procs, root)
        for k, v in saved.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)
        shutil.rmtree(root, ignore_errors=True)
    return rows


# -- report ---------------------------------------------------------------------------------------


def _json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.exists() else None


def report(out: Path, ns: list[int], k: int) -> str:
    """Markdown tables (returned and OUT/report.md) and OUT/scale.png from the stage JSONs."""
    pool = json.loads((out / "pool.json").read_text())
    lines = []
    p = lines.append

    def composition(n: int) -> str:
        train = synth = 0
        for scene in pool:
            take = min(n - train - synth, len(scene["files"]))
            if scene["kind"] == "train":
                train += take
            else:
                synth += take
        return f"{train} train + {synth} rendered"

    p(
        "| N (photos) | pairs | pairs matched (of exhaustive) | "
        "verified (exhaustive's kept) | extract s | select s | match s | verify s | "
        "map (global) s | total s (CPU s) | peak RSS: run / match stage (start) MB | "
        "images held max / reads | registered (train + rendered) | models | load 1-min |"
    )
    p("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    per_pair, rows = {}, {}
    for n in ns:
        ex = _json(out / f"n{n}" / "extract.json")
        for mode in ("retrieval", "exhaustive"):
            m = _json(out / f"n{n}" / mode / "match.json")
            g = _json(out / f"n{n}" / mode / "map_global.json")
            if ex is None or m is None:
                continue
            stages = [r for r in (ex, m, g) if r]
            total = sum(r["wall"] for r in stages)
            cpu = sum(r["cpu"] for r in stages)
            pure_match = m["match_time"] + m["verify_time"]
            if mode == "exhaustive":
                per_pair[n] = (pure_match / m["num_pairs"], m["cpu"] / m["num_pairs"])
            rows[(n, mode)] = {
                "extract": ex["wall"],
                "select": m["select_time"],
                "match": m["match_time"],
                "verify": m["verify_time"],
                "map": g["wall"] if g else None,
                "total": total,
                "cpu": cpu,
                "rss_match": m["peak_rss_mb"],
                "rss_run": max(r["peak_rss_mb"] for r in stages),
                "held": (m.get("memory") or {}).get("images_held_max"),
            }
            mem = m.get("memory") or {}
            kept = "–"
            if (out / f"n{n}" / "exhaustive" / "match.json").exists():
                truth = _verified_pairs(out / f"n{n}" / "exhaustive" / "database.db")
                kept = (
                    f"{len(_verified_pairs(out / f'n{n}' / mode / 'database.db') & truth)}"
                    f"/{len(truth)}"
                )
            reg = (
                f"{g['registered']}/{n} ({g['registered_train']} + {g['registered_synthetic']})"
                if g
                else "–"
            )
            loads = [
                float(r[k].split("/")[0]) for r in stages for k in ("load_before", "load_after")
            ]
            p(
                f"| {n} ({composition(n)}) | {mode}"
                + (f" k={k}" if mode == "retrieval" else "")
                + f" | {m['num_pairs']} ({m['num_pairs'] / (n * (n - 1) / 2):.1%}) "
                f"| {m['num_verified_pairs']} ({kept}) | {ex['wall']:.0f} | {m['select_time']:.0f} "
                f"| {m['match_time']:.0f} | {m['verify_time']:.0f} | {g['wall']:.0f} | "
                if g
                else "– | "
            )
            lines[-1] += (
                f"{total:.0f} ({cpu:.0f}) | {max(r['peak_rss_mb'] for r in stages)} / "
                f"{m['peak_rss_mb']} ({m['rss_start_mb']}) | "
                f"{mem.get('images_held_max', '–')} / {mem.get('image_reads', '–')} | {reg} | "
                f"{g['num_models'] if g else '–'} | {min(loads):.1f}–{max(loads):.1f} |"
            )
    if per_pair:
        n0 = min(per_pair)
        wall_pp, cpu_pp = per_pair[n0]
        p("")
        p(
            f"Exhaustive matching projected from its measured time per pair at N={n0} "
            f"({wall_pp:.2f} s wall match + verify per pair, {cpu_pp:.2f} s CPU with "
            "selection): a projection, not a measurement:"
        )
        p("")
        p(
            "| N | exhaustive pairs | projected match + verify h (wall, this load) | "
            "projected CPU h |"
        )
        p("|---|---|---|---|")
        for n in ns:
            pairs = n * (n - 1) // 2
            p(f"| {n} | {pairs} | {pairs * wall_pp / 3600:.1f} | {pairs * cpu_pp / 3600:.1f} |")
    mapping = []
    for n in ns:
        for mode in ("retrieval", "exhaustive"):
            for mapper in ("incremental", "global", "hierarchical"):
                r = _json(out / f"n{n}" / mode / f"map_{mapper}.json")
                if r:
                    mapping.append((n, mode, r))
    if mapping:
        p("")
        p(
            "| N | pairs | mapper | wall s (CPU s) | models | registered (train + rendered) | "
            "largest model | photos in a verified pair | peak RSS MB | load 1-min |"
        )
        p("|---|---|---|---|---|---|---|---|---|---|")
        for n, mode, r in mapping:
            p(
                f"| {n} | {mode} | {r['mapper']} | {r['wall']:.0f} ({r['cpu']:.0f}) | "
                f"{r['num_models']} | {r['registered']} ({r['registered_train']} + "
                f"{r['registered_synthetic']}) | {r['largest']} | "
                f"{r['images_in_verified_pairs']} | {r['peak_rss_mb']} | "
                f"{r['load_before'].split('/')[0]}–{r['load_after'].split('/')[0]} |"
            )
    executors = [
        row
        for path in sorted(out.glob("n*/executors/result.json"))
        for row in json.loads(path.read_text())["rows"]
    ]
    if executors:
        lines += ["", *executors_table(executors)]
    text = "\n".join(lines)
    (out / "report.md").write_text(text + "\n")
    _plot(out / "scale.png", rows, executors, per_pair)
    return text


def executors_table(executors: list[dict]) -> list[str]:
    """Pairs/s per configuration and per worker against the same kind's 1-worker run."""
    base = {}
    for r in executors:
        if r["workers"] == 1:
            base.setdefault(
                ("local" if r["executor"] == "local" else "ray", r["config"].split("_r")[-1]), r
            )
    lines = [
        "| configuration | workers | pairs | match s | pairs/s | "
        "per worker vs 1 worker | same matches | load 1-min |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in executors:
        b = base.get(("local" if r["executor"] == "local" else "ray", r["config"].split("_r")[-1]))
        ratio = r["pairs_per_s"] / (r["workers"] * b["pairs_per_s"]) if b else float("nan")
        lines.append(
            f"| {r['config']} | {r['workers']} | {r['pairs']} | {r['match_time']:.0f} | "
            f"{r['pairs_per_s']:.2f} | {ratio:.2f} | {r['same_matches_as_local_1']} | "
            f"{r['load_before'].split('/')[0]}–{r['load_after'].split('/')[0]} |"
        )
    return lines


def _plot(path: Path, rows: dict, executors: list, per_pair: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ax = axes[0]
    for mode, style in (("retrieval", "o-"), ("exhaustive", "s--")):
        ns = sorted(n for n, m in rows if m == mode)
        if ns:
            for key, colour in (("extract", "C0"), ("match", "C1"), ("total", "k")):
                ax.plot(
                    ns,
                    [rows[(n, mode)][key] / 60 for n in ns],
                    style,
                    color=colour,
                    label=f"{mode}: {key}",
                )
            ax.plot(
                ns,
                [rows[(n, mode)]["cpu"] / 60 for n in ns],
                style,
                color="C2",
                label=f"{mode}: CPU (all stages)",
            )
    if per_pair:
        n0 = min(per_pair)
        ns = [n0, 200, 1000]
        ax.plot(
            ns,
            [n * (n - 1) / 2 * per_pair[n0][0] / 60 for n in ns],
            ":",
            color="C3",
            label="exhaustive match, projected",
        )
    ax.axhline(60, color="grey", lw=0.8)
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="photos N",
        ylabel="minutes",
        title="time per stage (wall, shared machine)",
    )
    ax.legend(fontsize=7)
    ax = axes[1]
    ns = sorted(n for n, m in rows if m == "retrieval")
    ax.plot(
        ns,
        [rows[(n, "retrieval")]["rss_match"] for n in ns],
        "o-",
        label="match stage peak RSS (MB)",
    )
    ax.plot(
        ns,
        [rows[(n, "retrieval")]["rss_run"] for n in ns],
        "s-",
        label="run peak RSS (MB, max over stages)",
    )
    ax2 = ax.twinx()
    ax2.plot(
        ns,
        [rows[(n, "retrieval")]["held"] or 0 for n in ns],
        "^:",
        color="C3",
        label="images held at once (max)",
    )
    ax2.set_ylabel("images held")
    ax.set(
        xscale="log",
        xlabel="photos N",
        ylabel="MB",
        title="memory (retrieval)",
        ylim=(0, 1.3 * max([r["rss_run"] for r in rows.values()] or [1])),
    )
    ax2.set_ylim(0, 140)
    ax.legend(fontsize=7, loc="upper left")
    ax2.legend(fontsize=7, loc="lower right")
    ax = axes[2]
    for kind, marker in (("local", "o"), ("ray_private", "s"), ("ray_2nodes", "^")):
        pts = [(r["workers"], r["pairs_per_s"]) for r in executors if r["config"].startswith(kind)]
        if pts:
            ax.plot(*zip(*pts), marker, label=kind, ms=8)
    ones = [r["pairs_per_s"] for r in executors if r["workers"] == 1]
    if ones:
        ax.plot(
            [1, 2],
            [min(ones), 2 * min(ones)],
            ":",
            color="grey",
            label="linear from the slower 1-worker run",
        )
    ax.set(xlabel="workers", ylabel="pairs / s", title="matching throughput", xticks=[1, 2])
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def stage_cli(argv=None) -> None:
    """One stage in this process (what run_stage starts)."""
    s = argparse.ArgumentParser(description="one stage of the scale benchmark")
    s.add_argument("cmd", choices=["_stage"])
    s.add_argument("stage", choices=["extract", "match", "map"])
    for a in ("--run_dir", "--images", "--result", "--pairs", "--mapper"):
        s.add_argument(a)
    s.add_argument("--k", type=int, default=10)
    stage_main(s.parse_args(argv))


if __name__ == "__main__":
    stage_cli()
