"""Training loop of the coarse network (paper §4.3): Adam, lr 1e-3, batch 8, frozen backbone first.

Resumable across sessions: ``OUT/checkpoint.pt`` holds the filter (and backbone when fine-tuned),
the optimiser, the batch sampler's and torch's RNG states, the iteration and the history, written
atomically every ``checkpoint_every`` iterations and when ``max_minutes`` is reached. Running the
same command again continues exactly where it stopped (same batches, same parameters as an
uninterrupted run). ``OUT/curves.png`` plots the losses and the validation PCK; ``OUT/history.json``
has the numbers; ``OUT/coarse_filter.safetensors`` (the coarse package's weight format, with the
training config) is refreshed at every checkpoint, so the latest filter can be evaluated any time;
a fine-tuned backbone's feature layers go into that file too (the pipeline loads them with the
filter).

Filter paths (``impl``): 'sparse' (default) trains what the CPU pipeline runs,
``CoarseNet.sparse_volume`` on the matcher's support (k best cells both ways + cells around each
best match), on whole grids, one pair at a time; 'dense' trains the batched dense filter (GPU; on a
CPU only on ``max_cells`` windows: its whole-grid step costs ~120x the sparse one, MODEL_CARD.md).

Stages: ``finetune_backbone=False`` trains the 4D filter on cached frozen-backbone features
(``CoarseTrainData.build_cache``); ``finetune_backbone=True`` (after convergence, ``init`` = the
frozen-stage checkpoint or weights) also trains the backbone with ``backbone_lr``, computing
features from the rendered images at every step (BatchNorm statistics stay frozen: batches are
small).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from colmap_guided.coarse.flow import interpolate_grid
from colmap_guided.coarse.geometry import stack_padded
from colmap_guided.coarse.matcher import CoarseMatcher
from colmap_guided.coarse.model import CoarseNet, correlation, sparse_best
from colmap_guided.coarse.weights import load_filter_weights, save_filter_weights
from colmap_guided.conf import merge_conf
from colmap_guided.log import logger
from colmap_guided.train.data import CoarseTrainData, collate
from colmap_guided.train.losses import coarse_loss, epipolar_loss_from_best, image_loss_from_best
from colmap_guided.train.views import PairSample
from colmap_guided.workspace import Workspace

PCK_THRESHOLDS = (8, 16, 32)
# What training writes in --out; a run started again there resumes from them.
WRITES = (
    "checkpoint.pt",
    "checkpoint.tmp",
    "coarse_filter.safetensors",
    "coarse_filter.tmp.safetensors",
    "history.json",
    "curves.png",
)

# an option's comment is the help of its flag in python -m colmap_guided.train
default_conf = {
    # loss (paper §4.2): 'image' (same scene or not), 'epipolar' (the pair's relative pose) or
    # 'points' (ground-truth matches)
    "supervision": "epipolar",
    "iterations": 25000,  # training steps (paper §4.3)
    "batch_size": 8,  # pairs per step, positives and negatives
    "negatives": None,  # negatives per batch; None: half the batch for image/epipolar, 0 for points
    "lr": 1e-3,  # learning rate of the 4D filter (Adam)
    # iterations after which the learning rates drop 10x (each); empty: constant (paper §4.3)
    "lr_steps": (),
    "seed": 0,  # torch's seed and the batch sampler's
    # filter during training: 'sparse' (the CPU inference path, CoarseNet.sparse_volume, whole
    # grids, one pair at a time) or 'dense' (batched 4D conv; GPU, or windows of max_cells on CPU)
    "impl": "sparse",
    # sparse support as the pipeline matches: best cells per cell and direction
    "sparse_k": CoarseMatcher.default_conf["sparse_k"],
    "sparse_radius": CoarseMatcher.default_conf["sparse_radius"],  # cells around each best match
    "finetune_backbone": False,  # second stage: also train the backbone
    "backbone_lr": 1e-5,  # learning rate of the backbone when finetune_backbone
    "init": None,  # checkpoint.pt or .safetensors to start from (fine-tuning stage)
    "max_minutes": None,  # stop and checkpoint after this many minutes of wall time in this run
    "log_every": 10,  # iterations between log lines
    "val_every": 250,  # iterations between validations (PCK on the held-out scenes)
    "checkpoint_every": 50,  # iterations between checkpoints
    "model": {},  # CoarseNet options (backbone, channels, kernel_sizes, mutual_before/after)
    "data": {},  # CoarseTrainData options
}


# ------------------------------------------------------------------------------------------- PCK
def pck_errors(ab: np.ndarray, ba: np.ndarray, sample: PairSample) -> np.ndarray:
    """Errors (pixels, original resolution) of the coarse flow at the GT points, both directions,
    from the coarse matches ab (hA·wA,) and ba (hB·wB,) of the pair's whole grids
    (flat cell indices)."""
    ga, gb = sample.a.geometry, sample.b.geometry
    if len(sample.pts_a) == 0:
        return np.zeros(0)
    # m^{A→B}: bilinear interpolation of the matches of the four nearest cells (coarse.flow, §4.1)
    flow_ab, _ = interpolate_grid(ga, gb.cell_centers()[ab], sample.pts_a)
    flow_ba, _ = interpolate_grid(gb, ga.cell_centers()[ba], sample.pts_b)
    e_ab = np.linalg.norm(flow_ab - sample.pts_b, axis=1)
    e_ba = np.linalg.norm(flow_ba - sample.pts_a, axis=1)
    return np.concatenate([e_ab, e_ba])


@torch.no_grad()
def evaluate_pck(
    model: CoarseNet,
    samples: list[PairSample],
    features,
    impl: str = "dense",
    k: int = 3,
    radius: int = 1,
    batch_size: int = 4,
) -> dict:
    """PCK@8/16/32 px (original resolution) of the coarse flow on ``samples`` (whole grids) with the
    dense filter or the sparse one (``k``, ``radius``). ``features(views)`` returns padded features
    and masks (cached or computed)."""
    model.eval()
    errors = []
    for i in range(0, len(samples), batch_size):
        chunk = samples[i : i + batch_size]
        feat_a, mask_a = features([s.a for s in chunk])
        feat_b, mask_b = features([s.b for s in chunk])
        out = model(feat_a, feat_b, mask_a, mask_b) if impl == "dense" else None
        for n, s in enumerate(chunk):
            ga, gb = s.a.geometry, s.b.geometry
            crop = (
                n,
                slice(0, ga.grid_height),
                slice(0, ga.grid_width),
                slice(0, gb.grid_height),
                slice(0, gb.grid_width),
            )
            if impl == "dense":
                na, nb = ga.grid_height * ga.grid_width, gb.grid_height * gb.grid_width
                ab = out["s_ab"][crop].reshape(na, nb).argmax(1).numpy()
                ba = out["s_ba"][crop].reshape(na, nb).argmax(0).numpy()
            else:
                fa = feat_a[n, :, : ga.grid_height, : ga.grid_width]
                m = model.match(
                    fa,
                    feat_b[n, :, : gb.grid_height, : gb.grid_width],
                    impl="sparse",
                    k=k,
                    radius=radius,
                )
                ab, ba = m.ab, m.ba
            errors.append(pck_errors(ab, ba, s))
    e = np.concatenate(errors) if errors else np.zeros(0)
    return {
        f"pck{t}": float((e < t).mean()) if len(e) else float("nan") for t in PCK_THRESHOLDS
    } | {"n_points": int(len(e))}


# ----------------------------------------------------------------------------------------- trainer
class Trainer:
    def __init__(self, out_dir: Path, conf: dict | None = None):
        self.conf = c = merge_conf(default_conf, conf, "training")
        if c["supervision"] not in ("image", "epipolar", "points"):
            raise ValueError(
                f"supervision must be image, epipolar or points, got {c['supervision']!r}"
            )
        if c["impl"] not in ("dense", "sparse"):
            raise ValueError(f"impl must be 'dense' or 'sparse', got {c['impl']!r}")
        if c["impl"] == "sparse" and c["supervision"] == "points":
            raise ValueError(
                "point supervision trains the dense filter only: use impl 'dense' (--impl dense)"
            )
        workspace = Workspace.claim(out_dir, "train", flag="--out")
        workspace.record(*WRITES)
        self.out = workspace.path
        torch.manual_seed(c["seed"])
        model_conf = {**c["model"], "filter": True}
        model_conf.setdefault(
            "backbone", c["data"].get("backbone", CoarseTrainData.default_conf["backbone"])
        )
        self.model = CoarseNet(model_conf)
        self.data = CoarseTrainData({**c["data"], "backbone": self.model.conf["backbone"]})
        for p in self.model.backbone.parameters():
            p.requires_grad_(c["finetune_backbone"])
        groups = [{"params": list(self.model.filter.parameters()), "lr": c["lr"]}]
        if c["finetune_backbone"]:
            groups.append(
                {"params": list(self.model.backbone.parameters()), "lr": c["backbone_lr"]}
            )
        self.optimizer = torch.optim.Adam(groups)
        self.rng = np.random.default_rng(c["seed"])
        self.iteration = 0
        self.history: list[dict] = []
        self.val_history: list[dict] = []
        self.train_seconds = 0.0
        if not self.resume() and c["init"]:
            self.load_init(Path(c["init"]))
        if not c["finetune_backbone"]:
            self.data.build_cache(_NormalizedBackbone(self.model))
            self.data.cache.load_all(self.data.views)

    # ------------------------------------------------------------------ state
    @property
    def checkpoint_path(self) -> Path:
        return self.out / "checkpoint.pt"

    def state_dict(self) -> dict:
        model_state = (
            self.model.filter.state_dict()
            if not self.conf["finetune_backbone"]
            else self.model.state_dict()
        )
        return {
            "model": model_state,
            "optimizer": self.optimizer.state_dict(),
            "iteration": self.iteration,
            "rng": self.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "history": self.history,
            "val_history": self.val_history,
            "train_seconds": self.train_seconds,
            "conf": _jsonable(self.conf),
        }

    def save_checkpoint(self) -> None:
        """checkpoint.pt (atomic), history.json, and the current filter as
        coarse_filter.safetensors."""
        tmp = self.checkpoint_path.with_suffix(".tmp")
        torch.save(self.state_dict(), tmp)
        os.replace(tmp, self.checkpoint_path)
        self.export(self.out / "coarse_filter.safetensors")
        (self.out / "history.json").write_text(
            json.dumps(
                {
                    "train": self.history,
                    "val": self.val_history,
                    "train_seconds": self.train_seconds,
                },
                indent=1,
            )
        )

    def resume(self) -> bool:
        if not self.checkpoint_path.exists():
            return False
        state = torch.load(self.checkpoint_path, map_location="cpu", weights_only=True)
        for key in ("supervision", "batch_size", "seed", "finetune_backbone", "impl"):
            if state["conf"].get(key) != self.conf[key]:
                raise ValueError(
                    f"{self.checkpoint_path} was written with {key}={state['conf'].get(key)!r}, "
                    f"not {self.conf[key]!r}: use another --out or the same options"
                )
        if self.conf["finetune_backbone"]:
            self.model.load_state_dict(state["model"])
        else:
            self.model.filter.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        self.iteration = state["iteration"]
        self.history, self.val_history = state["history"], state["val_history"]
        self.train_seconds = state.get("train_seconds", 0.0)
        logger.info("Resumed %s at iteration %d.", self.checkpoint_path, self.iteration)
        return True

    def load_init(self, path: Path) -> None:
        """Start from a frozen-stage checkpoint.pt or an exported filter (fine-tuning stage)."""
        if path.suffix == ".safetensors":
            load_filter_weights(self.model, path)
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)["model"]
            if any(k.startswith("filter.") for k in state):
                self.model.load_state_dict(state)
            else:
                self.model.filter.load_state_dict(state)
        logger.info("Initialised from %s.", path)

    # ------------------------------------------------------------------ steps
    def _features(self, views: list) -> tuple[torch.Tensor, torch.Tensor]:
        """Padded features of the views (cropped to their windows) and their validity masks."""
        if not self.conf["finetune_backbone"]:
            return stack_padded([v.crop(self.data.features(v.key)) for v in views])
        feats = []
        for v in views:
            x = torch.from_numpy(self.data.render(v.key)).permute(2, 0, 1).float()[None]
            feats.append(v.crop(self.model.extract_features(self.model.normalize(x))[0]))
        return stack_padded(feats)

    def n_negative(self) -> int:
        if self.conf["negatives"] is not None:
            return int(self.conf["negatives"])
        return 0 if self.conf["supervision"] == "points" else self.conf["batch_size"] // 2

    def step(self) -> dict:
        c = self.conf
        self.model.filter.train()
        self.model.backbone.eval()  # BatchNorm statistics frozen (also when fine-tuning)
        samples = self.data.sample_batch(self.rng, c["batch_size"], self.n_negative())
        loss, stats = self.loss(samples)
        # from the iteration: resume-safe
        decay = 0.1 ** sum(self.iteration >= s for s in c["lr_steps"])
        for group, base in zip(self.optimizer.param_groups, (c["lr"], c["backbone_lr"])):
            group["lr"] = base * decay
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return {"loss": float(loss.detach()), **stats}

    def loss(self, samples: list[PairSample]) -> tuple[torch.Tensor, dict]:
        """The training loss of a batch (paper eq. 2) and its statistics, on the conf's filter
        path."""
        c = self.conf
        if c["impl"] == "sparse":
            return self._sparse_loss(samples)
        batch = collate(samples, self.data, with_features=False)
        feat_a, mask_a = self._features([s.a for s in samples])
        feat_b, mask_b = self._features([s.b for s in samples])
        batch.update(mask_a=mask_a, mask_b=mask_b)
        out = self.model(feat_a, feat_b, mask_a, mask_b)
        return coarse_loss(
            c["supervision"], out["s_ab"], out["s_ba"], batch, lam=float(self.model.spec.stride)
        )

    def _sparse_loss(self, samples: list[PairSample]) -> tuple[torch.Tensor, dict]:
        """Image or epipolar loss (eq. 3, 5) on the sparse filter the CPU path runs
        (``sparse_volume`` with the pipeline's k and radius; entries outside the support read
        as 0 in the softmax), whole grids, one pair at a time; the per-cell max s and argmax are
        padded into a batch for the loss."""
        c = self.conf
        rows = {key: [] for key in ("best_ab", "idx_ab", "best_ba", "idx_ba", "xa", "xb")}
        for s in samples:
            fa, fb = self._features([s.a])[0][0], self._features([s.b])[0][0]
            ha, wa, hb, wb = *fa.shape[1:], *fb.shape[1:]
            a, b, v = self.model.sparse_volume(
                correlation(fa[None], fb[None])[0], c["sparse_k"], c["sparse_radius"]
            )
            for key, val in zip(("idx_ab", "best_ab"), sparse_best(a, b, v, ha * wa, hb * wb)):
                rows[key].append(val)
            for key, val in zip(("idx_ba", "best_ba"), sparse_best(b, a, v, hb * wb, ha * wa)):
                rows[key].append(val)
            rows["xa"].append(torch.from_numpy(np.ascontiguousarray(s.a.crop_xy()).reshape(-1, 2)))
            rows["xb"].append(torch.from_numpy(np.ascontiguousarray(s.b.crop_xy()).reshape(-1, 2)))
        pad = {
            key: torch.nn.utils.rnn.pad_sequence(val, batch_first=True) for key, val in rows.items()
        }
        ma = torch.nn.utils.rnn.pad_sequence(
            [torch.ones(len(x), dtype=torch.bool) for x in rows["xa"]], batch_first=True
        )
        mb = torch.nn.utils.rnn.pad_sequence(
            [torch.ones(len(x), dtype=torch.bool) for x in rows["xb"]], batch_first=True
        )
        positive = torch.tensor([s.positive for s in samples])
        if c["supervision"] == "image":
            return image_loss_from_best(pad["best_ab"], pad["best_ba"], positive, ma, mb)
        F = torch.from_numpy(np.stack([s.F for s in samples]))
        return epipolar_loss_from_best(
            pad["best_ab"],
            pad["idx_ab"],
            pad["best_ba"],
            pad["idx_ba"],
            positive,
            F,
            pad["xa"],
            pad["xb"],
            ma,
            mb,
            lam=float(self.model.spec.stride),
        )

    def validate(self) -> dict:
        t = time.time()
        c = self.conf
        res = evaluate_pck(
            self.model,
            self.data.val_samples,
            self._features,
            c["impl"],
            c["sparse_k"],
            c["sparse_radius"],
        )
        res = {"iteration": self.iteration, **res, "seconds": round(time.time() - t, 1)}
        self.val_history.append(res)
        logger.info(
            "Validation at %d: PCK@8/16/32 = %.1f / %.1f / %.1f %% (%d points, %.0f s)",
            self.iteration,
            100 * res["pck8"],
            100 * res["pck16"],
            100 * res["pck32"],
            res["n_points"],
            res["seconds"],
        )
        return res

    def train(self) -> bool:
        """Run until ``iterations`` or ``max_minutes``; returns True when training is complete."""
        c = self.conf
        start = time.time()
        if not self.val_history:
            self.validate()
        last_log = time.time()
        while self.iteration < c["iterations"]:
            t = time.time()
            stats = self.step()
            self.iteration += 1
            dt = time.time() - t
            self.train_seconds += dt
            self.history.append(
                {
                    "iteration": self.iteration,
                    "seconds": round(dt, 3),
                    **{k: _round(v) for k, v in stats.items()},
                }
            )
            if self.iteration % c["log_every"] == 0 or self.iteration == c["iterations"]:
                recent = self.history[-c["log_every"] :]
                logger.info(
                    "it %d  loss %.4f  %s  %.2f s/it",
                    self.iteration,
                    np.mean([h["loss"] for h in recent]),
                    "  ".join(
                        f"{k} {np.nanmean([h[k] for h in recent]):.3f}"
                        for k in stats
                        if k != "loss"
                    ),
                    (time.time() - last_log) / len(recent),
                )
                last_log = time.time()
            if self.iteration % c["val_every"] == 0 or self.iteration == c["iterations"]:
                self.validate()
                self.plot()
            if self.iteration % c["checkpoint_every"] == 0:
                self.save_checkpoint()
            if c["max_minutes"] is not None and time.time() - start > 60 * c["max_minutes"]:
                break
        self.save_checkpoint()
        self.plot()
        done = self.iteration >= c["iterations"]
        if not done:
            logger.info(
                "Stopped at iteration %d/%d after %.1f min: run the same command to resume.",
                self.iteration,
                c["iterations"],
                (time.time() - start) / 60,
            )
        return done

    # ------------------------------------------------------------------ outputs
    def export(self, path: Path) -> Path:
        """Filter weights (written atomically) + config (backbone, supervision, data scenes,
        iterations, seed) as safetensors."""
        meta = {
            "supervision": self.conf["supervision"],
            "iterations": self.iteration,
            "seed": self.conf["seed"],
            "batch_size": self.conf["batch_size"],
            "lr": self.conf["lr"],
            "lr_steps": list(self.conf["lr_steps"]),
            "finetuned_backbone": self.conf["finetune_backbone"],
            "train_scenes": self.data.train_scenes,
            "val_scenes": self.data.val_scenes,
            "data_conf": _jsonable(self.data.conf),
            "train_seconds": round(self.train_seconds),
            "val": self.val_history[-1] if self.val_history else None,
        }
        tmp = Path(path).with_name(Path(path).stem + ".tmp.safetensors")
        save_trained(
            self.model,
            tmp,
            meta,
            resize_max=self.data.conf["resolution"],
            backbone=self.conf["finetune_backbone"],
        )
        os.replace(tmp, path)
        return Path(path)

    def plot(self) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        if not self.history:
            return
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        it = np.array([h["iteration"] for h in self.history])
        loss = np.array([h["loss"] for h in self.history])
        w = max(1, min(50, len(loss) // 10))
        axes[0].plot(it, loss, alpha=0.3, lw=0.8, label="loss")
        if len(loss) >= w:
            axes[0].plot(
                it[w - 1 :],
                np.convolve(loss, np.ones(w) / w, "valid"),
                lw=1.5,
                label=f"mean of {w}",
            )
        for key in ("epi_inlier_frac", "max_pos", "max_neg", "gt_prob"):
            if key in self.history[-1]:
                axes[0].plot(
                    it, [h.get(key, np.nan) for h in self.history], lw=0.6, alpha=0.6, label=key
                )
        axes[0].set_xlabel("iteration")
        axes[0].set_title(f"{self.conf['supervision']} supervision")
        axes[0].legend(fontsize=7)
        vi = [v["iteration"] for v in self.val_history]
        for t in PCK_THRESHOLDS:
            axes[1].plot(
                vi, [100 * v[f"pck{t}"] for v in self.val_history], "o-", label=f"PCK@{t}px"
            )
        axes[1].set_xlabel("iteration")
        axes[1].set_ylabel("% of GT points (held-out scenes)")
        axes[1].legend(fontsize=7)
        axes[1].grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(self.out / "curves.png", dpi=100)
        plt.close(fig)


class _NormalizedBackbone(torch.nn.Module):
    """The frozen backbone as the cache sees it: RGB → normalised input → L2-normalised features."""

    def __init__(self, model: CoarseNet):
        super().__init__()
        self.model = model

    @staticmethod
    def normalize(x):
        return x

    def forward(self, x):
        return self.model.extract_features(self.model.normalize(x))


def save_trained(
    model: CoarseNet, path: Path, meta: dict, resize_max: int, backbone: bool = False
) -> Path:
    """Export the filter (and a fine-tuned backbone) with the coarse package's format (safetensors +
    checked config)."""
    save_filter_weights(
        model, path, resize_max=resize_max, training=_jsonable(meta), backbone=backbone
    )
    logger.debug("Exported %s.", path)
    return Path(path)


def _round(v):
    return round(v, 5) if isinstance(v, float) and np.isfinite(v) else v


def _jsonable(obj):
    return json.loads(
        json.dumps(obj, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    )
