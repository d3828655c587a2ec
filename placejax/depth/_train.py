"""Training MidasSmall with the scale- and shift-invariant objective, data-parallel, checkpointed and resumable.

The data are SimCampus's domain-randomised depth-training worlds (other seeds than the evaluation campus, random
appearance per object and frame), the analogue of MiDaS being trained on other datasets and used frozen.
The training step is a pure function of (state, batch, key), jitted once per model and optimiser; the batch axis
is sharded over all local devices with a `jax.sharding.Mesh`, parameters are replicated, and XLA inserts the
gradient all-reduce — so 1 and N devices compute the same update (BatchNorm statistics are over the global batch).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
import tqdm
from flax import struct

from placejax.depth._inference import IMAGENET_MEAN, IMAGENET_STD
from placejax.depth._losses import midas_loss
from placejax.models import MidasSmall
from placejax.training import data_mesh, replicate, shard_batch


@dataclasses.dataclass(frozen=True)
class DepthTrainConfig:
    """Everything that determines a trained depth network (its hash names the run's folder).

    Attributes:
        image_size: square training resolution (multiple of 32).
        features: MidasSmall decoder width (64 = official).
        encoder_width: EfficientNet-Lite3 channel multiplier (1.0 = official).
        frames: depth-training frames rendered once and reused for every epoch.
        n_worlds: depth-training worlds (seeds other than the evaluation campus).
        batch_size: global batch (split over local devices; must be divisible by their number).
        steps: optimiser steps.
        learning_rate: peak AdamW learning rate (linear warm-up, cosine decay).
        warmup_steps: linear warm-up steps.
        weight_decay: AdamW weight decay.
        loss: ``"trimmed"`` (ssitrim) or ``"mse"`` (ssimse); plus the gradient-matching term.
        alpha: weight of the gradient-matching term (0.5 in the paper).
        trim: share of each image's largest residuals left out of the "trimmed" loss (MiDaS: 0.2, for noisy
            ground truth). Rendered depth is exact, and trimming then discards exactly the pixels the net gets
            most wrong — at CPU scale, every object above the horizon, which it learns to flatten into the sky.
        sky_in_loss: sky pixels enter the loss with inverse depth 0 (infinitely far), so the net must tell sky
            from objects; otherwise sky and pixels beyond ``max_depth_m`` are masked out.
        max_depth_m: with ``sky_in_loss=False``, pixels farther than this (and sky) are masked out of the loss.
        seed: data order, augmentation and initialisation.
        checkpoint_every: steps between checkpoints.
        eval_frames: evaluation-campus frames per season for the report.
        world_seed: the evaluation campus (never trained on).
    """

    image_size: int = 64
    features: int = 16
    encoder_width: float = 0.35
    frames: int = 2048
    n_worlds: int = 8
    batch_size: int = 16
    steps: int = 1200
    learning_rate: float = 2e-3
    warmup_steps: int = 50
    weight_decay: float = 1e-4
    loss: str = "trimmed"
    trim: float = 0.0
    sky_in_loss: bool = True
    alpha: float = 0.5
    max_depth_m: float = 80.0
    seed: int = 0
    checkpoint_every: int = 100
    eval_frames: int = 48
    world_seed: int = 0

    def __post_init__(self):
        if self.image_size % 32:
            raise ValueError(f"image_size must be a multiple of 32, got {self.image_size}")
        if self.loss not in ("trimmed", "mse"):
            raise ValueError(f"loss must be 'trimmed' or 'mse', got {self.loss!r}")
        if not 0.0 <= self.trim < 1.0:
            raise ValueError(f"trim must be in [0, 1), got {self.trim}")
        if self.steps < 1 or self.batch_size < 1 or self.frames < self.batch_size:
            raise ValueError("need steps >= 1, batch_size >= 1 and frames >= batch_size")

    def model(self) -> MidasSmall:
        return MidasSmall(features=self.features, encoder_width=self.encoder_width)

    def fingerprint(self) -> str:
        """Short hash of every field that changes the trained weights (not the report-only fields)."""
        fields = dataclasses.asdict(self)
        fields.pop("eval_frames")
        fields.pop("checkpoint_every")
        return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:12]


PRESETS = {
    # A few steps of a tiny network: the tests' preset.
    "smoke": DepthTrainConfig(
        image_size=32,
        features=8,
        encoder_width=0.25,
        frames=32,
        n_worlds=2,
        batch_size=8,
        steps=4,
        warmup_steps=1,
        checkpoint_every=2,
        eval_frames=4,
    ),
    # CPU-sized: 1200 steps, about 7 minutes on two cores; the default depth source of the experiment.
    "default": DepthTrainConfig(),
    # The official architecture at MiDaS's resolution: for an accelerator.
    "full": DepthTrainConfig(
        image_size=256,
        features=64,
        encoder_width=1.0,
        frames=20000,
        n_worlds=32,
        batch_size=32,
        steps=30000,
        learning_rate=1e-4,
        warmup_steps=1000,
        checkpoint_every=1000,
        eval_frames=200,
    ),
}


@struct.dataclass
class TrainState:
    step: jax.Array
    params: Any
    batch_stats: Any
    opt_state: Any


@functools.cache
def _optimizer(cfg: DepthTrainConfig) -> optax.GradientTransformation:
    # Cached per config so that repeated runs in one process reuse the compiled step (its static argument).
    schedule = optax.warmup_cosine_decay_schedule(
        0.0, cfg.learning_rate, cfg.warmup_steps, max(cfg.steps, cfg.warmup_steps + 1)
    )
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=cfg.weight_decay))


def normalise(rgb_uint8: jax.Array) -> jax.Array:
    """uint8 RGB → ImageNet-normalised float32 (MiDaS's input convention)."""
    x = rgb_uint8.astype(jnp.float32) / 255.0
    mean = jnp.asarray(IMAGENET_MEAN, jnp.float32).reshape(1, 1, 1, 3)
    std = jnp.asarray(IMAGENET_STD, jnp.float32).reshape(1, 1, 1, 3)
    return (x - mean) / std


def targets(
    depth_m: jax.Array, sky: jax.Array, max_depth_m: float, sky_in_loss: bool = False
) -> tuple[jax.Array, jax.Array]:
    """Inverse-depth targets and the loss mask.

    ``sky_in_loss=False``: sky, non-finite and too-far pixels are masked out. ``sky_in_loss=True``: sky is a
    target at inverse depth 0 and every finite positive depth counts (non-finite depth stays out).
    """
    finite = jnp.isfinite(depth_m) & (depth_m > 0)
    if sky_in_loss:
        mask = sky | finite
        hit = (~sky) & finite
    else:
        mask = hit = (~sky) & finite & (depth_m < max_depth_m)
    inv = jnp.where(hit, 1.0 / jnp.where(hit, depth_m, 1.0), 0.0)
    return inv, mask.astype(jnp.float32)


def init_state(cfg: DepthTrainConfig) -> TrainState:
    return _init_state(cfg)


@functools.partial(jax.jit, static_argnames=("cfg",))
def _init_state(cfg: DepthTrainConfig) -> TrainState:
    # Jitted: initialising the deep EfficientNet op by op costs more than compiling it.
    s = cfg.image_size
    variables = cfg.model().init(jax.random.key(cfg.seed), jnp.zeros((1, s, s, 3)), train=False)
    params = variables["params"]
    return TrainState(jnp.zeros((), jnp.int32), params, variables["batch_stats"], _optimizer(cfg).init(params))


@functools.partial(jax.jit, static_argnames=("cfg",), donate_argnums=0)
def train_step(state: TrainState, batch: dict[str, jax.Array], key: jax.Array, cfg: DepthTrainConfig):
    """One AdamW step on L = L_ssi + α·L_grad. ``batch``: ``rgb`` uint8 (B,H,W,3), ``depth`` (B,H,W), ``sky``."""
    model = cfg.model()
    x = normalise(batch["rgb"])
    inv, mask = targets(batch["depth"], batch["sky"], cfg.max_depth_m, cfg.sky_in_loss)
    # Horizontal flips: a scene and its mirror image have mirrored depth.
    flip = jax.random.bernoulli(key, 0.5, (x.shape[0],))
    x = jnp.where(flip[:, None, None, None], x[:, :, ::-1], x)
    inv = jnp.where(flip[:, None, None], inv[:, :, ::-1], inv)
    mask = jnp.where(flip[:, None, None], mask[:, :, ::-1], mask)

    def loss_fn(params):
        pred, updates = model.apply(
            {"params": params, "batch_stats": state.batch_stats}, x, train=True, mutable=["batch_stats"]
        )
        return midas_loss(pred, inv, mask, variant=cfg.loss, alpha=cfg.alpha, trim=cfg.trim), updates["batch_stats"]

    (loss, batch_stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
    updates, opt_state = _optimizer(cfg).update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    return TrainState(state.step + 1, params, batch_stats, opt_state), {"loss": loss}


def batch_indices(cfg: DepthTrainConfig, step: int) -> np.ndarray:
    """Frame indices of step ``step``: epochs are seeded permutations, so any step can be recomputed on resume."""
    per_epoch = cfg.frames // cfg.batch_size
    epoch, pos = divmod(step, per_epoch)
    perm = np.random.default_rng([cfg.seed, epoch]).permutation(cfg.frames)
    return perm[pos * cfg.batch_size : (pos + 1) * cfg.batch_size]


def training_frames(cfg: DepthTrainConfig, progress: bool = True) -> dict[str, np.ndarray]:
    """The rendered depth-training frames (deterministic given the config)."""
    from placejax.data import simcampus

    s = cfg.image_size
    return simcampus.depth_training_frames(
        cfg.seed,
        cfg.frames,
        (s, s),
        n_worlds=cfg.n_worlds,
        exclude_world_seeds=(cfg.world_seed,),
        progress=progress,
    )


def _checkpoint_manager(workdir: Path, cfg: DepthTrainConfig) -> ocp.CheckpointManager:
    return ocp.CheckpointManager(
        (workdir / "checkpoints").absolute(),
        options=ocp.CheckpointManagerOptions(max_to_keep=2, save_interval_steps=cfg.checkpoint_every),
    )


def train(
    cfg: DepthTrainConfig,
    workdir: str | os.PathLike,
    *,
    devices: list[jax.Device] | None = None,
    stop_after: int | None = None,
    progress: bool = True,
) -> TrainState:
    """Trains (or resumes training of) the depth network in ``workdir``.

    Checkpoints go to ``workdir/checkpoints`` every ``cfg.checkpoint_every`` steps and at the end; a rerun after a
    kill restores the latest one and continues with the same data order and keys, so it ends with the same
    parameters as an uninterrupted run.

    Args:
        cfg: the run's configuration.
        workdir: the run's folder (created).
        devices: devices of the data-parallel mesh (default: all local devices).
        stop_after: stop (after checkpointing) once this step is reached — to simulate an interruption.
        progress: show a progress bar.

    Returns:
        The final train state (replicated on the mesh).
    """
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    devices = list(jax.local_devices()) if devices is None else devices
    if cfg.batch_size % len(devices):
        raise ValueError(f"batch_size {cfg.batch_size} must be divisible by the {len(devices)} devices")
    mesh = data_mesh(devices)

    state = replicate(init_state(cfg), mesh)
    mngr = _checkpoint_manager(workdir, cfg)
    start = mngr.latest_step()
    if start is not None:
        state = mngr.restore(start, args=ocp.args.StandardRestore(state))
    start = int(state.step)
    if start >= cfg.steps:
        mngr.close()
        return state
    frames = training_frames(cfg, progress=progress)
    last = cfg.steps if stop_after is None else min(cfg.steps, stop_after)
    root_key = jax.random.key(cfg.seed + 1)
    with tqdm.trange(start, last, desc="depth training", unit="step", disable=not progress) as bar:
        for step in bar:
            idx = batch_indices(cfg, step)
            batch = shard_batch({k: frames[k][idx] for k in ("rgb", "depth", "sky")}, mesh)
            state, metrics = train_step(state, batch, jax.random.fold_in(root_key, step), cfg)
            if (step + 1) % cfg.checkpoint_every == 0 or step + 1 == last:
                mngr.save(step + 1, args=ocp.args.StandardSave(state))
                bar.set_postfix(loss=f"{float(metrics['loss']):.4f}")
    mngr.wait_until_finished()
    mngr.close()
    return state


@dataclasses.dataclass(frozen=True)
class TrainedDepth:
    """A trained, frozen depth network: relative inverse depth for RGB images of any size."""

    config: DepthTrainConfig
    variables: Any

    @property
    def model(self) -> MidasSmall:
        return self.config.model()

    @property
    def fingerprint(self) -> str:
        return self.config.fingerprint()

    def predict(self, images: np.ndarray) -> np.ndarray:
        """``(N, H, W, 3)`` uint8 RGB → float32 ``(N, H, W)`` relative inverse depth (bigger = closer).

        Images are resized to the training resolution (square), the prediction back to ``(H, W)``.
        """
        from placejax.depth._inference import predict

        return predict(self.variables, images, model=self.model, size=self.config.image_size, square=True)


def load_trained(workdir: str | os.PathLike, cfg: DepthTrainConfig) -> TrainedDepth:
    """The network of a finished run in ``workdir`` (its final checkpoint)."""
    mngr = _checkpoint_manager(Path(workdir), cfg)
    step = mngr.latest_step()
    if step is None or step < cfg.steps:
        raise FileNotFoundError(f"no finished depth-training run in {workdir} (latest step {step} of {cfg.steps})")
    state = mngr.restore(step, args=ocp.args.StandardRestore(init_state(cfg)))
    mngr.close()
    return TrainedDepth(cfg, {"params": state.params, "batch_stats": state.batch_stats})
