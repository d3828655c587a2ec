"""Separable resizes written as two small matrix products, matching PyTorch's `F.interpolate`.

`jax.image.resize` has no ``align_corners=True`` mode (which MiDaS's fusion blocks use), antialiases when it
downsamples and uses the Keys cubic with a = -0.5 where PyTorch uses a = -0.75. Each resize here builds, for
each spatial axis, an interpolation matrix ``(out, in)`` in NumPy at trace time (shapes are static) and
applies it with one ``einsum`` per axis: XLA turns these into dense dots, which are fast on CPU and exactly
reproduce PyTorch's weights, including its border handling.
"""

from __future__ import annotations

import functools
from typing import Literal

import jax.numpy as jnp
import numpy as np
from jax import Array

Method = Literal["bilinear", "bicubic"]

# PyTorch's bicubic coefficient (aten/src/ATen/native/UpSample.h); Keys' a = -0.5 would differ by ~1e-2.
_TORCH_CUBIC_A = -0.75


def _cubic_weights(t: np.ndarray, a: float) -> np.ndarray:
    """Keys cubic convolution weights for taps at offsets -1, 0, 1, 2 from ``floor(x)``; ``t`` in [0, 1)."""
    x = np.stack([t + 1.0, t, 1.0 - t, 2.0 - t], axis=-1)
    near = ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0
    far = ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a
    return np.where(x <= 1.0, near, far)


@functools.lru_cache(maxsize=256)
def interpolation_matrix(in_size: int, out_size: int, method: Method, align_corners: bool) -> np.ndarray:
    """The ``(out_size, in_size)`` float64 matrix of a 1-D resize, as PyTorch's ``F.interpolate`` computes it.

    Args:
        in_size: input length (pixels), ≥ 1.
        out_size: output length (pixels), ≥ 1.
        method: ``"bilinear"`` (linear along this axis) or ``"bicubic"`` (Keys, a = -0.75).
        align_corners: ``True`` maps the first/last pixel centres onto each other (source position
            ``i·(in−1)/(out−1)``); ``False`` uses half-pixel centres (``(i+0.5)·in/out − 0.5``).

    Returns:
        Row ``i`` holds the weights of the input pixels that make output pixel ``i``; rows sum to 1.

    >>> interpolation_matrix(2, 3, "bilinear", True).tolist()
    [[1.0, 0.0], [0.5, 0.5], [0.0, 1.0]]
    """
    if in_size < 1 or out_size < 1:
        raise ValueError(f"resize sizes must be ≥ 1, got in_size={in_size}, out_size={out_size}")
    if method not in ("bilinear", "bicubic"):
        raise ValueError(f"method must be 'bilinear' or 'bicubic', got {method!r}")
    i = np.arange(out_size, dtype=np.float64)
    if align_corners:
        src = i * ((in_size - 1) / (out_size - 1)) if out_size > 1 else np.zeros_like(i)
    else:
        src = (i + 0.5) * (in_size / out_size) - 0.5
        if method == "bilinear":
            # PyTorch clamps negative half-pixel sources to 0 for linear modes (but not for cubic).
            src = np.maximum(src, 0.0)
    base = np.floor(src)
    t = src - base
    m = np.zeros((out_size, in_size), dtype=np.float64)
    rows = np.arange(out_size)
    if method == "bilinear":
        taps, weights = np.stack([base, base + 1], -1), np.stack([1.0 - t, t], -1)
    else:
        taps, weights = base[:, None] + np.arange(-1, 3), _cubic_weights(t, _TORCH_CUBIC_A)
    taps = np.clip(taps, 0, in_size - 1).astype(np.int64)
    for k in range(taps.shape[1]):
        np.add.at(m, (rows, taps[:, k]), weights[:, k])
    return m


def resize(
    x: Array,
    shape: tuple[int, int],
    method: Method = "bilinear",
    *,
    align_corners: bool = False,
) -> Array:
    """Resizes the two spatial axes of an NHWC batch exactly as PyTorch's ``F.interpolate`` does (no
    antialias).

    Args:
        x: ``(N, H, W, C)`` array (float).
        shape: output ``(H_out, W_out)`` in pixels.
        method: ``"bilinear"`` or ``"bicubic"`` (PyTorch's a = -0.75 cubic, clamped borders).
        align_corners: PyTorch's flag of the same name.

    Returns:
        ``(N, H_out, W_out, C)`` array of ``x.dtype``.

    >>> resize(jnp.ones((1, 4, 4, 2)), (8, 8), align_corners=True).shape
    (1, 8, 8, 2)
    """
    if x.ndim != 4:
        raise ValueError(f"resize expects an NHWC array (N, H, W, C), got shape {x.shape}")
    h_out, w_out = (int(s) for s in shape)
    _, h, w, _ = x.shape
    if (h, w) == (h_out, w_out):
        return x  # every mode above is the identity at equal sizes
    mh = jnp.asarray(interpolation_matrix(h, h_out, method, align_corners), dtype=x.dtype)
    mw = jnp.asarray(interpolation_matrix(w, w_out, method, align_corners), dtype=x.dtype)
    # Highest precision: on accelerators the default dot precision would round the weights to bf16.
    y = jnp.einsum("oh,nhwc->nowc", mh, x, precision="highest")
    return jnp.einsum("pw,nowc->nopc", mw, y, precision="highest")


def upsample2x_align_corners(x: Array) -> Array:
    """Bilinear ×2 upsampling of an NHWC batch with ``align_corners=True`` (MiDaS's fusion-block resize)."""
    _, h, w, _ = x.shape
    return resize(x, (2 * h, 2 * w), "bilinear", align_corners=True)
