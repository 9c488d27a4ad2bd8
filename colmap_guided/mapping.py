"""Stage 5: COLMAP's incremental mapping on the verified database (pycolmap.incremental_mapping).

Models are written to a temporary folder and moved into OUTPUT/sparse/N only when mapping finished,
so a killed run never leaves a half-written model; a rerun maps again from the (complete) database.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pycolmap

from .log import colmap_quiet, logger

default_conf = {"random_seed": 0, "min_model_size": 3, "num_threads": -1}


def incremental_mapping(database_path: Path, image_path: Path, sparse_path: Path, conf: dict | None = None) -> dict[int, pycolmap.Reconstruction]:
    conf = {**default_conf, **(conf or {})}
    sparse_path = Path(sparse_path)
    tmp = sparse_path.with_name(sparse_path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = conf["random_seed"]
    options.min_model_size = conf["min_model_size"]
    options.num_threads = conf["num_threads"]
    logger.info("Incremental mapping")
    with colmap_quiet():
        models = pycolmap.incremental_mapping(str(database_path), str(image_path), str(tmp), options)
    # Largest model first, as sparse/0, like COLMAP users expect to find it.
    ordered = sorted(models.values(), key=lambda rec: rec.num_reg_images(), reverse=True)
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    for index, rec in enumerate(ordered):
        (tmp / str(index)).mkdir()
        rec.write(str(tmp / str(index)))
    if sparse_path.exists():
        shutil.rmtree(sparse_path)
    tmp.rename(sparse_path)
    return dict(enumerate(ordered))


def load_models(sparse_path: Path) -> dict[int, pycolmap.Reconstruction]:
    sparse_path = Path(sparse_path)
    if not sparse_path.is_dir():
        return {}
    return {int(p.name): pycolmap.Reconstruction(str(p)) for p in sorted(sparse_path.iterdir(), key=lambda p: p.name) if p.name.isdigit()}
