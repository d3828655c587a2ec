"""VGG16 in torchvision's layout (``torchvision.models.vgg16``), NHWC, with a documented trunk/head split.

``docs/models.md``: 13 biased 3×3 convs with ReLU and five 2×2 max-pools, adaptive 7×7 average
pooling (any input size works), then fc6 → ReLU → dropout → fc7 → ReLU → dropout → fc8. The trunk (convs +
pooling) and the head (fc6..fc8) are separate submodules so a frozen trunk's output can be computed once and
cached while only the head trains (the paper fine-tunes the fully connected layers with the convolutions
frozen).

Layout note: the head flattens the pooled ``(7, 7, C)`` map in NHWC order, so fc6's kernel rows are ordered
``(h, w, c)``; ``placejax.weights.convert_vgg16`` permutes torchvision's NCHW-ordered rows once at conversion.
"""

from __future__ import annotations

import functools
from typing import Any

import flax.linen as nn
import jax.numpy as jnp
import numpy as np
from jax import Array

from placejax.models._conv import FEW_CHANNELS, FewChannelConv

Dtype = Any

# (block, convs in block, output channels) of VGG16 ("configuration D").
_BLOCKS: tuple[tuple[int, int, int], ...] = ((1, 2, 64), (2, 2, 128), (3, 3, 256), (4, 3, 512), (5, 3, 512))
CONV_NAMES: tuple[str, ...] = tuple(f"conv{b}_{j}" for b, n, _ in _BLOCKS for j in range(1, n + 1))
"""The 13 conv layers of VGG16's trunk in order (``conv1_1`` … ``conv5_3``), the names of its parameters."""
POOL_SIZE = 7
_FC_WIDTH = 4096


@functools.lru_cache(maxsize=64)
def adaptive_avg_pool_matrix(in_size: int, out_size: int) -> np.ndarray:
    """``(out, in)`` averaging matrix of PyTorch's AdaptiveAvgPool along one axis.

    Output cell i averages input rows ``floor(i·in/out) .. ceil((i+1)·in/out) − 1``; cells may overlap and,
    when ``in < out``, repeat rows. The 2-D pool is separable because every cell is a rectangle.

    >>> adaptive_avg_pool_matrix(2, 3).tolist()
    [[1.0, 0.0], [0.5, 0.5], [0.0, 1.0]]
    """
    m = np.zeros((out_size, in_size))
    for i in range(out_size):
        lo = (i * in_size) // out_size
        hi = -((-(i + 1) * in_size) // out_size)  # ceil
        m[i, lo:hi] = 1.0 / (hi - lo)
    return m


def adaptive_avg_pool(x: Array, out_hw: tuple[int, int]) -> Array:
    """PyTorch ``AdaptiveAvgPool2d`` on an NHWC batch: ``(N, H, W, C)`` → ``(N, h, w, C)``."""
    _, h, w, _ = x.shape
    if (h, w) == tuple(out_hw):
        return x  # identity at 224×224 input, the usual case
    ph = jnp.asarray(adaptive_avg_pool_matrix(h, out_hw[0]), x.dtype)
    pw = jnp.asarray(adaptive_avg_pool_matrix(w, out_hw[1]), x.dtype)
    y = jnp.einsum("oh,nhwc->nowc", ph, x, precision="highest")
    return jnp.einsum("pw,nowc->nopc", pw, y, precision="highest")


def _scaled(c: int, width: float) -> int:
    return max(1, round(c * width))


class VGG16Trunk(nn.Module):
    """The 13 convolutions, max-pools and adaptive average pooling of VGG16.

    Attributes:
        width: channel multiplier (1.0 = VGG16; e.g. 0.25 for CPU-sized presets, same topology).

    Maps ``(N, H, W, 3)`` normalised RGB (H, W ≥ 32) to the pooled ``(N, 7, 7, C)`` map, C = 512·width
    (``pool=False``: the last max-pool's ``(N, H//32, W//32, C)`` map, see ``fold_adaptive_pool``).
    """

    width: float = 1.0
    pool: bool = True
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x: Array) -> Array:
        if x.ndim != 4 or x.shape[-1] != 3:
            raise ValueError(f"VGG16 expects NHWC images (N, H, W, 3), got shape {x.shape}")
        if x.shape[1] < 32 or x.shape[2] < 32:
            raise ValueError(f"VGG16 needs H, W ≥ 32 (five 2×2 max-pools), got {x.shape[1:3]}")
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        for b, n, c in _BLOCKS:
            for j in range(1, n + 1):
                name, features = f"conv{b}_{j}", _scaled(c, self.width)
                if x.shape[-1] <= FEW_CHANNELS:  # conv1_1 on RGB: shifted products beat XLA's CPU convolution
                    x = FewChannelConv(features, 3, name=name, **kw)(x)
                else:
                    x = nn.Conv(features, (3, 3), padding=((1, 1), (1, 1)), name=name, **kw)(x)
                x = nn.relu(x)
            x = nn.max_pool(x, (2, 2), strides=(2, 2))
        return adaptive_avg_pool(x, (POOL_SIZE, POOL_SIZE)) if self.pool else x


class VGG16Head(nn.Module):
    """fc6 → ReLU → dropout → fc7 → ReLU → dropout → fc8 on the pooled trunk output.

    Attributes:
        num_classes: fc8 outputs.
        hidden: fc6/fc7 width (4096 for VGG16).
        dropout_rate: dropout after fc6 and fc7 when ``train=True`` (needs a ``"dropout"`` rng).
    """

    num_classes: int
    hidden: int = _FC_WIDTH
    dropout_rate: float = 0.5
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, pooled: Array, train: bool = False) -> tuple[Array, dict[str, Array]]:
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        x = pooled.reshape(pooled.shape[0], -1)  # NHWC flatten; fc6 rows are (h, w, c) ordered
        fc6 = nn.relu(nn.Dense(self.hidden, name="fc6", **kw)(x))
        x = nn.Dropout(self.dropout_rate, deterministic=not train)(fc6)
        fc7 = nn.relu(nn.Dense(self.hidden, name="fc7", **kw)(x))
        x = nn.Dropout(self.dropout_rate, deterministic=not train)(fc7)
        logits = nn.Dense(self.num_classes, name="fc8", **kw)(x)
        return logits, {"fc6": fc6, "fc7": fc7}


class VGG16(nn.Module):
    """VGG16 classifier, torchvision layout, NHWC.

    Attributes:
        num_classes: classes of fc8 (1000 for ImageNet; 100 places in the paper).
        width: channel multiplier of convs and fully connected layers (1.0 = VGG16). fc6/fc7 have
            ``round(4096·width)`` units.
        dropout_rate: dropout after fc6 and fc7 in training.
        folded_pool: the adaptive 7×7 average pool is folded into fc6 (``fold_adaptive_pool``): fc6 reads the
            trunk's last map directly. Same outputs, for variables folded for this input size.
        dtype: computation dtype; param_dtype: parameter dtype.

    ``logits, features = VGG16(num_classes=100).apply(variables, x, train=False)`` with ``x`` ``(N, H, W, 3)``
    ImageNet-normalised RGB; ``logits`` ``(N, num_classes)``, ``features["fc6"]``/``["fc7"]`` ``(N,
    4096·width)`` post-ReLU (before dropout). Training needs ``rngs={"dropout": key}``. The split for cached
    training: ``pooled = model.apply(v, x, method=VGG16.conv_features)`` (``(N, 7, 7, 512·width)``,
    parameters under ``params["trunk"]``) then ``model.apply(v, pooled, train=True, method=VGG16.head)``
    (``params["head"]``).

    >>> import jax
    >>> m = VGG16(num_classes=3, width=1 / 16)
    >>> v = m.init(jax.random.key(0), jnp.zeros((1, 32, 32, 3)))
    >>> logits, feats = m.apply(v, jnp.zeros((2, 32, 32, 3)))
    >>> logits.shape, feats["fc7"].shape
    ((2, 3), (2, 256))
    """

    num_classes: int = 1000
    width: float = 1.0
    dropout_rate: float = 0.5
    folded_pool: bool = False
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    def setup(self) -> None:
        kw = dict(dtype=self.dtype, param_dtype=self.param_dtype)
        self.trunk = VGG16Trunk(self.width, pool=not self.folded_pool, **kw)
        self.classifier = VGG16Head(self.num_classes, _scaled(_FC_WIDTH, self.width), self.dropout_rate, **kw)

    def __call__(self, x: Array, train: bool = False) -> tuple[Array, dict[str, Array]]:
        return self.classifier(self.trunk(x), train=train)

    def conv_features(self, x: Array) -> Array:
        """Frozen-trunk output ``(N, 7, 7, 512·width)`` (after adaptive average pooling, before flatten;
        ``folded_pool``: the unpooled ``(N, H//32, W//32, 512·width)`` map)."""
        return self.trunk(x)

    def head(self, pooled: Array, train: bool = False) -> tuple[Array, dict[str, Array]]:
        """fc6..fc8 on a ``conv_features`` output: ``(logits, {"fc6", "fc7"})``."""
        return self.classifier(pooled, train=train)


def _last_map_size(input_hw: tuple[int, int]) -> tuple[int, int]:
    """``(h, w)`` of the trunk's last max-pool output for an ``(H, W)`` input: five floor-halvings, ``H // 32``
    (``placejax.pretrain.trunk_map_size`` finds the same by tracing the model)."""
    h, w = (int(v) for v in input_hw)
    if h < 32 or w < 32:
        raise ValueError(f"VGG16 needs H, W ≥ 32 (five 2×2 max-pools), got {(h, w)}")
    return h // 32, w // 32


def fold_adaptive_pool(variables: dict[str, Any], input_hw: tuple[int, int]) -> dict[str, Any]:
    """Folds the adaptive 7×7 average pool into fc6, for ``VGG16(folded_pool=True)`` at one input size.

    The pool is linear, so ``fc6(pool(x)) = fc6'(x)`` with ``fc6'`` = the kernel contracted with the two
    pooling matrices: ``K'[a, b, c, :] = Σ_{o,p} P_h[o, a]·P_w[p, b]·K[o, p, c, :]`` (rows ``(h, w, c)``
    ordered, as the head flattens). Below 224×224 the trunk's last map has fewer than 49 cells and fc6 shrinks
    by 49/(h·w): at 64×64 (a 2×2 map) from 25,088 to 2,048 rows of VGG16, 392 MB less to read per call, which
    dominates fc7 embeddings at small batches. At ≥ 224×224 (a map of ≥ 7×7 cells) it does not pay.

    Args:
        variables: ``VGG16`` variables (unfolded: fc6 has ``49·C`` rows, C = the trunk's width).
        input_hw: the ``(H, W)`` images the folded model will see (the folded fc6 only fits maps of that size).

    Returns:
        New variables (inputs untouched); outputs of ``VGG16(..., folded_pool=True)`` on ``(H, W)`` inputs
        equal the unfolded model's up to float rounding.

    >>> import jax
    >>> m = VGG16(num_classes=3, width=1 / 16)
    >>> v = m.init(jax.random.key(0), jnp.zeros((1, 64, 64, 3)))
    >>> f = fold_adaptive_pool(v, (64, 64))
    >>> v["params"]["classifier"]["fc6"]["kernel"].shape, f["params"]["classifier"]["fc6"]["kernel"].shape
    ((1568, 256), (128, 256))
    """
    h, w = _last_map_size(input_hw)
    params = variables["params"]
    kernel = jnp.asarray(params["classifier"]["fc6"]["kernel"])
    rows, hidden = kernel.shape
    if rows % (POOL_SIZE * POOL_SIZE):
        raise ValueError(
            f"fold_adaptive_pool: fc6 kernel has {rows} rows, expected 49·C for the 7×7 pooled map (already folded?)"
        )
    c = rows // (POOL_SIZE * POOL_SIZE)
    ph = jnp.asarray(adaptive_avg_pool_matrix(h, POOL_SIZE), kernel.dtype)
    pw = jnp.asarray(adaptive_avg_pool_matrix(w, POOL_SIZE), kernel.dtype)
    k = kernel.reshape(POOL_SIZE, POOL_SIZE, c, hidden)
    folded = jnp.einsum("oa,pb,opcj->abcj", ph, pw, k, precision="highest").reshape(h * w * c, hidden)
    classifier = {**params["classifier"], "fc6": {**params["classifier"]["fc6"], "kernel": folded}}
    return {**variables, "params": {**params, "classifier": classifier}}
