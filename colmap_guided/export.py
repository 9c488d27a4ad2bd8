"""hloc-compatible h5 files from a COLMAP database, and back: guided matches for hloc or other
front-ends. Also the model for other tools (``export_model``: PLY points and COLMAP's text format,
beside the model).

    python -m colmap_guided export --database_path DB
        --output DIR    # DIR/features.h5, matches.h5, pairs.txt
    python -m colmap_guided import --database_path NEW.db
        --features DIR/features.h5 --matches DIR/matches.h5

The layout is hloc's (Hierarchical-Localization, ``hloc/utils/io.py`` and ``parsers.py``):

- features.h5: one group per image name (a name with '/' gives nested groups, as h5py does for
  hloc), with ``keypoints`` (N, 2) float32 in hloc's convention — pixel CENTRE at integer
  coordinates, i.e. COLMAP's x, y minus 0.5 (hloc adds 0.5 back when it imports into COLMAP) —,
  ``descriptors`` (D, N) (SIFT: uint8 as COLMAP stores them), ``scores`` (N,)
  (COLMAP stores none: ones) and ``image_size`` (width, height).
- matches.h5: one group per pair, named ``names_to_pair(name0, name1)`` =
  ``name0.replace('/', '-') + '/' + name1.replace('/', '-')``, with ``matches0`` (N0,) int32 (index
  in image 1, -1 = unmatched) and ``matching_scores0`` (N0,) float16 (1 matched, 0 not: COLMAP keeps
  no score).
- pairs.txt: the exported pairs, hloc's pairs-file format (hloc's import_matches needs it).

Datasets and attributes prefixed ``colmap_`` are ours (hloc ignores them): the exact COLMAP keypoint
rows (x, y, affine shape), the camera, and the verified two-view geometry, so that exporting and
importing gives back the same database. Files written by hloc (without them) import too; their pairs
are then verified with COLMAP's two-view estimator, as ``match`` does.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import h5py
import numpy as np
import pycolmap

from . import database as dbio
from . import verify
from .log import add_verbosity_flags, logger, progress
from .pairs import write_pairs
from .workspace import Workspace

# What `export` writes in its folder: --overwrite replaces these and nothing else.
WRITES = ("features.h5", "matches.h5", "features.h5.partial", "matches.h5.partial", "pairs.txt")


def export_model(rec: pycolmap.Reconstruction, model_path: Path) -> dict:
    """MODEL/points3D.ply (pycolmap's export_PLY: MeshLab, CloudCompare) and MODEL/text/
    (COLMAP text format).

    Written inside the model's folder (sparse/0 stays a model folder: COLMAP reads its .bin files),
    each through a temporary name, so a killed run never leaves a half-written file. Returns their
    paths.
    """
    import shutil

    model_path = Path(model_path)
    ply, text = model_path / "points3D.ply", model_path / "text"
    rec.export_PLY(str(model_path / "points3D.ply.partial"))
    (model_path / "points3D.ply.partial").replace(ply)
    partial = model_path / "text.partial"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    rec.write_text(str(partial))
    shutil.rmtree(text, ignore_errors=True)
    partial.rename(text)
    return {"ply": str(ply), "text": str(text)}


def names_to_pair(name0: str, name1: str, separator: str = "/") -> str:
    """hloc's pair key (current hloc; ``separator='_'`` gives its older ``names_to_pair_old``)."""
    return separator.join((name0.replace("/", "-"), name1.replace("/", "-")))


def _bar(total: int, desc: str, unit: str):
    return progress(desc=desc, unit=unit, total=total)


def export_h5(
    database_path: Path, output: Path, inliers_only: bool = False, overwrite: bool = False
) -> dict:
    """Write OUTPUT/features.h5, matches.h5 and pairs.txt from ``database_path``; returns counts.

    ``inliers_only``: matches.h5 holds the verified (inlier) matches instead of all putative
    matches.
    """
    workspace = Workspace.claim(output, "export", keep=(database_path,))
    output = workspace.path
    paths = {k: output / f"{k}.h5" for k in ("features", "matches")}
    for path in paths.values():
        if path.exists() and not overwrite:
            raise FileExistsError(
                f"{path} exists; pass --overwrite to replace it, or another --output."
            )
    workspace.record(*WRITES)
    tmp = {k: p.with_suffix(".h5.partial") for k, p in paths.items()}
    with dbio.open_database(database_path) as db:
        images = sorted(dbio.images_by_name(db).values(), key=lambda im: im.name)
        _check_pair_keys(images)
        _export_features(db, images, tmp["features"])
        pairs = _export_matches(db, images, tmp["matches"], inliers_only)
    for key in paths:
        tmp[key].replace(paths[key])
    write_pairs(output / "pairs.txt", pairs)
    logger.info("Exported %d images and %d pairs to %s", len(images), len(pairs), output)
    return {
        "num_images": len(images),
        "num_pairs": len(pairs),
        "features": str(paths["features"]),
        "matches": str(paths["matches"]),
        "pairs": str(output / "pairs.txt"),
    }


def _check_pair_keys(images: list) -> None:
    """Refuse two images whose names give the same hloc pair key ('/' written as '-')."""
    names_seen: dict[str, str] = {}
    for im in images:
        key = im.name.replace("/", "-")
        if key in names_seen:
            raise ValueError(
                f"Images {names_seen[key]!r} and {im.name!r} have "
                f"the same hloc pair key {key!r}; rename one of them."
            )
        names_seen[key] = im.name


def _export_features(db, images: list, path: Path) -> None:
    """features.h5 at ``path``: a group for each image with keypoints."""
    with h5py.File(path, "w") as fd, _bar(len(images), "export features", "img") as bar:
        for im in images:
            if dbio.has_keypoints(db, im.image_id):
                _write_features(fd, db, im)
            bar.update(1)


def _write_features(fd: h5py.File, db, im) -> None:
    """One image's group: hloc's keypoints, descriptors, scores, size; COLMAP's exact rows."""
    kpts = dbio.read_keypoints(db, im.image_id)
    desc, kind = dbio.read_descriptors(db, im.image_id)
    camera = dbio.read_camera(db, im.camera_id)
    grp = fd.create_group(im.name)
    grp.create_dataset("keypoints", data=kpts[:, :2] - 0.5)
    grp.create_dataset("descriptors", data=np.ascontiguousarray(desc.T))
    grp.create_dataset("scores", data=np.ones(len(kpts), np.float32))
    grp.create_dataset("image_size", data=np.array([camera.width, camera.height], np.int64))
    grp.create_dataset("colmap_keypoints", data=kpts)
    grp.attrs["colmap_descriptor_type"] = kind
    grp.attrs["colmap_camera_id"] = int(camera.camera_id)
    grp.attrs["colmap_camera_model"] = camera.model.name
    grp.attrs["colmap_camera_params"] = np.asarray(camera.params, np.float64)
    grp.attrs["colmap_prior_focal_length"] = bool(camera.has_prior_focal_length)


def _export_matches(db, images: list, path: Path, inliers_only: bool) -> list[tuple[str, str]]:
    """matches.h5 at ``path``: a group for each matched pair, by name; returns the pairs."""
    by_id = {im.image_id: im for im in images}
    id_pairs = list(dbio.pair_match_counts(db))
    pairs = []
    with h5py.File(path, "w") as fd, _bar(len(id_pairs), "export matches", "pair") as bar:
        for id_a, id_b in sorted(id_pairs, key=lambda p: tuple(sorted(by_id[i].name for i in p))):
            a, b = sorted((by_id[id_a], by_id[id_b]), key=lambda im: im.name)
            _write_matches(fd, db, a, b, inliers_only)
            pairs.append((a.name, b.name))
            bar.update(1)
    return pairs


def _write_matches(fd: h5py.File, db, a, b, inliers_only: bool) -> None:
    """One pair's group: hloc's matches0 and scores, and COLMAP's exact matches and geometry."""
    matches = dbio.read_pair_matches(db, a.image_id, b.image_id)
    geometry = dbio.read_two_view_geometry(db, a.image_id, b.image_id)
    if inliers_only:
        matches = (
            np.asarray(geometry.inlier_matches, np.uint32).reshape(-1, 2)
            if geometry is not None
            else np.zeros((0, 2), np.uint32)
        )
    grp = fd.create_group(names_to_pair(a.name, b.name))
    matches0 = np.full(dbio.num_keypoints(db, a.image_id), -1, np.int32)
    matches0[matches[:, 0]] = matches[:, 1]
    grp.create_dataset("matches0", data=matches0)
    grp.create_dataset("matching_scores0", data=(matches0 >= 0).astype(np.float16))
    grp.attrs["colmap_names"] = [a.name, b.name]
    representable = len(np.unique(matches[:, 0])) == len(matches) and np.all(
        np.diff(matches[:, 0].astype(np.int64)) > 0
    )
    # a keypoint matched twice, or not in order: matches0 cannot hold it exactly
    if not representable:
        grp.create_dataset("colmap_matches", data=matches)
    if geometry is not None and not inliers_only:
        _write_geometry(grp, geometry)


def _write_geometry(grp: h5py.Group, geometry: pycolmap.TwoViewGeometry) -> None:
    grp.create_dataset(
        "colmap_inlier_matches", data=np.asarray(geometry.inlier_matches, np.uint32).reshape(-1, 2)
    )
    grp.attrs["colmap_config"] = int(geometry.config)
    for key in ("F", "E", "H"):
        if getattr(geometry, key) is not None:
            grp.attrs[f"colmap_{key}"] = np.asarray(getattr(geometry, key), np.float64)
    pose = geometry.cam2_from_cam1
    if pose is not None:
        grp.attrs["colmap_cam2_from_cam1"] = np.r_[
            np.asarray(pose.rotation.quat, np.float64), np.asarray(pose.translation, np.float64)
        ]


def _read_geometry(grp: h5py.Group) -> pycolmap.TwoViewGeometry | None:
    if "colmap_inlier_matches" not in grp:
        return None
    geometry = pycolmap.TwoViewGeometry()
    geometry.config = int(grp.attrs["colmap_config"])
    for key in ("F", "E", "H"):
        if f"colmap_{key}" in grp.attrs:
            setattr(geometry, key, np.asarray(grp.attrs[f"colmap_{key}"], np.float64))
    if "colmap_cam2_from_cam1" in grp.attrs:
        v = np.asarray(grp.attrs["colmap_cam2_from_cam1"], np.float64)
        geometry.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(v[:4]), v[4:])
    geometry.inlier_matches = np.ascontiguousarray(
        grp["colmap_inlier_matches"][()], np.uint32
    ).reshape(-1, 2)
    return geometry


def _feature_groups(fd: h5py.File) -> dict[str, h5py.Group]:
    """{image name: group} for every group holding ``keypoints`` (nested names joined with '/')."""
    found = {}

    def visit(name, obj):
        if isinstance(obj, h5py.Group) and "keypoints" in obj:
            found[name] = obj

    fd.visititems(visit)
    return found


def _new_camera(grp: h5py.Group, name: str, image_path: Path | None) -> pycolmap.Camera:
    if "colmap_camera_model" in grp.attrs:
        width, height = (int(v) for v in grp["image_size"][()])
        camera = pycolmap.Camera.create_from_model_name(
            0, str(grp.attrs["colmap_camera_model"]), 1.0, width, height
        )
        camera.params = np.asarray(grp.attrs["colmap_camera_params"], np.float64)
        camera.has_prior_focal_length = bool(grp.attrs["colmap_prior_focal_length"])
        return camera
    if "image_size" in grp:
        width, height = (int(v) for v in grp["image_size"][()])
    elif image_path is not None:
        from .images import image_size

        width, height = image_size(Path(image_path) / name)
    else:
        raise ValueError(
            f"features.h5 has no image_size for {name!r}: pass "
            "--image_path so the camera size can be read from the photo."
        )
    return verify.default_camera(width, height)


def import_h5(
    database_path: Path,
    features_path: Path,
    matches_path: Path | None = None,
    image_path: Path | None = None,
    verification_conf: dict | None = None,
) -> dict:
    """Keypoints, descriptors (and matches) of hloc h5 files into a COLMAP database
    (created if needed).

    Images already in the database must have the same keypoints (else: an error, nothing written for
    them); new images get a camera (ours: the exported one; hloc's: COLMAP's default from
    image_size). Pairs already matched in the database are left as they are. Pairs without an
    exported two-view geometry are verified with COLMAP's estimator.
    """
    database_path, features_path = Path(database_path), Path(features_path)
    if not features_path.is_file():
        raise FileNotFoundError(
            f"No features file at {features_path}: pass "
            "the features.h5 written by `export` or hloc."
        )
    if matches_path is not None and not Path(matches_path).is_file():
        raise FileNotFoundError(
            f"No matches file at {matches_path}: pass the matches.h5 written by `export` or hloc."
        )
    database_path.parent.mkdir(parents=True, exist_ok=True)
    stats = {"num_images_added": 0, "num_pairs_added": 0, "num_pairs_verified": 0}
    with (
        h5py.File(features_path, "r") as fd,
        dbio.open_database(database_path, must_exist=False) as db,
    ):
        stats["num_images_added"] = _import_features(db, fd, features_path, image_path)
        if matches_path is None:
            return stats
        images = dbio.images_by_name(db)
        id_pairs, stats["num_pairs_added"] = _import_matches(
            db, images, matches_path, features_path
        )
        stats["num_pairs_verified"] = verify.verify_pairs(
            db, images, id_pairs, verify.two_view_options(verification_conf)
        )
        stats.update(dbio.database_summary(db))
    logger.info(
        "Imported %d new images and %d pairs into %s (%d pairs verified here)",
        stats["num_images_added"],
        stats["num_pairs_added"],
        database_path,
        stats["num_pairs_verified"],
    )
    return stats


def _import_features(db, fd: h5py.File, features_path: Path, image_path: Path | None) -> int:
    """Each image group of features.h5 into the database; returns how many images were new."""
    groups = _feature_groups(fd)
    if not groups:
        raise ValueError(
            f"{features_path} has no image groups with 'keypoints': not an hloc features file."
        )
    existing = dbio.images_by_name(db)
    cameras: dict[int, int] = {}  # exported camera id -> camera id in this database
    added = 0
    with _bar(len(groups), "import features", "img") as bar:
        for name in sorted(groups):
            grp = groups[name]
            kpts, desc = _read_features(grp)
            old = existing.get(name)
            if old is not None and dbio.has_keypoints(db, old.image_id):
                _check_same_keypoints(db, old.image_id, kpts, name, features_path)
                bar.update(1)
                continue
            kind = str(grp.attrs.get("colmap_descriptor_type", "SIFT"))
            if desc is not None and desc.dtype != np.uint8:
                raise ValueError(
                    f"{name}: descriptors are {desc.dtype}; COLMAP's database "
                    "holds uint8 (SIFT) descriptors — import keypoints and "
                    "matches only by deleting 'descriptors' or convert them."
                )
            with dbio.transaction(db):
                if old is not None:
                    image_id = old.image_id
                else:
                    image_id = dbio.add_image(db, name, _camera(db, grp, name, cameras, image_path))
                    added += 1
                dbio.write_features(db, image_id, kpts, desc, kind)
            bar.update(1)
    return added


def _read_features(grp: h5py.Group) -> tuple[np.ndarray, np.ndarray | None]:
    """COLMAP keypoint rows (exact ones, else hloc's shifted back by 0.5) and (N, D) descriptors."""
    kpts = np.asarray(
        grp["colmap_keypoints"][()] if "colmap_keypoints" in grp else grp["keypoints"][()] + 0.5,
        np.float32,
    )
    desc = (
        np.ascontiguousarray(np.asarray(grp["descriptors"][()]).T) if "descriptors" in grp else None
    )
    return kpts, desc


def _check_same_keypoints(
    db, image_id: int, kpts: np.ndarray, name: str, features_path: Path
) -> None:
    """Refuse a file whose keypoints differ from those the database holds for the image."""
    have = dbio.read_keypoints(db, image_id)
    if have.shape[0] != kpts.shape[0] or not np.array_equal(have[:, :2], kpts[:, :2]):
        raise ValueError(
            f"{name}: the database has other keypoints than {features_path}; "
            "import into a new database (another --database_path)."
        )


def _camera(
    db, grp: h5py.Group, name: str, cameras: dict[int, int], image_path: Path | None
) -> pycolmap.Camera:
    """The image's camera: one already imported for its exported camera id, else a new one."""
    exported = int(grp.attrs["colmap_camera_id"]) if "colmap_camera_id" in grp.attrs else None
    if exported is not None and exported in cameras:
        return dbio.read_camera(db, cameras[exported])
    camera = _new_camera(grp, name, image_path)
    camera.camera_id = dbio.write_camera(db, camera)
    if exported is not None:
        cameras[exported] = camera.camera_id
    return camera


def _import_matches(
    db, images: dict, matches_path: Path, features_path: Path
) -> tuple[list[tuple[int, int, str, str]], int]:
    """Each pair group of matches.h5 not matched yet into the database; returns every pair of the
    file (id_a, id_b, name_a, name_b) and how many were new."""
    by_key = {}
    for name in images:
        by_key.setdefault(name.replace("/", "-"), []).append(name)
    id_pairs = []
    added = 0
    with h5py.File(matches_path, "r") as fm:
        entries = list(_match_groups(fm, by_key))
        with _bar(len(entries), "import matches", "pair") as bar:
            for a, b, grp in entries:
                ia, ib = images[a].image_id, images[b].image_id
                id_pairs.append((ia, ib, a, b))
                if not dbio.pair_has_matches(db, ia, ib):
                    _import_pair(db, grp, (a, b), (ia, ib), features_path)
                    added += 1
                bar.update(1)
    return id_pairs, added


def _import_pair(db, grp: h5py.Group, names: tuple, ids: tuple, features_path: Path) -> None:
    """One pair's matches (exact ones, else from matches0) and exported geometry, if any."""
    if "colmap_matches" in grp:
        matches = np.asarray(grp["colmap_matches"][()], np.uint32).reshape(-1, 2)
    else:
        matches0 = np.asarray(grp["matches0"][()]).astype(np.int64)
        idx = np.flatnonzero(matches0 >= 0)
        matches = np.stack([idx, matches0[idx]], axis=1).astype(np.uint32)
    num_a, num_b = dbio.num_keypoints(db, ids[0]), dbio.num_keypoints(db, ids[1])
    if len(matches) and (matches[:, 0].max() >= num_a or matches[:, 1].max() >= num_b):
        raise ValueError(
            f"Pair {names[0]} / {names[1]}: matches index keypoints that {features_path} "
            "does not have; the two files do not belong together."
        )
    dbio.write_pair_matches(db, *ids, matches)
    geometry = _read_geometry(grp)
    if geometry is not None:
        dbio.write_pair_geometry(db, *ids, geometry)


def _match_groups(fm: h5py.File, by_key: dict[str, list[str]]):
    """(name_a, name_b, group) for every pair group of an hloc matches file
    (current or old naming)."""

    def resolve(key: str) -> str | None:
        names = by_key.get(key, [])
        if len(names) > 1:
            raise ValueError(
                f"Images {names} have the same hloc pair key {key!r}: "
                "hloc's matches cannot tell them apart."
            )
        return names[0] if names else None

    for k0, g0 in fm.items():
        if not isinstance(g0, h5py.Group):
            continue
        if "matches0" in g0:  # old hloc naming: name0_name1 in one group
            if "colmap_names" in g0.attrs:
                yield str(g0.attrs["colmap_names"][0]), str(g0.attrs["colmap_names"][1]), g0
                continue
            parts = k0.split("_")
            for cut in range(1, len(parts)):
                a, b = resolve("_".join(parts[:cut])), resolve("_".join(parts[cut:]))
                if a and b:
                    yield a, b, g0
                    break
            else:
                raise ValueError(
                    f"Pair {k0!r} of the matches file names images that "
                    "are not in the database; import the features first."
                )
            continue
        for k1, grp in g0.items():
            if not (isinstance(grp, h5py.Group) and "matches0" in grp):
                continue
            if "colmap_names" in grp.attrs:
                a, b = (str(v) for v in grp.attrs["colmap_names"])
            else:
                a, b = resolve(k0), resolve(k1)
            if a is None or b is None:
                raise ValueError(
                    f"Pair {k0}/{k1} of the matches file names images that "
                    "are not in the database; import the features first."
                )
            yield a, b, grp


def add_parser(sub) -> None:
    """The ``export`` and ``import`` commands."""
    exp = sub.add_parser(
        "export",
        help="keypoints and matches of a database as hloc "
        "h5 files (features.h5, matches.h5, pairs.txt)",
    )
    exp.add_argument("--database_path", type=Path, required=True)
    exp.add_argument(
        "--output",
        type=Path,
        required=True,
        help="folder for features.h5, matches.h5 and pairs.txt",
    )
    exp.add_argument(
        "--inliers_only",
        action="store_true",
        help="export the verified matches instead of all putative matches",
    )
    exp.add_argument(
        "--overwrite", action="store_true", help="replace existing h5 files in --output"
    )
    add_verbosity_flags(exp)
    exp.set_defaults(run=run_export)
    imp = sub.add_parser(
        "import",
        help="hloc h5 keypoints and matches into a COLMAP "
        "database (created if needed), then verify",
    )
    imp.add_argument("--database_path", type=Path, required=True)
    imp.add_argument("--features", type=Path, required=True, help="features.h5 (hloc layout)")
    imp.add_argument("--matches", type=Path, default=None, help="matches.h5 (hloc layout)")
    imp.add_argument(
        "--image_path",
        type=Path,
        default=None,
        help="photos folder: sizes for files without image_size",
    )
    add_verbosity_flags(imp)
    imp.set_defaults(run=run_import)


def run_export(args: argparse.Namespace) -> None:
    out = export_h5(
        args.database_path, args.output, inliers_only=args.inliers_only, overwrite=args.overwrite
    )
    print(
        f"{out['num_images']} images, {out['num_pairs']} pairs -> "
        f"{out['features']}, {out['matches']}, {out['pairs']}"
    )


def run_import(args: argparse.Namespace) -> None:
    out = import_h5(args.database_path, args.features, args.matches, args.image_path)
    print(
        f"{out['num_images_added']} images and {out['num_pairs_added']} "
        f"pairs imported into {args.database_path}"
    )
