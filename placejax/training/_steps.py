"""Pure, jitted train and predict steps for classifiers (VGG16, its head on cached features, the fusion MLP)."""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import optax

from placejax.training._state import TrainState


def _logits_and_features(out: Any) -> tuple[jax.Array, dict[str, jax.Array]]:
    if isinstance(out, tuple):
        return out[0], out[1]
    return out, {}


def _loss(params, state: TrainState, batch: dict[str, jax.Array], key: jax.Array):
    out = state.apply_fn({"params": params}, batch["x"], train=True, rngs={"dropout": key})
    logits, _ = _logits_and_features(out)
    labels = batch["label"]
    # Padding and "no class" rows (label −1) weigh 0, so a padded batch gives the mean over its real rows.
    weight = (batch["valid"] & (labels >= 0)).astype(jnp.float32)
    ce = optax.softmax_cross_entropy_with_integer_labels(logits.astype(jnp.float32), jnp.maximum(labels, 0))
    n = jnp.maximum(weight.sum(), 1.0)
    loss = (ce * weight).sum() / n
    acc = ((jnp.argmax(logits, -1) == labels) * weight).sum() / n
    return loss, {"loss": loss, "accuracy": acc}


@functools.partial(jax.jit, donate_argnums=0)
def train_step(state: TrainState, batch: dict[str, jax.Array], key: jax.Array) -> tuple[TrainState, dict]:
    """One SGD step on a batch; pure in (state, batch, key).

    Args:
        state: the TrainState (donated: its buffers are reused for the result).
        batch: ``x`` the model input ``(B, ...)`` (already normalised), ``label`` int32 ``(B,)`` (−1: ignore),
            ``valid`` bool ``(B,)`` (False for padding). Sharded along B over the mesh (or on one device).
        key: the run's base key; the step's dropout key is ``fold_in(key, state.step)``.

    Returns:
        ``(new_state, {"loss", "accuracy"})``, metrics averaged over the valid rows of the global batch.
    """
    step_key = jax.random.fold_in(key, state.step)
    grads, metrics = jax.grad(_loss, has_aux=True)(state.params, state, batch, step_key)
    return state.apply_gradients(grads=grads), metrics


@jax.jit
def predict_step(state: TrainState, x: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Deterministic forward pass: ``(logits (B, C), features)`` (features empty for models returning logits)."""
    return _logits_and_features(state.apply_fn({"params": state.params}, x, train=False))
