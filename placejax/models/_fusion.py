"""The paper's integration network (Sec. "MLP"): concatenated RGB and HHA embeddings → 1024 → places."""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax
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
        input_dropout_rate: dropout on the concatenated embeddings when ``train=True``.
        modality_sizes: the widths of the concatenated embeddings, in order (e.g. ``(512, 512)`` for RGB and
            HHA fc7); only read by ``modality_dropout``.
        modality_dropout: when ``train=True``, each example loses one of its ``modality_sizes`` blocks with this
            probability per block (never more than one, so ``len(modality_sizes) · modality_dropout`` must be
            ≤ 1), the kept blocks scaled by ``1 / (1 − modality_dropout)`` (ModDrop, Neverova et al. 2015). The
            parameters do not depend on either dropout: a head trained with them loads into a plain one.

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
    input_dropout_rate: float = 0.0
    modality_sizes: tuple[int, ...] = ()
    modality_dropout: float = 0.0
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, embeddings: Array, train: bool = False) -> Array:
        if embeddings.ndim != 2:
            raise ValueError(f"FusionMLP expects (N, D) concatenated embeddings, got shape {embeddings.shape}")
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        if train and self.modality_dropout > 0:
            embeddings = self._drop_modalities(embeddings)
        embeddings = nn.Dropout(self.input_dropout_rate, deterministic=not train)(embeddings)
        x = nn.relu(nn.Dense(self.hidden, name="hidden", **kw)(embeddings))
        x = nn.Dropout(self.dropout_rate, deterministic=not train)(x)
        return nn.Dense(self.num_classes, name="out", **kw)(x)

    def _drop_modalities(self, embeddings: Array) -> Array:
        sizes, p = self.modality_sizes, self.modality_dropout
        if sum(sizes) != embeddings.shape[1]:
            width = embeddings.shape[1]
            raise ValueError(f"FusionMLP modality_sizes {sizes} do not add up to the embedding width {width}")
        if not 0 <= p * len(sizes) <= 1:
            raise ValueError(f"FusionMLP modality_dropout {p} × {len(sizes)} blocks must lie in [0, 1]")
        u = jax.random.uniform(self.make_rng("dropout"), (embeddings.shape[0], 1))
        # Block i is dropped when u falls in [i·p, (i+1)·p): at most one block per example.
        blocks, start = [], 0
        for i, size in enumerate(sizes):
            dropped = (u >= i * p) & (u < (i + 1) * p)
            block = embeddings[:, start : start + size]
            blocks.append(jnp.where(dropped, 0.0, block / (1.0 - p)).astype(embeddings.dtype))
            start += size
        return jnp.concatenate(blocks, axis=1)
