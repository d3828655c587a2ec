"""Convolutions written as sums of shifted products, for the shapes where XLA's CPU convolution is slow.

XLA's CPU backend runs every convolution as a matrix product over im2col-like panels. When one side of that
product is tiny — a depthwise convolution (one input channel per output) or a first layer reading 3 colour
channels — the product is mostly overhead, while k² shifted slices multiplied by per-channel weights fuse into
one elementwise loop. Both modules here keep ``nn.Conv``'s parameters (names, shapes, initialisers), so weights
load unchanged, and compute the same result up to float rounding (tests/test_models_*.py compare them).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from jax import Array

Dtype = Any

# Input widths up to which FewChannelConv computes by shifted products (measured, 2-core CPU, batch 8, 3×3:
# 3 → 8 channels at 64²: 1.20 ms as a convolution vs 0.26 ms; 3 → 64 at 256²: 49 vs 46 ms; 8 → 8: 0.93 vs
# 0.78 ms; 16 → 16: 0.55 vs 1.24 ms — the product count grows with input × output channels).
FEW_CHANNELS = 4


def shifted_taps(x: Array, k: int, stride: int) -> Iterator[tuple[int, int, Array]]:
    """``(i, j, slice)`` for each of the k² taps of a k×k window over ``x`` ``(N, H, W, C)`` with TF "SAME"
    padding (total ``(out − 1)·s + k − in``, the odd pixel at the bottom/right) and stride ``stride``: the
    slice is ``(N, ceil(H/s), ceil(W/s), C)``, the inputs that tap (i, j) of every output window reads."""
    n, h, w, c = x.shape
    oh, ow = -(-h // stride), -(-w // stride)
    ph, pw = max((oh - 1) * stride + k - h, 0), max((ow - 1) * stride + k - w, 0)
    xp = jnp.pad(x, ((0, 0), (ph // 2, ph - ph // 2), (pw // 2, pw - pw // 2), (0, 0)))
    for i in range(k):
        for j in range(k):
            end = (n, i + (oh - 1) * stride + 1, j + (ow - 1) * stride + 1, c)
            yield i, j, jax.lax.slice(xp, (0, i, j, 0), end, (1, stride, stride, 1))


class FewChannelConv(nn.Module):
    """k×k convolution with TF "SAME" padding for inputs with few channels (e.g. RGB), as a sum of k²·C_in
    shifted products.

    Same parameters (``kernel`` ``(k, k, C_in, features)``, ``bias`` ``(features,)``) and result as
    ``nn.Conv(features, (k, k), strides=s, padding="SAME")`` (at stride 1 and odd k, "SAME" is the symmetric
    ``k // 2`` padding VGG uses). On CPU a 3-channel first layer runs ~4.7× faster this way at 1/8-width VGG16
    and 64×64 (1.20 → 0.26 ms, batch 8) and a little faster at full width; wider inputs should use ``nn.Conv``
    (see ``FEW_CHANNELS``).
    """

    features: int
    kernel_size: int
    stride: int = 1
    use_bias: bool = True
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32
    kernel_init: Callable[..., Array] = nn.initializers.lecun_normal()
    bias_init: Callable[..., Array] = nn.initializers.zeros_init()

    @nn.compact
    def __call__(self, x: Array) -> Array:
        k, cin = self.kernel_size, x.shape[-1]
        kernel = self.param("kernel", self.kernel_init, (k, k, cin, self.features), self.param_dtype)
        bias = self.param("bias", self.bias_init, (self.features,), self.param_dtype) if self.use_bias else None
        x, kernel, bias = nn.dtypes.promote_dtype(x, kernel, bias, dtype=self.dtype)
        out = None
        for i, j, tap in shifted_taps(x, k, self.stride):
            for ci in range(cin):
                term = tap[..., ci : ci + 1] * kernel[i, j, ci].reshape(1, 1, 1, -1)
                out = term if out is None else out + term
        return out if bias is None else out + bias.reshape(1, 1, 1, -1)


class DepthwiseConv(nn.Module):
    """Bias-free depthwise k×k convolution with TF "SAME" padding, as a sum of k² shifted products.

    Same parameter (``kernel``, ``(k, k, 1, C)``) and result as ``nn.Conv(C, (k, k), feature_group_count=C,
    padding="SAME", use_bias=False)``, but XLA's CPU backend runs grouped convolutions through a slow generic
    path (10–30× slower here, e.g. 200 ms vs 6 ms for 128×128×144, k = 3), while shifted multiply-adds fuse
    into one elementwise loop. This is what makes the EfficientNet encoder fast on CPU.

    Attributes:
        kernel_size: k (odd).
        stride: 1 or 2.
        use_bias: add a ``(C,)`` ``bias`` (used by the BatchNorm-folded inference model).
    """

    kernel_size: int
    stride: int = 1
    use_bias: bool = False
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32
    kernel_init: Callable[..., Array] = nn.initializers.lecun_normal()
    bias_init: Callable[..., Array] = nn.initializers.zeros_init()

    @nn.compact
    def __call__(self, x: Array) -> Array:
        k, c = self.kernel_size, x.shape[-1]
        kernel = self.param("kernel", self.kernel_init, (k, k, 1, c), self.param_dtype)
        x, kernel = nn.dtypes.promote_dtype(x, kernel, dtype=self.dtype)
        out = None
        for i, j, tap in shifted_taps(x, k, self.stride):
            term = tap * kernel[i, j, 0].reshape(1, 1, 1, c)  # explicit (1, 1, 1, C) broadcasting per tap
            out = term if out is None else out + term
        if self.use_bias:
            bias = self.param("bias", self.bias_init, (c,), self.param_dtype)
            out = out + bias.astype(out.dtype).reshape(1, 1, 1, c)
        return out
