"""Public entry points of the HHA encoder: input checks, batching, streaming over large datasets."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from placejax.hha._encode import HHAResult, _encode_batch


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _prepare(depth_m, intrinsics, raw_depth_m, dtype):
    """Checks shapes and values; returns batched arrays, whether a batch axis was added, and the dense flag."""
    depth = jnp.asarray(depth_m)
    if depth.ndim not in (2, 3):
        raise ValueError(f"depth_m must have shape (H, W) or (B, H, W), got shape {tuple(depth.shape)}")
    squeeze = depth.ndim == 2
    if squeeze:
        depth = depth[None]
    b, h, w = depth.shape
    if h < 1 or w < 1:
        raise ValueError(f"depth_m must be a non-empty image, got shape {tuple(depth.shape)}")
    k = jnp.asarray(intrinsics)
    if k.shape == (3, 3):
        k = jnp.broadcast_to(k, (b, 3, 3))
    elif k.shape != (b, 3, 3):
        raise ValueError(
            f"intrinsics must have shape (3, 3) or ({b}, 3, 3) to match depth_m {tuple(jnp.shape(depth_m))}, "
            f"got shape {tuple(k.shape)}"
        )
    if _is_concrete(k):
        kn = np.asarray(k, np.float64)
        if not np.all(np.isfinite(kn)):
            raise ValueError("intrinsics must be finite (fx, fy, cx, cy), got non-finite values")
        if np.any(kn[:, 0, 0] <= 0) or np.any(kn[:, 1, 1] <= 0):
            raise ValueError("intrinsics must have positive focal lengths fx = K[0, 0] and fy = K[1, 1]")
    raw = None
    if raw_depth_m is not None:
        raw = jnp.asarray(raw_depth_m)
        if raw.ndim == 2 and squeeze:
            raw = raw[None]
        if raw.shape != depth.shape:
            raise ValueError(
                f"raw_depth_m must have the same shape as depth_m {tuple(jnp.shape(depth_m))}, "
                f"got shape {tuple(jnp.shape(raw_depth_m))}"
            )
    depth = depth.astype(dtype)
    k = k.astype(dtype)
    # When every pixel is known to be usable, the fit mask is the same for all images and its window moments are
    # computed once per call. Only decidable on concrete input; under an outer jit the general path runs.
    if raw is None and _is_concrete(depth):
        dn = np.asarray(depth)
        if not np.all(np.isfinite(dn) & (dn > 0)):
            raw = jnp.ones(depth.shape, dtype)  # depth's own invalid pixels are masked inside
    elif raw is not None:
        raw = raw.astype(dtype)
    return depth, k, raw, squeeze


def encode_full(depth_m, intrinsics, raw_depth_m=None, *, dtype=jnp.float32) -> HHAResult:
    """HHA image plus its intermediates (normals, gravity, height, angle); see :class:`HHAResult`.

    Args and conventions as in :func:`encode`.
    """
    depth, k, raw, squeeze = _prepare(depth_m, intrinsics, raw_depth_m, dtype)
    out = _encode_batch(depth, k, raw)
    if squeeze:
        out = jax.tree_util.tree_map(lambda x: x[0], out)
    return out


def encode(depth_m, intrinsics, raw_depth_m=None, *, dtype=jnp.float32) -> jax.Array:
    """HHA encoding (Gupta et al., ECCV 2014) of metric depth images, as the original implementation computes it.

    Compiled once per input shape and dtype; a batch runs as one ``vmap`` of the single-image encoder.

    Args:
        depth_m: ``(H, W)`` or ``(B, H, W)`` depth in **metres** (z-depth along the optical axis). Pixels that are
            NaN, ±inf, zero or negative count as missing: they are left out of every fit and come out as
            (0, 0, 0).
        intrinsics: ``(3, 3)`` pinhole matrix shared by all images, or ``(B, 3, 3)`` one per image, in the 0-based
            OpenCV pixel convention (pixel (row i, col j) has u = j, v = i). A camera given 1-based (MATLAB
            style) has centre (cx − 1, cy − 1) here.
        raw_depth_m: optional raw depth of the same shape: where it is 0 the pixel is missing for the normal and
            gravity estimates (the reference's ``missing = RD == 0``), while disparity and height still use
            ``depth_m``. ``None``: nothing is missing (the right choice for dense, e.g. monocular, depth).
        dtype: compute dtype; float32 reproduces the reference (the normal fits are centred for that reason).

    Returns:
        ``uint8 (..., H, W, 3)`` channels in the order (disparity, height, angle): 31000 / max(Z_cm, 100),
        height above the estimated floor in cm, and the normal's angle with gravity in degrees + 38 (180° where
        the normal is undefined), each rounded half to even and capped at 255.

    Example:
        >>> import numpy as np
        >>> from placejax import hha
        >>> k = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
        >>> hha.encode(np.full((48, 64), 2.0), k).shape
        (48, 64, 3)
    """
    return encode_full(depth_m, intrinsics, raw_depth_m, dtype=dtype).hha


def encode_stream(
    depths: Iterable[np.ndarray], intrinsics, *, batch_size: int = 32, dtype=jnp.float32
) -> Iterator[np.ndarray]:
    """Encodes a stream of ``(H, W)`` depth images in fixed-size batches, in bounded memory.

    Every batch has the same shape (the last one is padded), so the encoder compiles once for the whole stream,
    and at most one batch of inputs and outputs is held at a time: a 100k-image dataset streams through.

    Args:
        depths: iterable of ``(H, W)`` metric depth images, all of one shape; or of ``(depth, raw_depth)`` pairs.
        intrinsics: ``(3, 3)`` matrix shared by all images (0-based convention).
        batch_size: images per compiled call.

    Yields:
        ``uint8 (H, W, 3)`` HHA images, one per input, in order.
    """
    buf: list = []
    for item in depths:
        buf.append(item)
        if len(buf) == batch_size:
            yield from _encode_chunk(buf, intrinsics, batch_size, dtype)
            buf = []
    if buf:
        yield from _encode_chunk(buf, intrinsics, batch_size, dtype)


def _encode_chunk(items, intrinsics, batch_size, dtype):
    pairs = [it if isinstance(it, tuple) else (it, None) for it in items]
    depth = np.stack([np.asarray(d, np.float32) for d, _ in pairs])
    has_raw = any(r is not None for _, r in pairs)
    raw = np.stack([np.asarray(d if r is None else r, np.float32) for d, r in pairs]) if has_raw else None
    n = len(items)
    if n < batch_size:  # pad with copies of the last image so the compiled shape never changes
        depth = np.concatenate([depth, np.repeat(depth[-1:], batch_size - n, 0)])
        if raw is not None:
            raw = np.concatenate([raw, np.repeat(raw[-1:], batch_size - n, 0)])
    out = np.asarray(encode(depth, intrinsics, raw, dtype=dtype))
    yield from out[:n]
