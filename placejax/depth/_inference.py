"""MiDaS inference: the original input transform, the pure jittable ``apply`` and the batched ``predict``.

Follows isl-org/MiDaS ``midas/transforms.py`` (``Resize`` with ``keep_aspect_ratio=True``,
``ensure_multiple_of=32``, ``resize_method="upper_bound"``, ``cv2.INTER_CUBIC``; ``NormalizeImage`` with
ImageNet statistics) and ``run.py``'s bicubic upsampling of the prediction back to the image size;
``docs/models.md``. ``apply`` does the whole transform in JAX (PyTorch's bicubic, a = -0.75, as OpenCV's
``INTER_CUBIC``; the two agree to float rounding), so it composes with a caller's ``jit`` / ``vmap``;
``predict`` keeps the original host-side OpenCV resize, the path the experiment's depth caches were built with.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from placejax.models import IMAGENET_MEAN, IMAGENET_STD, MidasSmall, cpu_compiler_options, resize

__all__ = ["apply", "network_size", "predict", "preprocess"]

_MULTIPLE = 32


def _to_multiple(x: float, max_val: int) -> int:
    # np.round is round-half-to-even, as in MiDaS's Resize.constrain_to_multiple_of.
    y = int(np.round(x / _MULTIPLE) * _MULTIPLE)
    if y > max_val:
        y = int(np.floor(x / _MULTIPLE) * _MULTIPLE)
    return y


def network_size(image_hw: tuple[int, int], size: int = 256, square: bool = False) -> tuple[int, int]:
    """The ``(h, w)`` MiDaS resizes an ``(H, W)`` image to before the network.

    The longer side goes to ``size`` and the aspect ratio is kept, each side rounded (half to even) to a
    multiple of 32; ``square=True`` gives ``(size, size)``.

    >>> network_size((480, 640)), network_size((1080, 1920)), network_size((50, 100))
    ((192, 256), (128, 256), (128, 256))
    """
    h, w = (int(v) for v in image_hw)
    if h < 1 or w < 1:
        raise ValueError(f"image size must be positive, got {image_hw}")
    if square:
        return size, size
    scale = min(size / w, size / h)
    out = _to_multiple(scale * h, size), _to_multiple(scale * w, size)
    if min(out) < _MULTIPLE:
        raise ValueError(f"image of size {image_hw} is too elongated for MiDaS: it would be resized to {out}")
    return out


def preprocess(image: np.ndarray, *, size: int = 256, square: bool = False) -> np.ndarray:
    """MiDaS's input transform of one image: resize (bicubic) to ``network_size`` and ImageNet-normalise.

    Args:
        image: ``(H, W, 3)`` RGB, ``uint8`` in [0, 255] or floating point in [0, 1] (not clipped).
        size: the longer network side (256 for MiDaS v2.1 small).
        square: resize to ``size × size`` ignoring the aspect ratio (MiDaS's ``square`` option).

    Returns:
        ``(h, w, 3)`` float32, ``(h, w) = network_size((H, W), size, square)``.
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"preprocess expects one (H, W, 3) RGB image, got shape {image.shape}")
    if image.dtype == np.uint8:
        x = image.astype(np.float32) / np.float32(255.0)
    elif np.issubdtype(image.dtype, np.floating):
        x = image.astype(np.float32)
    else:
        raise ValueError(f"preprocess expects uint8 or float images, got dtype {image.dtype}")
    h, w = network_size(image.shape[:2], size, square)
    if (h, w) != x.shape[:2]:
        x = cv2.resize(x, (w, h), interpolation=cv2.INTER_CUBIC)
    return (x - IMAGENET_MEAN) / IMAGENET_STD


def network_on_images(model: MidasSmall, variables: Any, x: jax.Array, net_hw: tuple[int, int]) -> jax.Array:
    """The MiDaS transform and network on float images in [0, 1], in JAX: ``(N, H, W, 3)`` → ``(N, H, W)``.

    Bicubic resize (PyTorch's, ``align_corners=False``) to ``net_hw``, ImageNet normalisation, the network, and
    the bicubic resize of its output back to ``(H, W)``. Shared by :func:`apply` and
    ``placejax.classify.forward``, so both compute the same numbers.
    """
    mean = jnp.asarray(IMAGENET_MEAN).reshape(1, 1, 1, 3)
    std = jnp.asarray(IMAGENET_STD).reshape(1, 1, 1, 3)
    resized = tuple(x.shape[1:3]) != tuple(net_hw)
    x_net = resize(x, tuple(net_hw), "bicubic", align_corners=False) if resized else x
    out = model.apply(variables, (x_net - mean) / std, train=False)
    # run.py: F.interpolate(prediction[:, None], size=image size, mode="bicubic", align_corners=False).
    return resize(out[..., None], tuple(x.shape[1:3]), "bicubic", align_corners=False)[..., 0]


def apply(
    params: Any,
    rgb_uint8: jax.Array | np.ndarray,
    *,
    model: MidasSmall | None = None,
    size: int = 256,
    square: bool = False,
) -> jax.Array:
    """The MiDaS-style network's output on a batch of images: a pure function of arrays, jittable and
    differentiable.

    The whole MiDaS transform runs in JAX (``jax.jit(placejax.depth.apply)`` works as it is; pass ``model``,
    ``size`` and ``square`` with ``functools.partial`` before ``jit``, as they fix shapes). It computes what
    :func:`predict` computes, whose input resize runs on the host in OpenCV: the two agree within float32
    rounding of the resize (about 1e-5 of the output's range).

    Args:
        params: ``MidasSmall`` variables (``{"params": ..., "batch_stats": ...}``), e.g.
            ``placejax.weights.load("midas_v21_small_256")`` or ``placejax.weights.resolve(spec).variables``.
        rgb_uint8: uint8 ``(N, H, W, 3)`` RGB in [0, 255] (floating point images in [0, 1] are accepted too).
        model: the network (default ``MidasSmall()``, the official architecture).
        size: the longer network side (256 for MiDaS v2.1 small); see :func:`network_size`.
        square: resize to ``size × size`` ignoring the aspect ratio (placejax's trained depth networks).

    Returns:
        float32 ``jax.Array`` ``(N, H, W)``, the network's output resized to the images: relative inverse depth
        (bigger is closer; unknown scale and shift) for MiDaS and inverse-depth networks; log depth for a
        placejax metric network (``target="log_metric"``, the shipped default: ``placejax.depth.depth_from_log``
        gives metres, what ``TrainedDepth.predict_metric`` returns).

    Raises:
        ValueError: not a batch of RGB images (wrong rank or channel count, an empty batch) or an integer dtype
            other than uint8.
    """
    x = jnp.asarray(rgb_uint8)
    if x.ndim != 4 or x.shape[-1] != 3 or 0 in x.shape:
        raise ValueError(f"apply expects a batch of RGB images (N, H, W, 3), got shape {x.shape}")
    if x.dtype == jnp.uint8:
        x = x.astype(jnp.float32) / 255.0
    elif jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.float32)
    else:
        raise ValueError(f"apply expects uint8 (or float in [0, 1]) images, got dtype {x.dtype}")
    model = MidasSmall() if model is None else model
    return network_on_images(model, params, x, network_size(x.shape[1:3], size, square))


def _forward_impl(model: MidasSmall, variables: Any, x: jax.Array, out_hw: tuple[int, int]) -> jax.Array:
    depth = model.apply(variables, x, train=False)
    # run.py: F.interpolate(prediction[:, None], size=image size, mode="bicubic", align_corners=False).
    return resize(depth[..., None], out_hw, "bicubic", align_corners=False)[..., 0]


@functools.cache
def _forward() -> Callable[..., jax.Array]:
    """The jitted forward pass with the CPU fast path's compiler options (YNNPACK matrix products: MiDaS small
    ~1.6× faster on CPU; none elsewhere). Built on first use, not at import: choosing the options asks for
    JAX's backend, which must not start before ``jax.distributed.initialize`` in multi-process runs."""
    return jax.jit(
        _forward_impl, static_argnames=("model", "out_hw"), compiler_options=cpu_compiler_options("midas_small")
    )


def predict(
    variables: Any,
    images: np.ndarray,
    *,
    model: MidasSmall | None = None,
    size: int = 256,
    square: bool = False,
) -> np.ndarray:
    """Relative inverse depth of a batch of images at their own resolution.

    Preprocessing runs in NumPy/OpenCV (as the original does); the network and the bicubic upsampling back to
    ``(H, W)`` run in one function jitted per (model, image size): repeated calls with same-sized batches do
    not recompile. :func:`apply` is the same computation as a pure JAX function (to float rounding).

    Args:
        variables: ``MidasSmall`` variables, e.g. ``placejax.weights.load("midas_v21_small_256")``, or
            already folded ones (``fold_batch_norm``) with a ``folded_bn=True`` model.
        images: ``(N, H, W, 3)`` or ``(H, W, 3)`` RGB, uint8 or float in [0, 1].
        model: the network (default ``MidasSmall()``, the official architecture).
        size, square: see ``preprocess``.

    Returns:
        float32 NumPy ``(N, H, W)`` (or ``(H, W)``) relative inverse depth: bigger is closer, unknown scale and
        shift. The network output is ≥ 0; bicubic upsampling may undershoot slightly near edges, as in MiDaS.
    """
    images = np.asarray(images)
    single = images.ndim == 3
    if single:
        images = images[None]
    if images.ndim != 4 or images.shape[-1] != 3 or 0 in images.shape:
        raise ValueError(f"predict expects (N, H, W, 3) or (H, W, 3) RGB images, got shape {images.shape}")
    model = MidasSmall() if model is None else model
    x = np.stack([preprocess(im, size=size, square=square) for im in images])
    depth = np.asarray(_forward()(model, variables, jnp.asarray(x), tuple(images.shape[1:3])))
    return depth[0] if single else depth
