"""Tiny CPU training on the sparse filter the CPU pipeline runs (default) and on dense windows: the
loss goes down, checkpoints resume exactly, weights are exported."""

import json

import numpy as np
import pytest
import torch

from colmap_guided.train import trainer as T

DATA = dict(
    train_scenes=["bundler_et", "vggsfm_statue"],
    val_scenes=["strecha_entry_P10"],
    max_images_per_scene=2,
    resolution=128,
    n_variants=2,
    n_synthetic=1,
    val_pairs_per_scene=2,
)


def _conf(cache, **kw):
    conf = dict(
        supervision="epipolar",
        iterations=6,
        batch_size=4,
        log_every=2,
        val_every=100,
        checkpoint_every=2,
        data={**DATA, "cache_dir": str(cache)},
    )
    return {**conf, **kw}


def _fixed_loss(tr):
    samples = tr.data.sample_batch(np.random.default_rng(99), 8, 4)
    with torch.no_grad():
        return tr.loss(samples)[0].item()


@pytest.fixture(scope="module")
def straight(tmp_path_factory, shared_data):
    """An uninterrupted 8-iteration run, and its loss on a fixed batch before and after training."""
    root = tmp_path_factory.mktemp("smoke")
    tr = T.Trainer(root / "run", _conf(root / "features", iterations=8, lr=1e-2))
    before = _fixed_loss(tr)
    assert tr.train() is True
    return tr, root, before, _fixed_loss(tr)


def test_smoke_training_decreases_loss_and_exports(straight):
    tr, root, before, after = straight
    assert after < before - 1e-3, (before, after)
    assert (root / "run" / "curves.png").stat().st_size > 1000
    hist = json.loads((root / "run" / "history.json").read_text())
    assert len(hist["train"]) == 8 and len(hist["val"]) == 2  # before training and at the end
    assert {"pck8", "pck16", "pck32"} <= set(hist["val"][-1])
    from safetensors import safe_open

    with safe_open(str(root / "run" / "coarse_filter.safetensors"), "pt") as f:
        keys = list(f.keys())
        meta = f.metadata()
    assert keys and any("weight" in k for k in keys)
    assert "epipolar" in json.dumps(meta) and "bundler_et" in json.dumps(meta)


def test_resume_continues_exactly(straight, tmp_path):
    ref, root, _, _ = straight
    conf = _conf(root / "features", iterations=4, lr=1e-2)
    first = T.Trainer(tmp_path / "b", conf)
    first.train()
    assert first.iteration == 4 and (tmp_path / "b" / "checkpoint.pt").exists()
    resumed = T.Trainer(tmp_path / "b", {**conf, "iterations": 8})
    assert resumed.iteration == 4
    resumed.train()
    assert resumed.iteration == 8
    for (k, p), q in zip(
        ref.model.filter.state_dict().items(), resumed.model.filter.state_dict().values()
    ):
        assert torch.equal(p, q), k
    assert [h["loss"] for h in ref.history] == [h["loss"] for h in resumed.history]
    with pytest.raises(ValueError, match="supervision"):
        T.Trainer(tmp_path / "b", {**conf, "supervision": "image"})


def test_pck_errors_zero_on_an_exact_translation():
    """A volume whose argmax is a 2-column, 1-row shift and GT points shifted by exactly that."""
    from colmap_guided.coarse.geometry import resize_geometry
    from colmap_guided.train.views import PairSample, View

    g = resize_geometry(640, 480, 320, 16, 15.5)
    h, w = g.grid_height, g.grid_width
    s = torch.zeros(h, w, h, w)
    for r in range(h):
        for c in range(w):
            s[r, c, min(r + 1, h - 1), min(c + 2, w - 1)] = 1
    view = View("x", "scene", "x", g, np.zeros((h, w, 2)))
    shift = np.array([2, 1]) * 16 / g.scale  # in original pixels
    # interior
    pts_a = g.cell_centers()[[43, 64, 110, 172]] + [
        [3.0, 4.0],
        [0.0, 0.0],
        [10.0, -7.0],
        [5.0, 5.0],
    ]
    sample = PairSample(view, view, True, "sfm", np.eye(3), pts_a, pts_a + shift)
    ab, ba = s.reshape(h * w, h * w).argmax(1).numpy(), s.reshape(h * w, h * w).argmax(0).numpy()
    err = T.pck_errors(ab, ba, sample)
    assert np.allclose(err, 0, atol=1e-9)  # both directions interpolate the shift exactly
    bad = PairSample(view, view, True, "sfm", np.eye(3), pts_a, pts_a + shift + [20.0, 0.0])
    assert np.allclose(T.pck_errors(ab, ba, bad)[:4], 20.0)


def test_finetune_stage_updates_the_backbone(straight, tmp_path):
    ref, root, _, _ = straight
    conf = _conf(
        root / "features",
        iterations=1,
        batch_size=2,
        finetune_backbone=True,
        backbone_lr=1e-3,
        init=str(root / "run" / "coarse_filter.safetensors"),
        val_every=1000,
    )
    tr = T.Trainer(tmp_path / "ft", conf)
    for p, q in zip(ref.model.filter.parameters(), tr.model.filter.parameters()):
        assert torch.equal(p, q)  # initialised from the frozen stage's export
    before = [p.detach().clone() for p in tr.model.backbone.parameters()]
    tr.train()
    changed = sum(not torch.equal(a, b) for a, b in zip(before, tr.model.backbone.parameters()))
    assert changed > 10  # the backbone is trained in this stage
    resumed = T.Trainer(tmp_path / "ft", {**conf, "iterations": 1})
    assert resumed.iteration == 1
    for p, q in zip(tr.model.backbone.parameters(), resumed.model.backbone.parameters()):
        assert torch.equal(p, q)  # its checkpoint holds the backbone too


def test_dense_windowed_path_trains_and_resume_checks_the_path(straight, tmp_path):
    """The batched dense filter on grid windows (--impl dense --max_cells, the GPU / old CPU
    recipe)."""
    _, root, _, _ = straight
    conf = _conf(root / "features", impl="dense", iterations=6, lr=1e-2, lr_steps=(5,))
    conf["data"] = {**conf["data"], "max_cells": 4}
    tr = T.Trainer(tmp_path / "dense", conf)
    before = _fixed_loss(tr)
    assert tr.train() is True
    assert _fixed_loss(tr) < before - 1e-3
    # the last iteration ran after the 10x drop
    assert tr.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3)
    # a checkpoint continues on the path it was trained on
    with pytest.raises(ValueError, match="impl"):
        T.Trainer(tmp_path / "dense", {**conf, "impl": "sparse"})
    with pytest.raises(ValueError, match="point supervision"):
        T.Trainer(tmp_path / "points", {**conf, "impl": "sparse", "supervision": "points"})
