"""Pretraining the VGG16 trunk on place classification across domain-randomised SimCampus worlds.

The ImageNet stand-in of the built-in path. The paper fine-tunes fc6–fc8 of an ImageNet VGG16 with the
convolutions frozen (§IV); SimCampus has no ImageNet, so the trunk is pretrained here on worlds other than the
evaluation campus, with a pretext that needs what cross-season recognition needs: *which place is this*, when
every object's colour, texture, the sky and the light are drawn anew for every frame. The class of a frame is its
grid cell and 90° heading bin in its world (``placejax.pretrain._data``), so only geometry tells classes apart.

What is specific here is the data and the config; the step, schedule, optimiser, batch order and orbax
checkpoints are ``placejax.training``'s, with the default ``classification_loss``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from placejax import config as _config
from placejax import training
from placejax.data import FrameSource, simcampus, train_dataset
from placejax.depth import PRESETS as DEPTH_PRESETS
from placejax.models import VGG16, he_init, imagenet_normalise
from placejax.pretrain import _data
from placejax.pretrain._data import (
    HHA_DEPTH_PERTURBED,
    HHA_DEPTH_TRAINED,
    NETWORK_SHIFTS,
    NETWORK_SKY_FROM_M,
    TRUNK_MODALITIES,
    check_hha_depth,
    place_frames,
)

# Bumped whenever the recipe changes in a way the config does not show.
_RECIPE_VERSION = 1


@dataclasses.dataclass(frozen=True)
class PretrainConfig:
    """Everything that determines a pretrained trunk; :meth:`fingerprint` (a hash of the fields that change the
    weights) names its folder. Each field's default, help and checks are written once, below; the rules that tie
    fields together are in ``__post_init__``."""

    image_size: int = _config.setting(
        64, "square input, pixels (a multiple of 32, ≥ 64 so that the trunk leaves ≥ 2 × 2 cells before fc6)"
    )
    width: float = _config.setting(0.125, "VGG16 channel multiplier (0.125 = the built-in path's net)")
    n_worlds: int = _config.setting(
        8, "pretraining worlds (seeds placejax.pretrain.data.place_world_seeds, never the evaluation campus)"
    )
    frames_per_world: int = _config.setting(384, "frames rendered per world, each with its own random look")
    # 5: coarser than the paper's 10 × 10, so that a class has several views (10 × 10 × 4 gives ~1.5 a class).
    grid: int = _config.setting(5, "place cells per axis of a world's grid")
    headings: int = _config.setting(4, "heading bins per cell (4: 90° bins, so a class is a view)")
    batch_size: int = _config.setting(32, "global batch")
    steps: int = _config.setting(2500, "optimiser steps")
    learning_rate: float = _config.setting(5e-4, "peak AdamW learning rate (linear warm-up, cosine decay)")
    warmup_steps: int = _config.setting(100, "linear warm-up steps")
    weight_decay: float = _config.setting(1e-4, "AdamW decoupled weight decay")
    dropout: float = _config.setting(0.0, "dropout after fc6 and fc7")
    place_weight: float = _config.setting(1.0, "weight of the place-classification term (PretextObjective)")
    pair_weight: float = _config.setting(1.0, "weight of the cross-look contrastive term")
    temperature: float = _config.setting(0.1, "InfoNCE temperature")
    seed: int = _config.setting(0, "worlds, poses, looks, data order and initialisation")
    checkpoint_every: int = _config.setting(250, "steps between checkpoints", affects_results=False)
    eval_seed: int = _config.setting(
        99, "seed of the held-out validation worlds (heldout_frames); differs from seed", affects_results=False
    )
    eval_frames: int = _config.setting(256, "held-out views per validation world", affects_results=False)
    world_seed: int = _config.setting(0, "the evaluation campus (never rendered here)")
    modality: str = _config.setting(
        "rgb",
        "what the trunk reads: 'rgb' (two random looks of each view) or 'hha' (HHA of each view's depth in two "
        "seasons' geometry; placejax.pretrain.data.place_frames)",
        omitted_at="rgb",
    )
    hha_depth: str = _config.setting(
        HHA_DEPTH_PERTURBED,
        "modality='hha': 'perturbed' (rendered depth through pretrain.data.perturb_depth) or 'trained:<preset>' "
        "(that depth network's predictions, with the experiment's default views and sky step)",
        omitted_at=HHA_DEPTH_PERTURBED,
    )
    hha_depth_shifts: tuple[int, ...] = _config.setting(
        NETWORK_SHIFTS,
        "hha_depth='trained:…': sideways shifts (px) whose views are averaged with the image and its mirror "
        "(() = the image and its mirror only, the experiment's default depth stage)",
        omitted_at=NETWORK_SHIFTS,
    )
    hha_sky_from_m: float = _config.setting(
        NETWORK_SKY_FROM_M,
        "hha_depth='trained:…': predictions from this distance (m) on are handed over as sky (the experiment's "
        "depth.far_as_sky_m)",
        omitted_at=NETWORK_SKY_FROM_M,
    )

    def __post_init__(self):
        shifts = self.hha_depth_shifts
        if isinstance(shifts, list):
            object.__setattr__(self, "hha_depth_shifts", tuple(shifts))
        _config.check(
            self,
            positive_int=(
                "image_size",
                "n_worlds",
                "frames_per_world",
                "grid",
                "headings",
                "batch_size",
                "steps",
                "checkpoint_every",
                "eval_frames",
            ),
            nonnegative_int=("warmup_steps", "seed", "eval_seed", "world_seed"),
            positive=("learning_rate", "width", "temperature", "hha_sky_from_m"),
            nonnegative=("weight_decay", "place_weight", "pair_weight"),
            unit_interval=("dropout",),
            choices={"modality": TRUNK_MODALITIES},
            string=("hha_depth",),
        )
        check_hha_depth(self.hha_depth)
        errors = []
        if self.image_size % 32:
            errors.append(f"image_size={self.image_size}: expected a multiple of 32")
        if self.n_worlds * self.frames_per_world < self.batch_size:
            errors.append("n_worlds · frames_per_world must be at least batch_size")
        if self.hha_depth != HHA_DEPTH_PERTURBED and self.modality != "hha":
            errors.append(f"hha_depth={self.hha_depth!r} needs modality='hha' (got {self.modality!r})")
        shifts = self.hha_depth_shifts
        pixels = isinstance(shifts, tuple) and all(isinstance(k, int) and not isinstance(k, bool) for k in shifts)
        if not (pixels and all(k > 0 for k in shifts)):
            errors.append(
                f"hha_depth_shifts={_config.shown(shifts)}: expected a tuple of positive pixel counts, e.g. (2, 4)"
            )
        depth_stage = (self.hha_depth_shifts, self.hha_sky_from_m) != (NETWORK_SHIFTS, NETWORK_SKY_FROM_M)
        if depth_stage and self.hha_depth == HHA_DEPTH_PERTURBED:
            errors.append("hha_depth_shifts and hha_sky_from_m need hha_depth='trained:<preset>'")
        if self.eval_seed == self.seed:
            errors.append("eval_seed must differ from seed: validation worlds must be held out")
        if errors:
            raise _config.ConfigError(*errors)

    def hha_depth_network(self) -> str | None:
        """``"<depth preset>-<its config fingerprint>"`` of the network whose predictions the HHA views are made of
        (``hha_depth="trained:<preset>"``), None on perturbed depth: what an exported trunk records."""
        if self.hha_depth == HHA_DEPTH_PERTURBED:
            return None

        preset = self.hha_depth.removeprefix(HHA_DEPTH_TRAINED)
        return f"{preset}-{DEPTH_PRESETS[preset].fingerprint()}"

    def fingerprint(self) -> str:
        """12 hex digits naming the trunk these settings train: the hash of the fields that change its weights
        (``placejax.config.results_fields``; RGB runs and runs on perturbed depth keep the hash they had before
        ``modality`` and ``hha_depth`` existed), the recipe's version and, on a depth network's predictions, that
        network's recipe (so that a change of it makes a new run, not a stale cache hit)."""
        fields = _config.results_fields(self)
        if self.hha_depth != HHA_DEPTH_PERTURBED:
            fields["hha_depth_network"] = DEPTH_PRESETS[self.hha_depth.removeprefix(HHA_DEPTH_TRAINED)].fingerprint()
        fields["recipe_version"] = _RECIPE_VERSION
        return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:12]


PRESETS = {
    # Seconds on one core: the tests' preset (a pretext that visibly learns, not a useful trunk).
    "smoke": PretrainConfig(
        image_size=64,
        width=0.0625,
        n_worlds=1,
        frames_per_world=64,
        grid=3,
        headings=2,
        batch_size=16,
        steps=150,
        learning_rate=1e-3,
        warmup_steps=15,
        checkpoint_every=75,
        eval_frames=32,
    ),
    # The shipped trunk (placejax/pretrain/weights): ~45 min on 2 shared CPU cores.
    "default": PretrainConfig(),
}
"""The trunk pretraining presets by name (:class:`PretrainConfig` each): ``smoke`` for the tests, ``default`` the
shipped trunk's."""


def training_frames(cfg: PretrainConfig, progress: bool = True) -> dict[str, np.ndarray]:
    """The rendered, place-labelled pretraining frames; labels renumbered densely ``0..C−1``."""

    s = cfg.image_size
    f = place_frames(
        cfg.seed,
        cfg.frames_per_world,
        (s, s),
        n_worlds=cfg.n_worlds,
        grid=cfg.grid,
        headings=cfg.headings,
        exclude_world_seeds=(cfg.world_seed,),
        modality=cfg.modality,
        hha_depth=cfg.hha_depth,
        hha_depth_shifts=cfg.hha_depth_shifts,
        hha_sky_from_m=cfg.hha_sky_from_m,
        progress=progress,
    )
    _, f["label"] = np.unique(f["label"], return_inverse=True)
    f["label"] = f["label"].astype(np.int32)
    return f


def num_classes(cfg: PretrainConfig) -> int:
    """Occupied place classes of the pretraining set (computed from the poses alone, no rendering)."""

    seeds = _data.place_world_seeds(cfg.seed, cfg.n_worlds, (cfg.world_seed,))
    labels = []
    for w, ws in enumerate(seeds):
        rng = np.random.default_rng([cfg.seed, 0x91ACE, w])
        poses = simcampus.random_poses(simcampus.make_world(ws), rng, cfg.frames_per_world)
        labels.append(
            w * cfg.grid**2 * cfg.headings + _data.place_labels(poses, _data.path_box(ws), cfg.grid, cfg.headings)
        )
    return int(np.unique(np.concatenate(labels)).size)


def model(cfg: PretrainConfig, n_classes: int) -> VGG16:
    return VGG16(num_classes=n_classes, width=cfg.width, dropout_rate=cfg.dropout)


def init_params(cfg: PretrainConfig, n_classes: int) -> dict[str, Any]:
    """He-initialised VGG16 parameters (``placejax.models.he_init``), as the built-in from-scratch path."""
    s = cfg.image_size
    key = jax.random.key(cfg.seed)
    params = model(cfg, n_classes).init(key, jnp.zeros((1, s, s, 3)))["params"]
    return he_init(params, jax.random.fold_in(key, 1))


@dataclasses.dataclass(frozen=True)
class PretextObjective:
    """The pretext's objective for ``placejax.training.train_step``: place classification of both looks of each
    view plus a cross-look contrastive term.

    ``batch``: ``x``, ``x2`` normalised ``(B, H, W, 3)`` — the same views in two versions (independent random
    looks, or HHA in two seasons' geometry) —,
    ``label`` int32 ``(B,)`` place classes, ``valid`` bool ``(B,)``. Loss::

        place_weight · CE(fc8(x), label) + place_weight · CE(fc8(x2), label)  (averaged)
        + pair_weight · InfoNCE(fc7(x), fc7(x2))

    InfoNCE (van den Oord et al. 2018; SimCLR's symmetric form): cosine similarities of the L2-normalised fc7
    embeddings over ``temperature``; each view's other look is its positive, the batch's other views negatives.
    It asks for exactly the appearance invariance cross-season recognition needs, and — unlike the place
    classes, of which a world has hundreds — it needs no frames per class. A frozen dataclass: hashable, so
    each configuration compiles one step.
    """

    place_weight: float = 1.0
    pair_weight: float = 1.0
    temperature: float = 0.1

    @classmethod
    def of(cls, cfg: PretrainConfig) -> PretextObjective:
        return cls(cfg.place_weight, cfg.pair_weight, cfg.temperature)

    def __call__(self, state, params, batch, key):
        b = batch["x"].shape[0]
        x = jnp.concatenate([batch["x"], batch["x2"]])
        logits, feats = state.apply_fn({"params": params}, x, train=True, rngs={"dropout": key})
        logits = logits.astype(jnp.float32)
        labels = jnp.concatenate([batch["label"], batch["label"]])
        valid = jnp.concatenate([batch["valid"], batch["valid"]]) & (labels >= 0)
        w = valid.astype(jnp.float32)
        n = jnp.maximum(w.sum(), 1.0)
        ce = optax.softmax_cross_entropy_with_integer_labels(logits, jnp.maximum(labels, 0))
        place = (ce * w).sum() / n
        acc = ((jnp.argmax(logits, -1) == labels) * w).sum() / n
        z = feats["fc7"].astype(jnp.float32)
        z = z / jnp.sqrt(jnp.sum(z * z, -1, keepdims=True) + 1e-12)
        za, zb = z[:b], z[b:]
        sim = za @ zb.T / self.temperature
        vb = batch["valid"]
        # Padding rows are neither anchors nor negatives.
        sim = jnp.where(vb[None, :] & vb[:, None] | jnp.eye(b, dtype=bool), sim, -1e9)
        target = jnp.arange(b)
        nce = 0.5 * (
            optax.softmax_cross_entropy_with_integer_labels(sim, target)
            + optax.softmax_cross_entropy_with_integer_labels(sim.T, target)
        )
        wb = vb.astype(jnp.float32)
        nb = jnp.maximum(wb.sum(), 1.0)
        pair = (nce * wb).sum() / nb
        pair_acc = ((jnp.argmax(sim, -1) == target) * wb).sum() / nb
        loss = self.place_weight * place + self.pair_weight * pair
        metrics = {"loss": loss, "place_loss": place, "accuracy": acc, "pair_loss": pair, "pair_accuracy": pair_acc}
        return loss, (metrics, None)


def _optimizer(cfg: PretrainConfig):
    return training.make_optimizer("adamw", weight_decay=cfg.weight_decay, clip_norm=1.0)


def _prepare(batch: dict) -> dict[str, np.ndarray]:
    return {
        "x": imagenet_normalise(batch["image"]),
        "x2": imagenet_normalise(batch["image2"]),
        "label": batch["label"],
        "valid": batch["valid"],
    }


def _checkpoint_dir(workdir: Path) -> Path:
    return Path(workdir).absolute() / "checkpoints"


def train_trunk(
    cfg: PretrainConfig,
    workdir: str | os.PathLike,
    *,
    frames: dict[str, np.ndarray] | None = None,
    stop_after: int | None = None,
    progress: bool = True,
) -> training.TrainState:
    """Trains (or resumes) the pretext in ``workdir``; checkpoints in ``workdir/checkpoints``.

    Args:
        cfg: the run's configuration.
        workdir: the run's folder (created).
        frames: the rendered training frames (default: rendered from ``cfg``; pass them to reuse a rendering).
        stop_after: stop after this step (after a checkpoint), as an interruption would.
        progress: progress bars.

    Returns:
        The final train state.
    """

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    n_classes = num_classes(cfg)

    def batches(frames=frames):  # rendered only when steps remain
        frames = training_frames(cfg, progress=progress) if frames is None else frames
        epochs = math.ceil(cfg.steps * cfg.batch_size / len(frames["label"]))
        source = FrameSource(frames["image"], frames["label"], extras={"image2": frames["image2"]})
        return train_dataset(source, batch_size=cfg.batch_size, seed=cfg.seed, num_epochs=epochs)

    return training.train(
        training.apply_fn(model(cfg, n_classes)),
        init_params(cfg, n_classes),
        _optimizer(cfg),
        batches,
        key=jax.random.key(cfg.seed + 1),
        mesh=training.data_mesh(),
        prepare=_prepare,
        learning_rate=cfg.learning_rate,
        warmup_steps=cfg.warmup_steps,
        num_steps=cfg.steps,
        objective=PretextObjective.of(cfg),
        checkpoint_dir=_checkpoint_dir(workdir),
        save_every=cfg.checkpoint_every,
        stop_after=stop_after,
        desc="trunk pretraining",
        progress=progress,
    )


def load_trained(workdir: str | os.PathLike, cfg: PretrainConfig) -> dict[str, Any]:
    """The parameters of a finished run in ``workdir`` (its final checkpoint)."""
    n_classes = num_classes(cfg)
    with training.Checkpointer(_checkpoint_dir(Path(workdir))) as ck:
        step = ck.latest_step()
        if step is None or step < cfg.steps:
            raise FileNotFoundError(f"no finished pretraining run in {workdir} (latest step {step} of {cfg.steps})")
        template = training.create_state(
            training.apply_fn(model(cfg, n_classes)),
            init_params(cfg, n_classes),
            _optimizer(cfg),
            learning_rate=cfg.learning_rate,
            total_steps=cfg.steps,
        )
        state = ck.restore(template, step)
    return jax.device_get(state.params)
