"""Pair selection: exhaustive, sequential, retrieval (VLAD of ALIKED, the backbone's GeM), auto."""

import numpy as np
import pytest

from colmap_guided import database as dbio
from colmap_guided.features import extract_features
from colmap_guided.match import _global_descriptors
from colmap_guided.matchers import get_matcher
from colmap_guided.pairs import (
    AUTO_EXHAUSTIVE_MAX,
    exhaustive_pairs,
    gem,
    retrieval_pairs,
    select_pairs,
    sequential_pairs,
)
from colmap_guided.reconstruct import reconstruct
from colmap_guided.synthetic import render_scene


def test_sequential_pairs_link_each_image_to_the_next_ones():
    assert sequential_pairs(["c", "a", "b", "d"], 2) == [
        ("a", "b"),
        ("a", "c"),
        ("b", "c"),
        ("b", "d"),
        ("c", "d"),
    ]


def test_retrieval_takes_the_nearest_images_symmetrically_whatever_the_input_order():
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(2, 16))
    desc = np.concatenate(
        [centres[0] + 0.1 * rng.normal(size=(4, 16)), centres[1] + 0.1 * rng.normal(size=(4, 16))]
    )
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    names = [f"{group}{i}.jpg" for group in "ab" for i in range(4)]
    pairs = retrieval_pairs(names, desc, 2)
    assert all(a[0] == b[0] for a, b in pairs)  # never across the two places
    assert {n for p in pairs for n in p} == set(names) and all(a < b for a, b in pairs)
    order = rng.permutation(8)
    # a resumed run selects the same pairs
    assert retrieval_pairs([names[i] for i in order], desc[order], 2) == pairs


def test_gem_is_unit_norm_and_pools_the_positive_part():
    features = np.zeros((3, 4, 4), np.float32)
    features[0, 0, 0], features[1] = 1.0, -1.0
    d = gem(features)
    assert np.linalg.norm(d) == pytest.approx(1.0) and d[0] > 0.99 and d[1] < 1e-3


def test_auto_is_exhaustive_for_small_sets_and_retrieval_above(tmp_path):
    small = [f"{i:03d}.jpg" for i in range(AUTO_EXHAUSTIVE_MAX)]
    assert select_pairs(None, small) == (exhaustive_pairs(small), "exhaustive")
    large = [f"{i:03d}.jpg" for i in range(AUTO_EXHAUSTIVE_MAX + 1)]
    desc = np.eye(len(large), dtype=np.float32)
    pairs, mode = select_pairs("auto", large, 3, desc)
    assert mode == "retrieval" and len(pairs) <= 3 * len(large)
    with pytest.raises(FileNotFoundError, match="no such pairs file; pass a file or one of auto"):
        select_pairs(str(tmp_path / "missing.txt"), large)
    with pytest.raises(ValueError, match="--num_neighbors must be at least 1"):
        select_pairs("retrieval", large, 0, desc)


def test_retrieval_separates_three_real_places(shared_data):
    """Five photos each of three training scenes pooled, two neighbours per image: no pair across
    places, and each place's photos are linked (the backbone of the shipped guided matcher)."""
    root = shared_data / "train"
    scenes = ["bundler_kermit", "dfsfm_sacre_coeur", "strecha_entry_P10"]
    names = [
        f"{s}/images/{p.name}" for s in scenes for p in sorted((root / s / "images").iterdir())[:5]
    ]
    pairs = retrieval_pairs(names, _global_descriptors(get_matcher("guided"), root, names), 2)
    assert all(a.split("/")[0] == b.split("/")[0] for a, b in pairs), pairs
    for scene in scenes:  # connected: a union-find over the scene's pairs
        parent = {n: n for n in names if n.startswith(scene)}

        def find(x):
            return x if parent[x] == x else find(parent[x])

        for a, b in pairs:
            if a.startswith(scene):
                parent[find(a)] = find(b)
        assert len({find(n) for n in parent}) == 1, (scene, pairs)


def test_retrieval_on_aliked_pairs_each_look_alike_landmark_with_its_own_views(tmp_path):
    """Two rendered landmarks of one make (brick halls with windows, a tower, an annex; each its own
    size) in one folder, ALIKED extracted: each photo's 3 retrieval neighbours (VLAD over the
    shipped codebook) are views of its own landmark."""
    images = tmp_path / "images"
    images.mkdir()
    for seed, hall in ((1000, (12.2, 7.7)), (1001, (9.1, 6.6))):
        conf = {"hall_size": hall}
        scene = render_scene(tmp_path / str(seed), 6, 512, 384, seed=seed, conf=conf)
        for name in scene.names:
            (images / f"{seed}_{name}").symlink_to(scene.image_dir / name)
    names = sorted(p.name for p in images.iterdir())
    extract_features(tmp_path / "database.db", images, names, {"type": "aliked"})
    with dbio.open_database(tmp_path / "database.db") as db:
        desc = _global_descriptors(get_matcher("guided_lightglue"), images, names, db)
    pairs = retrieval_pairs(names, desc, 3)
    assert desc.shape == (12, 64 * 128)
    assert all(a[:4] == b[:4] for a, b in pairs), pairs


def test_reconstruct_with_retrieval_pairs_registers_every_image(synthetic_scene, tmp_path):
    result = reconstruct(
        synthetic_scene.image_dir.parent,
        output=tmp_path / "out",
        matcher="raw",
        pairs_path="retrieval",
        match_options={"num_neighbors": 3},
    )
    assert (
        result["options"]["pairs"]["mode"] == "retrieval"
        and result["options"]["pairs"]["num_neighbors"] == 3
    )
    assert result["database"]["num_pairs"] < 28
    assert result["num_registered"] == len(synthetic_scene.names)


def test_ray_executor_without_ray_says_how_to_install_it(synthetic_scene, tmp_path, monkeypatch):
    import sys

    import pycolmap

    from colmap_guided.match import match_database

    db = tmp_path / "db.db"
    pycolmap.extract_features(db, synthetic_scene.image_dir)
    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    with pytest.raises(
        RuntimeError, match=r"--executor ray needs Ray: pip install 'colmap_guided\[ray\]'"
    ):
        match_database(db, synthetic_scene.image_dir, matcher="raw", executor="ray")
