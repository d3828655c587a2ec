"""TrainState and the optimiser: optax SGD+momentum or AdamW, with a warmup + cosine schedule held as data.

The learning-rate schedule lives in the state (peak, warmup, total steps as arrays), not in the optax
transformation: ``tx`` is a static field of the state, so a schedule closed over each run's length would make
every network of another length a new jit cache entry (a recompile of the whole train step per network). Here
``tx`` depends only on the optimiser kind and its constants and is shared.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from flax.training import train_state


def lr_schedule(step: jax.Array, peak: jax.Array, warmup: jax.Array, total: jax.Array) -> jax.Array:
    """Linear warmup from 0 to ``peak`` over ``warmup`` steps, then cosine decay to 0 at ``total``."""
    step = step.astype(jnp.float32)
    warm = peak * step / jnp.maximum(warmup, 1.0)
    frac = jnp.clip((step - warmup) / jnp.maximum(total - warmup, 1.0), 0.0, 1.0)
    cosine = 0.5 * peak * (1.0 + jnp.cos(jnp.pi * frac))
    return jnp.where(step < warmup, warm, cosine)


class TrainState(train_state.TrainState):
    """``step``, ``params``, ``opt_state``, BatchNorm statistics and the schedule (``lr_peak``, ``warmup_steps``,
    ``total_steps``).

    ``apply_fn`` and ``tx`` are static (part of the jit cache key), everything else is data. ``batch_stats`` is
    ``None`` for models without BatchNorm (VGG16, the fusion MLP) and the ``"batch_stats"`` collection otherwise
    (MidasSmall), updated by the objective on every step.
    """

    batch_stats: Any = None
    lr_peak: jax.Array = struct.field(default_factory=lambda: jnp.float32(0.0))
    warmup_steps: jax.Array = struct.field(default_factory=lambda: jnp.float32(0.0))
    total_steps: jax.Array = struct.field(default_factory=lambda: jnp.float32(1.0))

    @property
    def learning_rate(self) -> jax.Array:
        return lr_schedule(self.step, self.lr_peak, self.warmup_steps, self.total_steps)

    @property
    def variables(self) -> dict[str, Any]:
        """The model's variables for ``apply_fn``: ``{"params", ["batch_stats"]}``."""
        if self.batch_stats is None:
            return {"params": self.params}
        return {"params": self.params, "batch_stats": self.batch_stats}

    def apply_gradients(self, *, grads, **kwargs):
        updates, opt_state = self.tx.update(grads, self.opt_state, self.params)
        # ``tx`` ends without a learning rate: scaling the final direction by −lr is exactly optax.sgd /
        # optax.adamw with this schedule (both apply the learning rate last).
        lr = self.learning_rate
        updates = jax.tree_util.tree_map(lambda u: (-lr * u).astype(u.dtype), updates)
        params = optax.apply_updates(self.params, updates)
        return self.replace(step=self.step + 1, params=params, opt_state=opt_state, **kwargs)


@functools.lru_cache(maxsize=16)
def make_optimizer(
    optimizer: str = "sgd", *, momentum: float = 0.9, weight_decay: float = 0.0, clip_norm: float | None = None
) -> optax.GradientTransformation:
    """The update direction of every network placejax trains (the learning rate is applied by the state).

    Args:
        optimizer: ``"sgd"`` (heavy-ball momentum, L2 added to the gradient, the VGG recipe) or ``"adamw"``
            (decoupled weight decay).
        momentum: SGD momentum.
        weight_decay: L2 coefficient (SGD) or decoupled decay (AdamW, scaled by the learning rate as in optax).
        clip_norm: clip the gradient to this global norm first (``None``: no clipping).

    Equal arguments return the same object, so states built from it share compiled steps.
    """
    clip = [] if clip_norm is None else [optax.clip_by_global_norm(clip_norm)]
    if optimizer == "sgd":
        return optax.chain(*clip, optax.add_decayed_weights(weight_decay), optax.trace(decay=momentum))
    if optimizer == "adamw":
        return optax.chain(*clip, optax.scale_by_adam(), optax.add_decayed_weights(weight_decay))
    raise ValueError(f"optimizer must be 'sgd' or 'adamw', got {optimizer!r}")


@functools.lru_cache(maxsize=64)
def apply_fn(model: nn.Module, method: str | None = None) -> Callable[..., Any]:
    """``model.apply`` (optionally with ``method=``) as one stable object per (model, method).

    The jitted steps treat ``state.apply_fn`` as static: a fresh ``functools.partial`` or bound method per
    network would retrace them for every network; equal modules share one function here, so they share one
    compiled step per input shape.
    """
    if method is None:
        return model.apply
    return functools.partial(model.apply, method=getattr(type(model), method))


def create_state(
    apply_fn: Callable[..., Any],
    params: Any,
    tx: optax.GradientTransformation,
    *,
    learning_rate: float,
    total_steps: int,
    warmup_steps: int = 0,
    batch_stats: Any = None,
) -> TrainState:
    """A fresh state at step 0.

    Args:
        apply_fn: from :func:`apply_fn` (stable per model).
        params: initial parameters (placed as given, e.g. already replicated on a mesh).
        tx: from :func:`make_optimizer`.
        learning_rate: peak learning rate.
        total_steps: steps of the whole run; the cosine reaches 0 there.
        warmup_steps: linear warmup steps.
        batch_stats: initial BatchNorm statistics (``None``: the model has none).
    """
    if total_steps < 1:
        raise ValueError(f"total_steps must be >= 1, got {total_steps}")
    return TrainState.create(
        apply_fn=apply_fn,
        params=params,
        tx=tx,
        lr_peak=jnp.float32(learning_rate),
        warmup_steps=jnp.float32(min(warmup_steps, total_steps - 1)),
        total_steps=jnp.float32(total_steps),
        batch_stats=batch_stats,
    )


def abstract_like(state: TrainState) -> TrainState:
    """Shape/dtype/sharding skeleton of a state, the restore target of a checkpoint."""

    def skeleton(x):
        if not hasattr(x, "shape"):  # a Python scalar (a fresh state's step) is restored as a 0-d array
            x = np.asarray(x)
        return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None))

    return jax.tree_util.tree_map(skeleton, state)
