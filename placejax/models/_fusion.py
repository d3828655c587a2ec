"""The paper's integration network (Sec. "MLP"): concatenated RGB and HHA embeddings → 1024 → places."""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax.numpy as jnp
from jax import Array

Dtype = Any


class FusionMLP(nn.Module):
    """Dense → ReLU → dropout → Dense over concatenated embeddings (paper: 8192 → 1024 → 100).

    Attributes:
        num_classes: outputs (100 places: cells of the 10×10 grid).
        hidden: hidden units (1024 in the paper).
        dropout_rate: dropout on the hidden layer when ``train=True`` (0 disables it; needs a ``"dropout"``
            rng).

    Input ``(N, D)`` (D = 2·4096 for two VGG16 fc7 embeddings; any D works); output ``(N, num_classes)``
    logits.

    >>> import jax
    >>> m = FusionMLP(num_classes=5, hidden=8)
    >>> v = m.init(jax.random.key(0), jnp.zeros((1, 16)))
    >>> m.apply(v, jnp.ones((3, 16))).shape
    (3, 5)
    """

    num_classes: int = 100
    hidden: int = 1024
    dropout_rate: float = 0.0
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, embeddings: Array, train: bool = False) -> Array:
        if embeddings.ndim != 2:
            raise ValueError(
                f"FusionMLP expects (N, D) concatenated embeddings, got shape {embeddings.shape}"
            )
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        x = nn.relu(nn.Dense(self.hidden, name="hidden", **kw)(embeddings))
        x = nn.Dropout(self.dropout_rate, deterministic=not train)(x)
        return nn.Dense(self.num_classes, name="out", **kw)(x)
