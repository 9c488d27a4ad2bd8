"""Scale: time per stage, pairs, registered images and peak memory vs N photos.

    python -m recon_scripts scale sets=[]    # the photo pool only (once, ~5 min)
    python -m recon_scripts scale sets=1000 pairs=retrieval
    python -m recon_scripts scale sets="50 200" pairs="retrieval exhaustive"
    python -m recon_scripts scale sets="50 200 1000" mappers="global hierarchical incremental"
    python -m recon_scripts scale_executors sets=200 num_pairs=160
    python -m recon_scripts scale_default sets=1000   # reconstruct end to end, as shipped
    python -m recon_scripts archive                   # the 1,000-photo development archive
    python -m recon_scripts archive sets=60 labels="sacre_coeur wxbs:k*" alone=false
    python -m recon_scripts archive methods=aliked_1024 alone_labels="sacre_coeur postcards:*"

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

`archive`: every labelled photo of ../shared/data (landmark sets, postcards, training scenes,
PhotoTourism landmarks, WxBS pairs: recon_scripts/scale/archive.py) and rendered landmarks up to
N, shuffled (seeded) into one flat folder under opaque names (WORK/n<N>/archive: symlinks,
labels.json); ``reconstruct`` of it in one run, then of each label of 3 photos or more alone
(those of ``alone_labels``, with the archive run's flags); per label, how many of its own run's
photos one archive model holds, and the archive's models that mix labels. A run that succeeded is
kept (WORK/n<N>/<run>.json, alone/<label>/run.json or run_<run>.json) and is not run again.
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

from recon_scripts.bench import Benchmark
from recon_scripts.evaluation.registration import method_slug
from recon_scripts.scale.archive import (
    RUNS,
    archive_report,
    build_archive,
    costs_report,
    run_archive,
    sample_archive,
)
from recon_scripts.scale.executors import match_executors
from recon_scripts.scale.photos import make_pool, photo_set
from recon_scripts.scale.report import default_table, executors_table, report
from recon_scripts.scale.stage import run_stage


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


class ScaleDefault(ScaleBenchmark):
    """reconstruct end to end as shipped: stage times, pairs, registered photos, peak memory.

    One uninterrupted run per N, in a fresh process, on the photo sets of `scale`."""

    name = "scale_default"
    default_conf = {
        "sets": [1000],  # N photos, each set a prefix of the next
        "work": "outputs/benchmark_scale",
        "timeout": 3 * 3600,  # seconds per run
    }

    def configs(self):
        return {"default": {}}

    def prepare(self, n, images, work):
        return {}

    def run_config(self, n, images, prepared, label, config, out):
        r = run_stage("reconstruct", out, images, out / "reconstruct.json", self.conf["timeout"])
        return {"failed": "reconstruct"} if r is None else {"wall": r["wall"]}

    def summarize(self, results):
        return "\n".join(default_table(self.out, self.conf["sets"]))


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


class Archive(Benchmark):
    """The development archive in one run: per label its photos in one model, models mixing labels.

    Labelled photo sets and rendered landmarks shuffled into one folder, reconstructed end to end in
    one run and each label alone: per label the photos of its own run's model in one archive model
    (≥ 95 % each), the models holding photos of two labels (none), time per stage, peak memory."""

    name = "archive"
    default_conf = {
        "sets": [1000],  # N photos per archive: the labels' real photos, rendered landmarks to N
        "work": "outputs/benchmark_archive",
        # the labels taken (fnmatch patterns: "sacre_coeur postcards:* wxbs:*"); first N photos
        "labels": ["*"],
        "seed": 0,  # the shuffle: which photo gets which name
        "take": None,  # a sample: the archive's first N names (all kinds of photos), not all
        "alone": True,  # each label of 3 photos or more reconstructed alone: the reference
        "alone_labels": ["*"],  # the labels of 3 photos or more run alone (fnmatch patterns)
        "methods": ["default"],  # the archive's runs, named in archive.RUNS: "default orphans_kept"
        "timeout": 4 * 3600,  # seconds per reconstruct run
    }
    resume = True  # a killed benchmark keeps the runs that finished

    def folder(self, n, whole: bool = False) -> str:
        c = self.conf
        labels = "" if c["labels"] == ["*"] else "_" + method_slug("-".join(c["labels"]))
        if len(labels) > 40:  # the labels' start and a digest of them all
            labels = labels[:32] + "_" + hashlib.sha1(labels.encode()).hexdigest()[:8]
        take = "" if whole or c["take"] is None else f"_take{c['take']}"
        return f"n{n}{labels}" + (f"_seed{c['seed']}" if c["seed"] else "") + take

    def images(self, n, work):
        c = self.conf
        if c["take"] is None:
            return build_archive(work, n, c["labels"], c["seed"]) / "images"
        whole = build_archive(work.parent / self.folder(n, whole=True), n, c["labels"], c["seed"])
        return sample_archive(whole, work / "archive", c["take"]) / "images"

    def configs(self):
        return {
            name: {
                "alone": self.conf["alone"] and self.conf["alone_labels"],
                "flags": RUNS[name],
            }
            for name in self.conf["methods"]
        }

    def run_config(self, n, images, prepared, label, config, out):
        timeout = self.conf["timeout"]
        result = run_archive(images.parent, out, config["alone"], timeout, config["flags"])
        (out / "report.md").write_text("\n".join(archive_report(n, result)) + "\n")
        return result

    def progress(self, results, n, label):
        c = results[n][label].get("comparison")
        if c is None:
            return f"N={n}: the archive run failed"
        return (
            f"N={n}: {c['labels_ok']}/{c['labels_checked']} labels with ≥ 95 % in one model, "
            f"{len(c['mixing'])} models mixing labels"
        )

    def summarize(self, results):
        parts = []
        for n, res in results.items():
            for name, result in res.items():
                head = [f"### {name}", ""] if len(res) > 1 else []
                parts.append("\n".join(head + archive_report(n, result)))
            parts.append("\n".join(costs_report(res)))
        return "\n\n".join(parts)
