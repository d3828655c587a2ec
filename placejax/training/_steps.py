"""Pure, jitted train and predict steps; what is minimised is an *objective*, a static argument.

An objective is a hashable callable ``objective(state, params, batch, key) -> (loss, (metrics, batch_stats))``:
it runs ``state.apply_fn`` with ``params`` (the variable being differentiated), returns the scalar loss, a dict
of scalar metrics and the model's updated BatchNorm statistics (``None`` for models without them). Being static,
each objective (a module-level function, or a frozen dataclass whose fields are its constants) gets its own
compiled step. :func:`classification_loss` trains the place classifiers; ``placejax.depth`` defines the depth
network's objective.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax

from placejax.training._state import TrainState

Objective = Callable[[TrainState, Any, dict[str, jax.Array], jax.Array], tuple[jax.Array, tuple[dict, Any]]]
"""The type of a training objective: ``(state, params, batch, key) → (loss, (metrics, batch_stats))``, static in the
jitted step."""


def _logits_and_features(out: Any) -> tuple[jax.Array, dict[str, jax.Array]]:
    if isinstance(out, tuple):
        return out[0], out[1]
    return out, {}


def classification_loss(state: TrainState, params: Any, batch: dict[str, jax.Array], key: jax.Array):
    """Softmax cross-entropy of a classifier (``apply_fn`` returns logits or ``(logits, features)``).

    ``batch``: ``x`` the model input ``(B, ...)`` (already normalised), ``label`` int32 ``(B,)`` (−1: ignore),
    ``valid`` bool ``(B,)`` (False for padding). Metrics: ``loss`` and ``accuracy`` over the valid rows.
    """
    out = state.apply_fn({"params": params}, batch["x"], train=True, rngs={"dropout": key})
    logits, _ = _logits_and_features(out)
    labels = batch["label"]
    # Padding and "no class" rows (label −1) weigh 0, so a padded batch gives the mean over its real rows.
    weight = (batch["valid"] & (labels >= 0)).astype(jnp.float32)
    ce = optax.softmax_cross_entropy_with_integer_labels(logits.astype(jnp.float32), jnp.maximum(labels, 0))
    n = jnp.maximum(weight.sum(), 1.0)
    loss = (ce * weight).sum() / n
    acc = ((jnp.argmax(logits, -1) == labels) * weight).sum() / n
    return loss, ({"loss": loss, "accuracy": acc}, None)


@functools.partial(jax.jit, donate_argnums=0, static_argnames=("objective",))
def train_step(
    state: TrainState, batch: dict[str, jax.Array], key: jax.Array, objective: Objective = classification_loss
) -> tuple[TrainState, dict]:
    """One optimiser step on a batch; pure in (state, batch, key).

    Args:
        state: the TrainState (donated: its buffers are reused for the result).
        batch: what ``objective`` reads, sharded along the batch axis over the mesh (or on one device).
        key: the run's base key; the step's key is ``fold_in(key, state.step)``, so a resumed run draws the same
            dropout masks and augmentations as an uninterrupted one.
        objective: see the module docstring; default :func:`classification_loss`.

    Returns:
        ``(new_state, metrics)``, metrics of the global batch.
    """
    step_key = jax.random.fold_in(key, state.step)
    grads, (metrics, batch_stats) = jax.grad(objective, argnums=1, has_aux=True)(state, state.params, batch, step_key)
    new = state.apply_gradients(grads=grads)
    if batch_stats is not None:
        new = new.replace(batch_stats=batch_stats)
    return new, metrics


@jax.jit
def predict_step(state: TrainState, x: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Deterministic forward pass: ``(logits (B, C), features)`` (features empty for models returning logits)."""
    return _logits_and_features(state.apply_fn(state.variables, x, train=False))
