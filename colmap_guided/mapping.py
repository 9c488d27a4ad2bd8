"""Stage 5: mapping the verified database with COLMAP — incremental, global (GLOMAP) or
hierarchical.

``mapper``: 'auto' (default: incremental mapping, and global mapping too when incremental's model is
doubtful; the larger largest model that passes the model check is kept, on ties the one whose poses
explain more verified inliers, then incremental), 'incremental' (pycolmap.incremental_mapping,
COLMAP's `mapper`), 'global' (pycolmap.global_mapping: rotation averaging + global positioning,
then bundle adjustment) or 'hierarchical' (pycolmap.hierarchical_mapping: the view graph cut into
overlapping clusters mapped incrementally and merged; for thousands of photos). Seeded by default;
with ``num_threads=1`` a rerun on the same database gives the same model (more threads: runs may
differ slightly).

Models are written to a temporary folder and moved into OUTPUT/sparse/N (largest first) only when
mapping finished, so a killed run never leaves a half-written model; a rerun maps the (complete)
database again.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pycolmap

from . import database as dbio
from . import model_check
from .conf import merge_conf
from .geometry import essential_from_pose
from .log import colmap_quiet, logger

MAPPERS = ("auto", "incremental", "global", "hierarchical")
# The default mapper, auto: global places more photos on most sets but drops planar pairs and
# misplaces short straight walks, so it runs only where incremental's model is doubtful
# (docs/RESULTS.md).
default_conf = {
    # auto (incremental, and global too when its model is doubtful: the better checked model),
    # incremental (COLMAP's mapper), global (GLOMAP) or hierarchical (thousands of photos)
    "mapper": "auto",
    "random_seed": 0,  # seeds every random choice of the mapper; None = unseeded (COLMAP's default)
    "num_threads": -1,  # mapping threads: -1 = all cores; 1 = the same model on every rerun
    # keep models of at least this many images (COLMAP: 10 incremental, 3 global)
    "min_model_size": 3,
    # a verified pair joins the view graph with at least this many inliers (COLMAP's)
    "min_num_matches": 15,
    # Incremental (and hierarchical) thresholds for thin view graphs; COLMAP's defaults in brackets.
    # inliers of the initial pair [100]: a ring of ~50-inlier pairs can start a model
    "init_min_num_inliers": 50,
    "init_min_tri_angle": 16.0,  # degrees of parallax the initial pair needs [16]
    # 2D-3D inliers to register a photo [30]: a ring's next photo sees ~25 points
    "abs_pose_min_num_inliers": 15,
    # A photo that observes fewer 3D points than this in the final model is taken out of it (None =
    # keep every photo): its pose rests on too little (proxy: 14 of the 21 such photos were off the
    # reference pose).
    "min_image_points": 15,
    "image_names": None,  # map only these photos (None: all; repeated prints leave some out)
    # bundle adjustment also refines each camera's principal point (a cropped print's is off
    # centre); COLMAP's default: fixed at the image centre
    "refine_principal_point": False,
}


def check_conf(conf: dict | None) -> dict:
    """``default_conf`` updated with ``conf``; an unknown key or mapper is a one-line ValueError."""
    conf = merge_conf(default_conf, conf, "mapping")
    if conf["mapper"] not in MAPPERS:
        raise ValueError(f"Unknown mapper {conf['mapper']!r}; choose one of {list(MAPPERS)}.")
    if conf["random_seed"] is not None and conf["random_seed"] < 0:  # COLMAP's -1: unseeded
        conf["random_seed"] = None
    return conf


def _colmap_seed(conf: dict) -> int:
    """The mapper's seed as COLMAP takes it (-1: unseeded)."""
    return -1 if conf["random_seed"] is None else conf["random_seed"]


def _pipeline_options(options, conf: dict):
    """The options that incremental and global pipelines share, set from ``conf``."""
    for key in ("num_threads", "min_model_size", "min_num_matches"):
        setattr(options, key, conf[key])
    options.image_names = list(conf["image_names"] or [])
    return options


def _incremental_options(conf: dict) -> pycolmap.IncrementalPipelineOptions:
    options = _pipeline_options(pycolmap.IncrementalPipelineOptions(), conf)
    options.mapper.init_min_num_inliers = conf["init_min_num_inliers"]
    options.mapper.init_min_tri_angle = conf["init_min_tri_angle"]
    options.mapper.abs_pose_min_num_inliers = conf["abs_pose_min_num_inliers"]
    options.ba_refine_principal_point = conf["refine_principal_point"]
    for seeded in (options, options.mapper, options.triangulation):
        seeded.random_seed = _colmap_seed(conf)
    return options


def _global_options(conf: dict) -> pycolmap.GlobalPipelineOptions:
    options = _pipeline_options(pycolmap.GlobalPipelineOptions(), conf)
    mapper = options.mapper
    mapper.bundle_adjustment.refine_principal_point = conf["refine_principal_point"]
    for seeded in (
        options,
        mapper,
        mapper.rotation_averaging,
        mapper.global_positioning,
        mapper.retriangulation,
    ):
        seeded.random_seed = _colmap_seed(conf)
    return options


def pose_support(rec: pycolmap.Reconstruction, database_path: Path, max_error: float = 4.0) -> int:
    """Verified inliers between the model's photos that its poses explain: Sampson error under
    ``max_error`` pixels (the verification's RANSAC threshold) of the epipolar geometry of the two
    photos' poses, in undistorted normalized coordinates. A photo placed on a wrong pose contradicts
    the inliers of its pairs."""
    placed = {rec.images[i].name: rec.images[i] for i in rec.reg_image_ids()}
    with dbio.open_database(database_path) as db:
        ids = {image_id: name for image_id, name in dbio.image_names(db).items() if name in placed}
        inliers = dbio.read_verified_inliers(db, set(ids))
        keypoints = {
            image_id: dbio.read_keypoints(db, image_id)[:, :2].astype(np.float64)
            for image_id in {i for pair in inliers for i in pair}
        }
    support = 0
    for (id_a, id_b), matches in inliers.items():
        image_a, image_b = placed[ids[id_a]], placed[ids[id_b]]
        camera_a, camera_b = rec.cameras[image_a.camera_id], rec.cameras[image_b.camera_id]
        b_from_a = image_b.cam_from_world() * image_a.cam_from_world().inverse()
        E = essential_from_pose(b_from_a.rotation.matrix(), b_from_a.translation)
        x_a = camera_a.cam_from_img(keypoints[id_a][matches[:, 0]])
        x_b = camera_b.cam_from_img(keypoints[id_b][matches[:, 1]])
        focal = (camera_a.mean_focal_length() + camera_b.mean_focal_length()) / 2
        errors = np.asarray(
            pycolmap.compute_squared_sampson_error(
                np.ascontiguousarray(x_a), np.ascontiguousarray(x_b), E
            )
        )
        support += int(np.sum(errors < (max_error / focal) ** 2))
    return support


def auto_key(largest: pycolmap.Reconstruction | None, database_path: Path | None) -> tuple:
    """What ``auto`` prefers in a mapper's largest model: passing the model check, then more photos,
    then more verified inliers explained by its poses (``pose_support``; left out when
    ``database_path`` is None)."""
    key = (
        (False, 0)
        if largest is None
        else (not model_check.check_model(largest), largest.num_reg_images())
    )
    if database_path is None:
        return key
    return key + (0 if largest is None else pose_support(largest, database_path),)


def placeable_images(database_path: Path, min_inliers: int) -> set[str]:
    """Photos with at least one verified pair of ``min_inliers`` inliers: those a model could
    hold."""
    with dbio.open_database(database_path) as db:
        names = dbio.image_names(db)
        counts = dbio.pair_inlier_counts(db)
    return {names[i] for pair, n in counts.items() if n >= min_inliers for i in pair}


def _auto(
    conf: dict, database_path: Path, image_path: Path, out: Path
) -> dict[int, pycolmap.Reconstruction]:
    """Incremental mapping, and global mapping only when incremental's model is doubtful (it fails
    the model check or leaves out a photo that has a verified pair); then the largest model that
    passes the model check, on ties the one whose poses explain more verified inliers (computed on
    ties only: it reads every verified pair), then incremental."""
    scored = []
    for mapper in ("incremental", "global"):
        if scored and scored[0][0][0]:
            placeable = placeable_images(database_path, conf["min_num_matches"])
            if conf["image_names"]:  # only these are mapped
                placeable &= set(conf["image_names"])
            left = placeable - registered(scored[0][3])
            if not left:
                logger.info("Incremental mapping placed every photo that has a verified pair")
                break
        (out / mapper).mkdir()
        models = _run({**conf, "mapper": mapper}, database_path, image_path, out / mapper)
        largest = max(models.values(), key=lambda rec: rec.num_reg_images(), default=None)
        scored.append([auto_key(largest, None), mapper, models, largest])
        logger.info(
            "%s mapping: %d images in the largest model, model check %s",
            mapper,
            scored[-1][0][1],
            "ok" if scored[-1][0][0] else "failed",
        )
    if len(scored) == 2 and scored[0][0] == scored[1][0] and scored[0][0][1]:
        for item in scored:
            item[0] += (pose_support(item[3], database_path),)
        logger.info(
            "Tie: %d verified inliers fit incremental's poses, %d global's",
            scored[0][0][2],
            scored[1][0][2],
        )
    return max(scored, key=lambda item: item[0])[2]  # incremental (the first) on ties


def prune_weak_images(rec: pycolmap.Reconstruction, min_points: int) -> dict[str, int]:
    """Deregister the photos that observe fewer than ``min_points`` 3D points, until none is left (a
    photo taken out takes its observations with it, which can leave another one short); returns
    {name: 3D points it observed}."""
    pruned: dict[str, int] = {}
    while True:
        weak = [
            rec.images[i] for i in rec.reg_image_ids() if rec.images[i].num_points3D < min_points
        ]
        if not weak:
            return pruned
        for image in weak:
            pruned[image.name] = image.num_points3D
            rec.deregister_frame(image.frame_id)


def _prune(
    conf: dict, models: dict[int, pycolmap.Reconstruction]
) -> dict[int, pycolmap.Reconstruction]:
    """The models with their weak photos taken out (``min_image_points``); models left with fewer
    than ``min_model_size`` photos are dropped."""
    if not conf["min_image_points"]:
        return models
    kept = {}
    for key, rec in models.items():
        pruned = prune_weak_images(rec, conf["min_image_points"])
        if pruned:
            logger.info(
                "Took %d photo(s) out of a %s-photo model: "
                "each observes fewer than %d 3D points (%s)",
                len(pruned),
                rec.num_reg_images() + len(pruned),
                conf["min_image_points"],
                ", ".join(f"{n}: {k}" for n, k in sorted(pruned.items())),
            )
        if rec.num_reg_images() >= max(2, conf["min_model_size"]):
            kept[key] = rec
    return kept


def _run(
    conf: dict, database_path: Path, image_path: Path, out: Path
) -> dict[int, pycolmap.Reconstruction]:
    def opening(mapper, options):
        args = (str(database_path), str(image_path), str(out), options)
        return dbio.colmap_opening(database_path, lambda: mapper(*args))

    if conf["mapper"] == "auto":
        return _auto(conf, database_path, image_path, out)
    if conf["mapper"] == "global":
        return _prune(conf, opening(pycolmap.global_mapping, _global_options(conf)))
    if conf["mapper"] == "hierarchical":
        options = pycolmap.HierarchicalPipelineOptions()
        options.num_threads = conf["num_threads"]
        # one cluster at a time: reproducible
        options.num_workers = 1 if conf["num_threads"] == 1 else -1
        options.incremental_options = _incremental_options(conf)
        return _prune(conf, opening(pycolmap.hierarchical_mapping, options))
    return _prune(conf, opening(pycolmap.incremental_mapping, _incremental_options(conf)))


def run_mapping(
    database_path: Path,
    image_path: Path,
    sparse_path: Path,
    conf: dict | None = None,
    extend: bool = False,
) -> dict[int, pycolmap.Reconstruction]:
    """Map the database with ``conf['mapper']``; models in ``sparse_path``/0, 1, ... largest
    first. ``extend``: continue ``sparse_path``/0 incrementally with the photos it lacks
    instead."""
    conf = check_conf(conf)
    sparse_path = Path(sparse_path)
    if extend:
        previous = load_models(sparse_path)
        extended = extend_model(database_path, image_path, sparse_path, 0, conf)
        models = one_model_per_photo(extended, previous, conf["min_model_size"])
    else:
        tmp = _scratch(sparse_path, conf)
        logger.info("%s mapping", conf["mapper"].capitalize())
        with colmap_quiet():
            models = _run(conf, database_path, image_path, tmp)
    return write_models(sparse_path, models.values())


def _scratch(sparse_path: Path, conf: dict) -> Path:
    """An empty ``sparse_path``.partial for mapping to write into (``write_models`` replaces it),
    the mapper seeded."""
    tmp = sparse_path.with_name(sparse_path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    if conf["random_seed"] is not None:
        pycolmap.set_random_seed(conf["random_seed"])
    return tmp


def extend_model(
    database_path: Path, image_path: Path, sparse_path: Path, index: int, conf: dict | None = None
) -> dict[int, pycolmap.Reconstruction]:
    """``sparse_path``/``index`` continued incrementally with the photos it lacks (of
    ``conf['image_names']``; None: all), weak photos pruned: the models mapping gives, not
    written (``write_models``)."""
    conf = check_conf(conf)
    sparse_path = Path(sparse_path)
    tmp = _scratch(sparse_path, conf)
    logger.info("Extending the model by mapping")
    with colmap_quiet():
        models = dbio.colmap_opening(
            database_path,
            lambda: pycolmap.incremental_mapping(
                str(database_path),
                str(image_path),
                str(tmp),
                _incremental_options(conf),
                input_path=str(sparse_path / str(index)),
            ),
        )
    shutil.rmtree(tmp)
    return _prune(conf, models)


def registered(rec: pycolmap.Reconstruction) -> set[str]:
    """The names of the model's registered photos."""
    return {rec.images[i].name for i in rec.reg_image_ids()}


def one_model_per_photo(
    extended: dict[int, pycolmap.Reconstruction],
    previous: dict[int, pycolmap.Reconstruction],
    min_size: int,
) -> dict[int, pycolmap.Reconstruction]:
    """The models of ``extend_model`` (``previous[0]`` continued, and what incremental mapping made
    of the other photos) with the other ``previous`` models, each photo in one model: the continued
    model first, then the largest first, each without the photos of a model before it, kept while
    it holds ``min_size`` photos. Mapping the other photos again can place fewer of a model's photos
    than the mapper that made it (the global mapper's street walk): that model stays."""
    base = registered(previous[0]) if 0 in previous else set()
    # incremental mapping may return the input model as it was beside the one it continued
    first = max(
        extended.values(),
        key=lambda rec: (len(registered(rec) & base), rec.num_reg_images()),
        default=None,
    )
    rest = [rec for rec in extended.values() if rec is not first]
    rest += [rec for k, rec in previous.items() if k != 0 or first is None]
    rest.sort(key=lambda rec: -rec.num_reg_images())
    kept, taken = {}, set()
    for rec in ([first] if first is not None else []) + rest:
        for i in list(rec.reg_image_ids()):
            if rec.images[i].name in taken:
                rec.deregister_frame(rec.images[i].frame_id)
        if rec.num_reg_images() >= max(2, min_size):
            kept[len(kept)] = rec
            taken |= registered(rec)
    return kept


def write_models(sparse_path: Path, models) -> dict[int, pycolmap.Reconstruction]:
    """``models`` written to ``sparse_path``/0, 1, ... largest first, as COLMAP users expect to
    find them: into ``sparse_path``.partial, which then replaces ``sparse_path`` (a killed run
    never leaves a half-written model). Returns them by folder."""
    sparse_path = Path(sparse_path)
    ordered = sorted(models, key=lambda rec: rec.num_reg_images(), reverse=True)
    tmp = sparse_path.with_name(sparse_path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for index, rec in enumerate(ordered):
        (tmp / str(index)).mkdir()
        rec.write(str(tmp / str(index)))
    if sparse_path.exists():
        shutil.rmtree(sparse_path)
    tmp.rename(sparse_path)
    return dict(enumerate(ordered))


# A second try's initial pair when the first made no model although pairs verified: a few prints
# linked by a few dozen inliers, taken from nearby places.
WEAK_START = {"init_min_num_inliers": 15, "init_min_tri_angle": 4.0}


def map_weak_start(
    database_path: Path, image_path: Path, sparse_path: Path, conf: dict
) -> dict[int, pycolmap.Reconstruction]:
    """``run_mapping`` with ``WEAK_START``'s thresholds; of its models only those that pass the
    model check are kept (``sparse_path`` rewritten with them)."""
    models = run_mapping(database_path, image_path, sparse_path, {**conf, **WEAK_START})
    kept = [rec for rec in models.values() if not model_check.check_model(rec)]
    if len(kept) < len(models):
        models = write_models(sparse_path, kept)
    logger.info("A weaker initial pair (%s): %d model(s) kept.", WEAK_START, len(kept))
    return models


def load_models(sparse_path: Path) -> dict[int, pycolmap.Reconstruction]:
    sparse_path = Path(sparse_path)
    if not sparse_path.is_dir():
        return {}
    return {
        int(p.name): pycolmap.Reconstruction(str(p))
        for p in sorted(sparse_path.iterdir(), key=lambda p: p.name)
        if p.name.isdigit()
    }


def model_folder(workspace: Path, model: int) -> Path:
    """WORKSPACE/sparse/``model``; a one-line ValueError naming the models there otherwise."""
    sparse = Path(workspace) / "sparse"
    found = sorted(
        int(p.name)
        for p in (sparse.iterdir() if sparse.is_dir() else [])
        if p.name.isdigit() and any((p / f"images.{ext}").is_file() for ext in ("bin", "txt"))
    )
    if not found:
        raise ValueError(
            f"{workspace} holds no model (sparse/0): reconstruct made none; its report.json says "
            "why."
        )
    if model not in found:
        raise ValueError(
            f"--model {model}: {sparse} holds model{'s' if len(found) > 1 else ''} "
            f"{', '.join(map(str, found)) or 'none'} (0 the largest); pass one of them."
        )
    return sparse / str(model)
