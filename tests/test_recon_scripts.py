"""The benchmark runner: `python -m recon_scripts PRESET key=value ...`."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

from colmap_guided.paths import REPO_ROOT
from recon_scripts.__main__ import PRESETS, main, parse_value, preset_class


def test_help_lists_every_preset():
    out = subprocess.run(
        [sys.executable, "-m", "recon_scripts", "--help"],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    for name in PRESETS:
        assert f"\n  {name} " in out and preset_class(name).name == name


def test_options_are_read_against_the_presets_defaults(capsys):
    assert parse_value("sacre_coeur_hloc opensfm_lund", ["a"]) == [
        "sacre_coeur_hloc",
        "opensfm_lund",
    ]
    assert parse_value("3 5", [1]) == [3, 5] and parse_value("5", [1]) == [5]
    assert parse_value("[]", [1]) == [] and parse_value("false", True) is False
    assert parse_value("guided:raw_below=100", "x") == "guided:raw_below=100"
    conf = preset_class("pairs")({"k": [5], "sets": ["opensfm_lund"]}).conf
    assert conf["k"] == [5] and conf["matcher"] == "guided" and conf["sets"] == ["opensfm_lund"]


def test_an_unknown_option_or_preset_is_one_line_and_runs_nothing(capsys):
    assert main(["pairs", "kk=3"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "'kk'" in err and "did you mean 'k'" in err
    assert main(["pairs", "k"]) == 2 and "key=value" in capsys.readouterr().err
    assert main(["no_such_preset"]) == 2 and "unknown preset" in capsys.readouterr().err


def test_the_archive_is_a_flat_folder_of_labelled_photos_under_opaque_names(shared_data, tmp_path):
    from colmap_guided.features import list_images
    from colmap_guided.images import read_image
    from recon_scripts.scale.archive import (
        build_archive,
        plan_archive,
        real_sources,
        sample_archive,
    )

    chosen = ["berliner_dom", "wxbs:kettle", "alamo"]  # 5 + 4 + 4 photos, 2 rendered views
    archive = build_archive(tmp_path, 15, chosen, seed=3)
    labels = json.loads((archive / "labels.json").read_text())
    sources = json.loads((archive / "sources.json").read_text())
    files = sorted(os.listdir(archive / "images"))
    assert files == sorted(labels) == sorted(sources) == list_images(archive / "images")
    assert {m["name"] for m in json.loads((archive / "manifest.json").read_text())["images"]} == {
        *files
    }
    assert sorted(set(labels.values())) == sorted([*chosen, "rendered:s_1000"])
    # opaque, unique names: nothing of the label or the source's name, the sources shuffled
    assert all(re.fullmatch(r"p[0-9]{4}\.(jpg|png)", name) for name in files)
    in_name_order = [labels[name] for name in files]
    assert in_name_order != sorted(in_name_order, key=in_name_order.index)
    # the same seed, the same names; another seed, others
    real = [(lb, f) for lb, f in real_sources(shared_data) if lb in chosen]
    rendered = sorted((lb, Path(sources[n])) for n, lb in labels.items() if lb.startswith("rend"))
    plan = {n: (lb, str(f)) for n, (lb, f) in plan_archive(real + rendered, 3).items()}
    assert plan == {n: (labels[n], sources[n]) for n in files}
    assert plan_archive(real, 3) == plan_archive(real, 3) != plan_archive(real, 4)
    # a sample: the first names, the same photos under the same labels
    sample = sample_archive(archive, tmp_path / "sample", 5)
    taken = sorted(os.listdir(sample / "images"))
    assert taken == files[:5] == sorted(json.loads((sample / "labels.json").read_text()))
    assert all((sample / "images" / n).resolve() == Path(sources[n]).resolve() for n in taken)
    assert json.loads((sample / "labels.json").read_text()) == {n: labels[n] for n in taken}
    # each a link to a photo outside the checkout, read as the pipeline reads it
    for name in files:
        assert not Path(os.path.realpath(archive / "images" / name)).is_relative_to(REPO_ROOT)
        assert read_image(archive / "images" / name).ndim == 3


def test_the_archive_comparison_finds_a_label_split_and_a_model_mixing_labels(
    synthetic_scene, tmp_path
):
    import pycolmap

    from colmap_guided.cards import panel_name
    from recon_scripts.scale.archive import compare, label_of, read_models

    names = synthetic_scene.names  # view_000 ... view_007
    labels = {n: "a" if i < 4 else "b" for i, n in enumerate(names)}
    for model, keep in {"0": names[:6], "1": names[6:]}.items():
        rec = pycolmap.Reconstruction(synthetic_scene.gt_dir)
        for image in list(rec.images.values()):
            if image.name not in keep:
                rec.deregister_frame(image.frame_id)
        (tmp_path / model).mkdir()
        rec.write(tmp_path / model)
    (tmp_path / "text").mkdir()  # not a model
    models = read_models(tmp_path, names)
    assert models == {"0": set(names[:6]), "1": set(names[6:])}
    alone = {"a": {"0": set(names[:4])}, "b": {"0": set(names[4:]), "1": {names[0]}}}
    c = compare(labels, models, alone)
    a, b = c["labels"]["a"], c["labels"]["b"]
    assert (a["registered_alone"], a["in_best_model"], a["ratio"], a["ok"]) == (4, 4, 1.0, True)
    assert (b["registered_alone"], b["in_best_model"], b["ok"]) == (4, 2, False)
    assert b["archive_models"] == ["0", "1"] and b["registered_archive"] == 4
    assert c["mixing"] == [{"model": "0", "photos": 6, "labels": {"a": 4, "b": 2}}]
    assert (c["labels_checked"], c["labels_ok"]) == (2, 1)
    # a collage card's panel counts as its card
    label = label_of({"p0007.jpg": "a", "p0012.png": "b"})
    assert label("../default/run/panels/" + panel_name("p0012.png", 2)) == "b"
    assert label("p0007.jpg") == "a" and label("x.jpg") is None
