"""Joining models: the photos of one landmark that retrieval ranks apart (its modern street views
and its archival prints) can make two models, which no pair of the first pass links and
escalation, working for the largest model's left-out photos, does not try to link.

After escalation, for two models whose photos look alike (each model with its ``CANDIDATES`` most
alike others, most alike first), the ``join_pairs`` most similar pairs of a
photo of one and a photo of the other (retrieval descriptors) are matched with the full matcher
where the first pass did not (the ``PROBE`` most similar first, the rest only where one of them
verified). Where pairs verified with ``strong_inliers`` reach at least
``MIN_PHOTOS`` photos on each side, the larger model is continued by incremental mapping with the
smaller's photos; the merge is kept only where it holds the two models' photos, has no model check
problem they did not have, and its two parts agree on what their photos see
(``visibility_conflicts``). Two buildings of one style (an architect's, a repeated facade) verify
on their look-alike windows, and a merge aligned on them passes every other check; the rest of
each building stands in front of what the other's photos see, and they stay two models.

The same test cuts a model that mapping made of two such buildings (``split_models``, after the
first mapping and after escalation): the model's weakest seam in shared points, where most of what
each side's photos see of the other side conflicts. The photos a cut put apart are not mapped
together again, neither by escalation nor by the join.
"""

from __future__ import annotations

import time
from collections import Counter
from itertools import combinations
from pathlib import Path

import numpy as np
import pycolmap

from . import database as dbio
from . import escalate, mapping, match, model_check
from .log import colmap_quiet, logger
from .mapping import registered
from .matchers import Matcher
from .model_check import covisibility
from .pipeline import PipelineConf

# verified pairs must reach this many photos of each model: a single look-alike pair (one
# repeated facade seen from two places) joins nothing
MIN_PHOTOS = 2
# a try matches its most similar cross pairs first, this many, and stops where none verified: two
# buildings' most alike photos are their best chance
PROBE = 2 * MIN_PHOTOS
# each model tries the models whose photos are most like its own, this many: an archive of many
# buildings costs a few tries per model, not one per two models
CANDIDATES = 3
# a merge may leave out this share of the two models' photos (mapping's pruning of weak photos);
# one that leaves out more placed the smaller model only in part, and is not kept
MAX_LEFT_OUT = 0.1
# A merge whose parts put more than this share of their points in front of what the other part's
# photos see there (``visibility_conflicts``) is two places that look alike: 0.32 on two halls of
# one style, 0.01-0.04 on landmarks joined right (synthetic, lund_door; docs/RESULTS.md), ~2.7x
# from each.
MAX_CONFLICTS = 0.12
# A model whose two sides (its ``seam``) put more of their points well in front of what the other
# side's photos see there (``SPLIT_IN_FRONT``) than at its depth is two places mapped as one: 0.88
# on two halls of one style the first pass mapped as one, at most 0.20 on 23 COLMAP models of
# single places and on the archive's models of one place (docs/RESULTS.md). The join refuses at
# MAX_CONFLICTS: a model is cut on a majority, two models joined on agreement.
SPLIT_CONFLICTS = 0.5
# well in front: at most this share of the depth seen, a building where another stands; points a
# little in front (a pillar's edge in a cell of a wall) reach 0.44 of a sparse model of one hall
SPLIT_IN_FRONT = 0.7
# and at least this many conflicts a photo of the smaller side, as many matches as a pair needs to
# verify: a building where the other's photos look is seen by each of them (3.4 a photo where a hall
# of one place was cut, 78 on the halls of one style)
MIN_CONFLICTS = 15
# a point agrees with what a photo sees where their depths differ by at most this share; the
# photo's view is cut in cells of this share of its larger side (each: its nearest point)
DEPTH_TOLERANCE, CELL = 0.05, 0.015


def cross_pairs(
    names_a: set[str], names_b: set[str], descriptors: dict, num_pairs: int
) -> list[tuple[str, str]]:
    """The ``num_pairs`` most similar pairs of a photo of ``names_a`` and one of ``names_b``
    (cosine similarity of their retrieval ``descriptors``), most similar first, each photo in at
    most a (2 ``MIN_PHOTOS``)th of them: a print similar to every photo takes few, and the pairs
    reach several photos of each model."""
    a, b = sorted(names_a), sorted(names_b)
    similarity = np.stack([descriptors[n] for n in a]) @ np.stack([descriptors[n] for n in b]).T
    per_photo, taken, pairs = -(-num_pairs // (2 * MIN_PHOTOS)), Counter(), []
    for i, j in zip(
        *np.unravel_index(np.argsort(-similarity, axis=None, kind="stable"), similarity.shape)
    ):
        if taken[a[i]] < per_photo and taken[b[j]] < per_photo:
            taken.update((a[i], b[j]))
            pairs.append((a[i], b[j]))
            if len(pairs) == num_pairs:
                break
    return pairs


def join_models(
    database_path: Path,
    image_path: Path,
    sparse_path: Path,
    models: dict,
    matcher: Matcher,
    conf: PipelineConf,
    mapping_conf: dict,
    descriptors: dict | None,
    pairs_path: Path,
    kept: set[frozenset] = frozenset(),
    cuts: list[dict] = (),
) -> tuple[dict, list[dict]]:
    """Two ``models`` of ``candidates`` at a time, each two tried once: their ``join_pairs`` most
    similar cross pairs matched with the full matcher where the first pass did not (written to
    ``pairs_path``), the models merged where verified pairs reach ``MIN_PHOTOS`` photos of each
    (``merge``); a join rewrites ``sparse_path`` and the models are tried again. ``descriptors``:
    the retrieval descriptors by name where matching computed them; ``kept``: the pairs a cheap
    decision kept (``escalate.read_kept``); ``cuts``: ``split_models``'s, two models it put apart
    are not tried. Returns the models and a record of each try."""
    num_pairs, tries, tried = conf.escalation.join_pairs, [], set()
    full, descriptors = None, dict(descriptors or {})
    while num_pairs and len(models) > 1:
        missing = sorted(set().union(*map(registered, models.values())) - set(descriptors))
        if missing:
            with dbio.open_database(database_path) as db:
                computed = match._global_descriptors(matcher, image_path, missing, db)
            descriptors.update(zip(missing, computed))
        untried = [
            pair
            for pair in candidates(models, descriptors)
            if _key(models, pair) not in tried
            and not _cut_apart(cuts, *(registered(models[k]) for k in pair))
        ]
        if not untried:
            break
        start, pair = time.time(), untried[0]
        tried.add(_key(models, pair))
        names = [registered(models[k]) for k in pair]
        cross = cross_pairs(*names, descriptors, num_pairs)
        todo = escalate.pairs_to_escalate(
            database_path,
            names[0] | names[1],
            cross,
            set(),
            num_pairs,
            kept,
        )
        matched = 0
        for part in (todo[:PROBE], todo[PROBE:]):
            if part:
                full = full or escalate.full_matcher(matcher)
                match.rematch(database_path, image_path, full, conf, part, pairs_path)
                matched += len(part)
            counted = _with_inliers(database_path, cross)
            verified = [(a, b) for a, b, n in counted if n >= conf.escalation.strong_inliers]
            if not verified:
                break
        cross = counted
        sides = [len({p[k] for p in verified}) for k in (0, 1)]
        merged, found = (
            merge(database_path, image_path, sparse_path, models, pair, mapping_conf)
            if min(sides) >= MIN_PHOTOS
            else (None, {"why": f"verified pairs on {sides[0]} and {sides[1]} photos"})
        )
        tries.append(
            {
                "models": list(pair),
                "photos": [len(n) for n in names],
                "pairs": [list(p) for p in cross],
                "matched": matched,
                "verified": len(verified),
                "joined": merged is not None,
                **found,
                "time": time.time() - start,
            }
        )
        logger.info(
            "Models %d and %d (%d and %d photos): %s", *pair, *tries[-1]["photos"], found["why"]
        )
        if merged is not None:
            others = [rec for k, rec in models.items() if k not in pair]
            models = mapping.write_models(sparse_path, [merged, *others])
    return models, tries


def _with_inliers(database_path: Path, pairs: list) -> list[tuple[str, str, int]]:
    """(name_a, name_b, verified inliers; 0 where none) of ``pairs`` in the database."""
    with dbio.open_database(database_path) as db:
        ids = {name: image.image_id for name, image in dbio.images_by_name(db).items()}
        inliers = dbio.pair_inlier_counts(db)
    return [(a, b, inliers.get(tuple(sorted((ids[a], ids[b]))), 0)) for a, b in pairs]


def candidates(models: dict, descriptors: dict) -> list[tuple[int, int]]:
    """The pairs of models to try, most alike first: each model with its ``CANDIDATES`` most alike
    others (the largest cosine similarity of a photo of one and a photo of the other)."""
    stacks = {
        k: np.stack([descriptors[n] for n in sorted(registered(rec))]) for k, rec in models.items()
    }
    alike = {
        (a, b): float((stacks[a] @ stacks[b].T).max()) for a, b in combinations(sorted(models), 2)
    }
    kept = set()
    for k in models:
        mine = sorted((pair for pair in alike if k in pair), key=lambda pair: -alike[pair])
        kept.update(mine[:CANDIDATES])
    return sorted(kept, key=lambda pair: (-alike[pair], pair))


def _key(models: dict, pair: tuple[int, int]) -> frozenset:
    """Two models by their photos (a try is not repeated when folders are renumbered)."""
    return frozenset(frozenset(registered(models[k])) for k in pair)


def merge(
    database_path: Path,
    image_path: Path,
    sparse_path: Path,
    models: dict,
    pair: tuple[int, int],
    mapping_conf: dict,
) -> tuple[pycolmap.Reconstruction | None, dict]:
    """The larger model of ``pair`` (``sparse_path``/N) continued by incremental mapping with the
    smaller's photos, and why it is kept or not (None), with the evidence: kept where it holds the
    two models' photos (``MAX_LEFT_OUT``), has no model check problem more than the two had and
    few ``visibility_conflicts`` (``MAX_CONFLICTS``), and the smaller continued with the larger's
    photos passes the same checks: a merge aligned on look-alike parts may pass them from one side
    only."""
    found, merged = {"conflicts": []}, None
    for order in (pair, pair[::-1]):
        extended, why = _extend(database_path, image_path, sparse_path, models, order, mapping_conf)
        found["conflicts"].append(why.pop("conflicts", None))
        if extended is None:
            return None, {**found, **why}
        merged = merged or extended
    return merged, {**found, "why": f"joined: one model of {merged.num_reg_images()} photos"}


def _extend(database_path, image_path, sparse_path, models, pair, mapping_conf) -> tuple:
    """``pair[0]``'s model continued with ``pair[1]``'s photos: (the model, {}), or (None, why);
    with the visibility conflicts where counted."""
    both = registered(models[pair[0]]) | registered(models[pair[1]])
    conf = {**mapping_conf, "image_names": sorted(both)}
    extended = mapping.extend_model(database_path, image_path, sparse_path, pair[0], conf)
    merged = max(extended.values(), key=lambda rec: rec.num_reg_images(), default=None)
    held = len(registered(merged) & both) if merged is not None else 0
    if held < (1 - MAX_LEFT_OUT) * len(both):
        return None, {"why": f"the merge held {held} of {len(both)} photos"}
    problems = model_check.check_model(merged)
    if len(problems) > sum(len(model_check.check_model(models[k])) for k in pair):
        return None, {"why": f"the merge fails the model check: {problems[0]}"}
    conflicts, agreements = visibility_conflicts(merged, registered(models[pair[1]]))
    found = {"conflicts": [conflicts, agreements]}
    if conflicts > MAX_CONFLICTS * max(1, conflicts + agreements):
        why = (
            f"the merge puts {conflicts} points of one model in front of what the other's photos "
            f"see there ({agreements} agree): two places that look alike"
        )
        return None, {**found, "why": why}
    return merged, found


def seam(rec: pycolmap.Reconstruction) -> set[str] | None:
    """The photos of one side of ``rec``'s weakest cut in shared 3D points: of the cuts along the
    normalized Laplacian's second eigenvector, the one of least conductance (Shi and Malik's
    normalized cut), each side ``MIN_PHOTOS`` photos or more. None where no cut leaves both."""
    ids = sorted(rec.reg_image_ids())
    if len(ids) < 2 * MIN_PHOTOS:
        return None
    index = {image_id: k for k, image_id in enumerate(ids)}
    weights = np.zeros((len(ids), len(ids)))
    for (a, b), shared in covisibility(rec).items():
        weights[index[a], index[b]] = weights[index[b], index[a]] = shared
    degree = np.maximum(weights.sum(axis=1), 1e-9)
    scale = 1 / np.sqrt(degree)
    _, vectors = np.linalg.eigh(np.eye(len(ids)) - scale[:, None] * weights * scale[None, :])
    order = np.argsort(vectors[:, 1] * scale, kind="stable")
    # the weight across each cut of the order, and the degree on its first side
    across = np.cumsum(
        [
            weights[i, order[k + 1 :]].sum() - weights[i, order[:k]].sum()
            for k, i in enumerate(order)
        ]
    )
    volume = np.cumsum(degree[order])
    cuts = range(MIN_PHOTOS, len(ids) - MIN_PHOTOS + 1)
    k = min(cuts, key=lambda k: across[k - 1] / min(volume[k - 1], volume[-1] - volume[k - 1]))
    return {rec.images[ids[i]].name for i in order[k:]}


def find_cut(rec: pycolmap.Reconstruction, in_front: float = SPLIT_IN_FRONT) -> dict:
    """``rec``'s ``seam`` (``side``: the photos of one side, None where none), its
    ``visibility_conflicts`` (``in_front``) and whether it is cut there: two places that look
    alike mapped as one where its sides conflict (``SPLIT_CONFLICTS``; ``MIN_CONFLICTS`` a photo
    of the smaller side)."""
    side = seam(rec)
    conflicts, agreements = visibility_conflicts(rec, side, in_front) if side else (0, 0)
    smaller = min(len(side), rec.num_reg_images() - len(side)) if side else 0
    cut = conflicts >= max(1, MIN_CONFLICTS * smaller, SPLIT_CONFLICTS * (conflicts + agreements))
    return {"side": side, "conflicts": conflicts, "agreements": agreements, "cut": cut}


def split_models(models: dict, sparse_path: Path) -> tuple[dict, list[dict]]:
    """Each model cut at its seam where ``find_cut`` says so: two places that look alike (a
    repeated facade, one architect's windows) mapped as one. Each side becomes a model of its own
    (the other's photos taken out, bundle adjusted) and is cut again; ``sparse_path`` is rewritten
    where a model was cut. Returns the models and each cut made."""
    todo, kept, cuts = list(models.values()), [], []
    while todo:
        rec = todo.pop()
        found = find_cut(rec)
        if not found["cut"]:
            kept.append(rec)
            continue
        parts = [_part(rec, found["side"]), _part(rec, registered(rec) - found["side"])]
        cuts.append(
            {
                "photos": [sorted(registered(p)) for p in parts],
                "conflicts": found["conflicts"],
                "agreements": found["agreements"],
            }
        )
        logger.info(
            "Cut a model of %d photos in two (%d and %d): %d of its points lie in front of what "
            "the other side's photos see there (%d agree), two places that look alike",
            rec.num_reg_images(),
            *map(pycolmap.Reconstruction.num_reg_images, parts),
            found["conflicts"],
            found["agreements"],
        )
        todo += parts
    return (mapping.write_models(sparse_path, kept) if cuts else models), cuts


def cut_away(cuts: list[dict], names: set[str]) -> set[str]:
    """The photos that a cut of ``cuts`` put on the other side from most of ``names``: a model
    of ``names`` is not continued with them (mapping a look-alike's photos one by one into a
    building's model can agree with it, as a merge of the two sides cannot)."""
    away = set()
    for cut in cuts:
        sides = [set(side) for side in cut["photos"]]
        held = [len(side & names) for side in sides]
        if held[0] != held[1]:
            away |= sides[held[0] > held[1]]
    return away


def _cut_apart(cuts: list[dict], names_a: set[str], names_b: set[str]) -> bool:
    """Whether ``cuts`` put most of ``names_b`` away from most of ``names_a``."""
    return 2 * len(names_b & cut_away(cuts, names_a)) > len(names_b)


def _part(rec: pycolmap.Reconstruction, names: set[str]) -> pycolmap.Reconstruction:
    """A copy of ``rec`` with the photos ``names`` only, bundle adjusted."""
    part = pycolmap.Reconstruction(rec)
    for image_id in list(part.reg_image_ids()):
        if part.images[image_id].name not in names:
            part.deregister_frame(part.images[image_id].frame_id)
    with colmap_quiet():
        pycolmap.bundle_adjustment(part, pycolmap.BundleAdjustmentOptions(print_summary=False))
    return part


def visibility_conflicts(
    rec: pycolmap.Reconstruction, names: set[str], in_front: float = 1 - DEPTH_TOLERANCE
) -> tuple[int, int]:
    """How the two parts of ``rec`` (the photos ``names`` and the others) see each other: of the
    points only one part observes, those that a photo of the other part would see where it
    observes a point (the nearest in a ``CELL`` of its view), in front of that point (conflicts:
    it would hide what the photo sees; ``in_front``: at most this share of its depth) or at its
    depth (``DEPTH_TOLERANCE``: agreements). A landmark joined right agrees with itself; two
    buildings that share a facade, aligned on it, conflict everywhere else. Points behind are
    hidden and say nothing. Returns (conflicts, agreements)."""
    part = {i: rec.images[i].name in names for i in rec.reg_image_ids()}
    xyz = {True: [], False: []}
    for point in rec.points3D.values():
        sides = {part[element.image_id] for element in point.track.elements}
        if len(sides) == 1:
            xyz[sides.pop()].append(point.xyz)
    conflicts = agreements = 0
    for image_id, side in part.items():
        image = rec.images[image_id]
        camera = rec.cameras[image.camera_id]
        observed = [rec.points3D[p.point3D_id].xyz for p in image.points2D if p.has_point3D()]
        if not observed or not xyz[not side]:
            continue
        cell = CELL * max(camera.width, camera.height)
        shape = (int(camera.height // cell) + 1, int(camera.width // cell) + 1)
        nearest = np.full(shape, np.inf)
        cells, depth = _project(image, camera, np.array(observed), cell)
        np.minimum.at(nearest, cells, depth)
        cells, depth = _project(image, camera, np.array(xyz[not side]), cell)
        seen = nearest[cells]
        depth, seen = depth[np.isfinite(seen)], seen[np.isfinite(seen)]
        conflicts += int(np.sum(depth < in_front * seen))
        agreements += int(np.sum(np.abs(depth - seen) <= DEPTH_TOLERANCE * seen))
    return conflicts, agreements


def _project(image, camera, xyz: np.ndarray, cell: float) -> tuple[tuple, np.ndarray]:
    """The cells (rows, columns) of the points ``xyz`` in front of the photo and inside its view,
    and their depths."""
    pose = image.cam_from_world()
    cam = xyz @ pose.rotation.matrix().T + pose.translation
    cam = cam[cam[:, 2] > 0]
    uv = np.asarray(camera.img_from_cam(cam)).reshape(-1, 2)
    inside = (
        (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    )
    uv = (uv[inside] // cell).astype(int)
    return (uv[:, 1], uv[:, 0]), cam[inside, 2]
