"""Separable resizes that reproduce PyTorch's `F.interpolate` (bilinear, bicubic, either corner mode).

`jax.image.resize` has no ``align_corners=True`` mode (which MiDaS's fusion blocks use), antialiases when
it downsamples and uses the Keys cubic with a = -0.5 where PyTorch uses a = -0.75. Here each spatial axis
is resized separately: its source indices and weights are computed in NumPy at trace time (shapes are
static), exactly as PyTorch computes them (border clamping included), and applied as K = 2 (bilinear) or
4 (bicubic) constant-index gathers and a weighted sum, which XLA fuses into one loop (a dense
interpolation-matrix product was ~70× slower on CPU).
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
def interpolation_taps(
    in_size: int, out_size: int, method: Method, align_corners: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Input indices ``(out, K)`` and weights ``(out, K)`` of a 1-D resize as PyTorch's ``F.interpolate``.

    K = 2 for bilinear, 4 for bicubic; indices are clamped to the border as PyTorch does. See
    ``interpolation_matrix`` for the arguments.
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
    if method == "bilinear":
        taps, weights = np.stack([base, base + 1], -1), np.stack([1.0 - t, t], -1)
    else:
        taps, weights = base[:, None] + np.arange(-1, 3), _cubic_weights(t, _TORCH_CUBIC_A)
    return np.clip(taps, 0, in_size - 1).astype(np.int32), weights


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
    taps, weights = interpolation_taps(in_size, out_size, method, align_corners)
    m = np.zeros((out_size, in_size), dtype=np.float64)
    rows = np.repeat(np.arange(out_size), taps.shape[1])
    np.add.at(m, (rows, taps.ravel()), weights.ravel())
    return m


def _resize_axis(x: Array, axis: int, out_size: int, method: Method, align_corners: bool) -> Array:
    taps, weights = interpolation_taps(x.shape[axis], out_size, method, align_corners)
    shape = [1] * x.ndim
    shape[axis] = out_size
    out = None
    # K gathers with constant indices and a weighted sum: XLA fuses them into one loop over the output, far
    # cheaper on CPU than a dense (out × in) interpolation matrix product with its transposes.
    for k in range(taps.shape[1]):
        w = jnp.asarray(weights[:, k].reshape(shape), x.dtype)
        term = jnp.take(x, jnp.asarray(taps[:, k]), axis=axis) * w
        out = term if out is None else out + term
    return out


def resize(
    x: Array,
    shape: tuple[int, int],
    method: Method = "bilinear",
    *,
    align_corners: bool = False,
) -> Array:
    """Resizes the two spatial axes of an NHWC batch as PyTorch's ``F.interpolate`` does (no antialias).

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
    if x.shape[1] != h_out:
        x = _resize_axis(x, 1, h_out, method, align_corners)
    if x.shape[2] != w_out:
        x = _resize_axis(x, 2, w_out, method, align_corners)
    return x  # every mode is the identity along an axis whose size does not change


def upsample2x_align_corners(x: Array) -> Array:
    """Bilinear ×2 upsampling of an NHWC batch ``(N, H, W, C)`` → ``(N, 2H, 2W, C)`` with ``align_corners=True``
    (MiDaS's fusion-block resize)."""
    _, h, w, _ = x.shape
    return resize(x, (2 * h, 2 * w), "bilinear", align_corners=True)
