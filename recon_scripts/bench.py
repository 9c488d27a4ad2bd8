"""The base of the benchmark presets (``python -m recon_scripts PRESET key=value ...``).

A preset subclasses ``Benchmark``: ``default_conf`` (every option, set as key=value), ``configs``
(what one run compares, each a JSON-able dict holding all that decides its result), ``prepare``
(once per set, e.g. features extracted once), ``run_config`` (one config on one set, usually on a
copy of the prepared database) and ``summarize`` (Markdown from all results). The base runs the
sets and configs, keeps each result as WORK/<set>/<config>/result.json next to the conf it was made
with (conf.json) and reuses it only while that conf is the same (otherwise it is run again), prints
the summary and writes OUTPUT (JSON: the conf and every result) and the summary beside it
(OUTPUT with .md). Without ``work`` everything goes to a temporary folder, so ratios compare configs
timed in the same run.

Options are named alike in every preset: ``sets`` (what is measured on), ``methods`` (what one run
compares: matcher specs, named runs), ``seeds`` (where a result is random), ``work``, ``output``.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path

from colmap_guided import features
from colmap_guided.conf import merge_conf
from colmap_guided.log import logger, set_verbosity
from colmap_guided.paths import shared_data_dir
from colmap_guided.reconstruct import WRITES
from colmap_guided.workspace import Workspace
from recon_scripts.evaluation.registration import method_slug
from recon_scripts.evaluation.tables import write_json

# Options of every preset: the photo sets (folders of ../shared/data with images/, or
# train/SCENE), the work folder (results and features kept for a rerun; none: temporary) and the
# JSON written at the end (none: outputs/benchmark_<preset>.json).
BASE_CONF = {"sets": ["sacre_coeur_hloc"], "work": None, "output": None}


def same(a, b) -> bool:
    """Confs equal once written as JSON (tuples read back as lists)."""
    return json.dumps(a, sort_keys=True, default=str) == json.dumps(b, sort_keys=True, default=str)


class Benchmark:
    name = ""
    default_conf: dict = {}
    resume = False  # True: run_config always runs, on what a killed run left, skipping what is done

    def __init__(self, conf: dict | None = None):
        self.conf = merge_conf({**BASE_CONF, **self.default_conf}, conf, f"{self.name} benchmark")

    # -- what a preset defines ---------------------------------------------------------------

    def configs(self) -> dict[str, dict]:
        """label -> config, in the order of the table."""
        raise NotImplementedError

    def folder(self, name) -> str:
        """The set's folder under the work folder."""
        return method_slug(str(name))

    def images(self, name, work: Path) -> Path:
        """The set's photos."""
        return shared_data_dir() / name / "images"

    def prepare(self, name: str, image_path: Path, work: Path) -> dict:
        """What every config of one set shares (nothing by default)."""
        return {}

    def run_config(
        self, name: str, image_path: Path, prepared: dict, label: str, config: dict, out: Path
    ) -> dict:
        raise NotImplementedError

    def summarize(self, results: dict) -> str:
        """Markdown of {set: {label: result}}."""
        raise NotImplementedError

    def progress(self, results: dict, name: str, label: str) -> str:
        """What is printed as each result comes (a run stopped early keeps it)."""
        return f"{name} {label} {results[name][label]}"

    # -- shared steps ----------------------------------------------------------------------------

    @staticmethod
    def extract(
        image_path: Path, work: Path, feature_conf: dict | None = None
    ) -> tuple[Path, float]:
        """A database of the set's features (``feature_conf`` over the defaults), extracted once
        per work folder, and the extraction's seconds per image."""
        slug = "_".join(f"{k}-{v}" for k, v in sorted((feature_conf or {}).items())) or "default"
        db = work / f"features_{method_slug(slug)}" / "database.db"
        timing = db.parent / "extract_s_per_image.txt"
        if not timing.exists():
            shutil.rmtree(db.parent, ignore_errors=True)
            db.parent.mkdir(parents=True)
            names = features.list_images(image_path)
            start = time.time()
            features.extract_features(db, image_path, names, feature_conf)
            timing.write_text(str((time.time() - start) / len(names)))
        return db, float(timing.read_text())

    @staticmethod
    def copy_database(db: Path, out: Path) -> Path:
        """``out``, claimed for ``reconstruct`` (which refuses a folder of other files), holding a
        copy of ``db``."""
        Workspace.claim(out, "reconstruct").record(*WRITES)
        shutil.copy(db, out / "database.db")
        return out / "database.db"

    def run_cached(self, name, image_path, prepared, label, config, out: Path) -> dict:
        saved = {"set": name, "config": config}
        conf_file, result_file = out / "conf.json", out / "result.json"
        if result_file.exists() and conf_file.exists() and not self.resume:
            if same(json.loads(conf_file.read_text()), saved):
                return json.loads(result_file.read_text())
            logger.warning("%s %s: its saved conf differs from this one, run again", name, label)
        if not self.resume:
            shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True, exist_ok=True)
        result = self.run_config(name, image_path, prepared, label, config, out)
        write_json(conf_file, saved)
        write_json(result_file, result)
        return result

    def run(self) -> dict:
        set_verbosity(quiet=True)
        output = Path(self.conf["output"] or f"outputs/benchmark_{self.name}.json")
        configs = self.configs()
        results = {}
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(self.conf["work"] or tmp)
            for name in self.conf["sets"]:
                set_work = work / self.folder(name)
                image_path = self.images(name, set_work)
                prepared = self.prepare(name, image_path, set_work)
                for label, config in configs.items():
                    out = set_work / method_slug(label)
                    result = self.run_cached(name, image_path, prepared, label, config, out)
                    results.setdefault(name, {})[label] = result
                    print(self.progress(results, name, label), flush=True)
                    write_json(output, {"conf": self.conf, "results": results})
        summary = self.summarize(results)
        output.with_suffix(".md").write_text(summary + "\n")
        print("\n" + summary)
        return results
