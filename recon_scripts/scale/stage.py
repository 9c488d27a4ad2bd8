"""One stage of the pipeline (extract, match, map, or reconstruct end to end) in a fresh process
under ``nice``, measured: its times, memory and load go to a JSON file."""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

from colmap_guided import features, mapping
from colmap_guided.log import set_verbosity
from colmap_guided.match import match_database
from colmap_guided.report import model_statistics
from recon_scripts.scale.measure import RssSampler, load, verified_pairs

# the checkout holding recon_scripts: a stage imports it from there, wherever it was started
CHECKOUT = Path(__file__).resolve().parents[2]
THREADS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def _extract(args, db: Path, images: Path, run_dir: Path) -> dict:
    stats = features.extract_features(db, images, features.list_images(images))
    return {"skipped": len(stats["skipped"])}


def _match(args, db: Path, images: Path, run_dir: Path) -> dict:
    stats = match_database(db, images, args.pairs, "guided", num_neighbors=args.k)
    return {
        "num_pairs": stats["num_pairs"],
        "select_time": stats["pairs"]["time"],
        "match_time": stats["match_time"],
        "verify_time": stats["verify_time"],
        "num_verified_pairs": stats["num_verified_pairs"],
        "memory": stats.get("memory"),
        "executor": stats.get("executor"),
    }


def _map(args, db: Path, images: Path, run_dir: Path) -> dict:
    models = mapping.run_mapping(
        db, images, run_dir / f"sparse_{args.mapper}", {"mapper": args.mapper}
    )
    names = features.list_images(images)
    registered = {rec.images[i].name for rec in models.values() for i in rec.reg_image_ids()}
    return {
        "mapper": args.mapper,
        "num_models": len(models),
        "largest": model_statistics(models, names)["num_registered"],
        "registered": len(registered),
        "registered_train": sum(n.startswith("t_") for n in registered),
        "registered_synthetic": sum(n.startswith("s_") for n in registered),
        "num_images": len(names),
        "images_in_verified_pairs": len({i for pair in verified_pairs(db, 15) for i in pair}),
    }


def _reconstruct(args, db: Path, images: Path, run_dir: Path) -> dict:
    """``reconstruct`` end to end as shipped (its workspace: RUN_DIR/workspace)."""
    from colmap_guided.reconstruct import reconstruct

    result = reconstruct(images, image_path=images, output=run_dir / "workspace")
    registered = result["model"]["registered_images"]
    return {
        "timings": result["timings"],
        "matcher": result["matcher"]["name"],
        "num_pairs": result["database"]["num_pairs"],
        "num_pairs_matched": result["database"]["num_pairs_matched_now"],
        "num_verified_pairs": result["database"]["num_verified_pairs"],
        "profile": result["database"]["profile"],
        "escalation": result["database"].get("escalation", []),
        "num_images": result["num_images"],
        "largest": result["model"]["num_registered"],
        "registered": result["model"]["num_registered_all_models"],
        "num_models": result["model"]["num_models"],
        "registered_largest_train": sum(n.startswith("t_") for n in registered),
        "registered_largest_synthetic": sum(n.startswith("s_") for n in registered),
    }


STAGES = {"extract": _extract, "match": _match, "map": _map, "reconstruct": _reconstruct}


def stage_main(args) -> None:
    """Runs one stage (this process) and writes its JSON."""
    set_verbosity(quiet=True)
    run_dir, images = Path(args.run_dir), Path(args.images)
    result = {
        "stage": args.stage,
        "load_before": load(),
        "start": time.strftime("%H:%M:%S", time.gmtime()),
    }
    sampler = RssSampler()
    result["rss_start_mb"] = sampler.rss() >> 20
    t0, c0 = time.time(), time.process_time()
    result.update(STAGES[args.stage](args, run_dir / "database.db", images, run_dir))
    result["wall"] = time.time() - t0
    ru_self = resource.getrusage(resource.RUSAGE_SELF)
    ru_kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    result["cpu"] = time.process_time() - c0 + ru_kids.ru_utime + ru_kids.ru_stime
    result["peak_rss_mb"] = ru_self.ru_maxrss >> 10
    result["rss_samples"] = sampler.close()
    result["load_after"] = load()
    out = Path(args.result)
    out.with_suffix(".partial").write_text(json.dumps(result, indent=1))
    out.with_suffix(".partial").rename(out)


def run_stage(
    stage: str, run_dir: Path, images: Path, result: Path, timeout: float, **extra
) -> dict | None:
    """The stage's JSON ``result``: read when it exists, else written by this module run in a
    fresh process, with one torch/BLAS thread for a single stage (``reconstruct`` runs with the
    machine's own, as a user's run); None when that failed or ran past ``timeout`` s."""
    if result.exists():
        return json.loads(result.read_text())
    options = {"run_dir": run_dir, "images": images, "result": result, **extra}
    cmd = ["nice", "-n", "5", sys.executable, "-m", "recon_scripts.scale.stage", "_stage", stage]
    cmd += [a for k, v in options.items() for a in (f"--{k}", str(v))]
    path = os.pathsep.join(filter(None, [str(CHECKOUT), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "PYTHONPATH": path}
    if stage != "reconstruct":
        env.update(dict.fromkeys(THREADS, "1"))
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


def stage_cli(argv=None) -> None:
    """One stage in this process (what run_stage starts)."""
    s = argparse.ArgumentParser(description="one stage of the scale benchmark")
    s.add_argument("cmd", choices=["_stage"])
    s.add_argument("stage", choices=list(STAGES))
    for a in ("--run_dir", "--images", "--result", "--pairs", "--mapper"):
        s.add_argument(a)
    s.add_argument("--k", type=int, default=10)
    stage_main(s.parse_args(argv))


if __name__ == "__main__":
    stage_cli()
