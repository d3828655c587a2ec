"""Public entry points of the HHA encoder: input checks, batching, streaming over large datasets."""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np

from placejax.hha._constants import MAX_DEPTH_M, MIN_DEPTH_M
from placejax.hha._encode import REFERENCE_HEIGHT, HeightRule, HHAResult, _encode_batch


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check_depth_dtype(x, name: str, depth_scale) -> None:
    """The dtype rule: floating depth is metres; integer depth needs an explicit ``depth_scale``; bool is refused."""
    dt = jnp.result_type(x)
    if dt == jnp.bool_:
        raise TypeError(f"{name} must be a float (metres) or integer (with depth_scale) array, got dtype bool")
    if jnp.issubdtype(dt, jnp.complexfloating) or not jnp.issubdtype(dt, jnp.number):
        raise TypeError(f"{name} must be a real float (metres) or integer array, got dtype {dt}")
    if jnp.issubdtype(dt, jnp.integer) and depth_scale is None:
        raise TypeError(
            f"{name} has integer dtype {dt}: give its unit explicitly, e.g. depth_scale=0.001 for millimetres "
            "(metres per unit); floating depth is taken as metres"
        )


def _check_scalar(value, name: str, *, allow_inf: bool = False) -> None:
    """A positive real number argument (not bool): finite, or +inf where ``allow_inf``. Traced values pass."""
    if isinstance(value, bool | np.bool_ | str | bytes):
        raise TypeError(f"{name} must be a real number, got {value!r}")
    if not _is_concrete(value):
        return
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a real number, got {value!r}") from None
    if not v > 0 or (math.isinf(v) and not allow_inf):
        raise ValueError(f"{name} must be a positive {'' if allow_inf else 'finite '}number, got {value!r}")


def intrinsics_valid(intrinsics) -> jax.Array:
    """Whether each pinhole matrix is usable by the encoder: all entries finite, fx = K[0, 0] > 0, fy = K[1, 1] > 0.

    Works on concrete and traced arrays (inside ``jit``/``vmap``), where :func:`encode` cannot raise: an image
    whose intrinsics fail this check comes out as entirely missing. Callers that trace the encoder can test their
    cameras with this (or ``jax.experimental.checkify``) beforehand.

    Args:
        intrinsics: ``(..., 3, 3)`` matrices.

    Returns:
        ``bool (...)``.
    """
    k = jnp.asarray(intrinsics)
    return jnp.all(jnp.isfinite(k), axis=(-2, -1)) & (k[..., 0, 0] > 0) & (k[..., 1, 1] > 0)


def _check_options(dtype, depth_scale, min_depth_m, max_depth_m) -> None:
    try:
        dt = jnp.dtype(dtype)
    except TypeError:
        raise TypeError(f"dtype must be a floating dtype (float32 or float64), got {dtype!r}") from None
    if dt not in (jnp.float32, jnp.float64):
        # float16/bfloat16 pass a "floating" test but the encoder's fits and linear solves need float32 at least.
        raise TypeError(f"dtype must be a floating dtype the encoder computes in (float32 or float64), got {dtype!r}")
    if depth_scale is not None:
        _check_scalar(depth_scale, "depth_scale")
    _check_scalar(min_depth_m, "min_depth_m")
    _check_scalar(max_depth_m, "max_depth_m", allow_inf=True)
    if _is_concrete(min_depth_m) and _is_concrete(max_depth_m) and not float(min_depth_m) < float(max_depth_m):
        raise ValueError(f"need min_depth_m < max_depth_m, got {min_depth_m!r} and {max_depth_m!r}")


def _check_intrinsics_dtype(intrinsics) -> None:
    kdt = jnp.result_type(intrinsics)
    if kdt == jnp.bool_ or not jnp.issubdtype(kdt, jnp.number) or jnp.issubdtype(kdt, jnp.complexfloating):
        raise TypeError(f"intrinsics must be a real float array, got dtype {kdt}")


def _as_intrinsics(intrinsics) -> jax.Array:
    _check_intrinsics_dtype(intrinsics)
    return jnp.asarray(intrinsics)


def _check_intrinsics(kn: np.ndarray, dtype=jnp.float32) -> None:
    """Finite in float64 and in the compute dtype, with focal lengths that are positive normal numbers there."""
    compute = jax.dtypes.canonicalize_dtype(dtype)
    if not np.all(np.isfinite(kn)):
        raise ValueError("intrinsics must be finite (fx, fy, cx, cy), got non-finite values")
    if np.any(kn[..., 0, 0] <= 0) or np.any(kn[..., 1, 1] <= 0):
        raise ValueError("intrinsics must have positive focal lengths fx = K[0, 0] and fy = K[1, 1]")
    with np.errstate(over="ignore"):
        kc = kn.astype(compute)
    tiny = np.finfo(compute).tiny
    if not np.all(np.isfinite(kc)) or np.any(kc[..., 0, 0] < tiny) or np.any(kc[..., 1, 1] < tiny):
        raise ValueError(
            f"intrinsics must be finite in the compute dtype {compute} with focal lengths fx = K[0, 0] and "
            f"fy = K[1, 1] normal numbers (at least {tiny:.3g}); got fx, fy = {float(kn[..., 0, 0].min())!r}, "
            f"{float(kn[..., 1, 1].min())!r}"
        )


def _check_integer_depth(x, name: str, dtype) -> None:
    """Concrete integer depth must convert to the compute dtype exactly (no wrap-around, no rounding)."""
    if not _is_concrete(x) or not jnp.issubdtype(jnp.result_type(x), jnp.integer):
        return
    a = np.asarray(x)
    if a.size == 0:
        return
    compute = jax.dtypes.canonicalize_dtype(dtype)
    exact = 1 << (np.finfo(compute).nmant + 1)  # every integer up to 2**24 (float32) is a float32
    if jnp.dtype(jax.dtypes.canonicalize_dtype(a.dtype)).itemsize < a.dtype.itemsize:
        exact = min(exact, int(np.iinfo(jax.dtypes.canonicalize_dtype(a.dtype)).max))  # x64 off: int64 → int32
    lo, hi = int(a.min()), int(a.max())
    if max(-lo, hi) > exact:
        raise ValueError(
            f"{name} holds integer values up to {max(-lo, hi)} (dtype {a.dtype}), beyond {exact}, the largest that "
            f"converts exactly to the compute dtype {compute}: scale it to metres as floating point first"
        )


def _host_or_traced(x):
    """``x`` as a NumPy array when it is host data (lists, scalars, NumPy arrays), else as a JAX array: host data
    is converted with NumPy and crosses into the compiled call once, instead of going through one eager JAX
    operation per conversion step (~0.1 ms each, several per call)."""
    if isinstance(x, jax.Array | jax.core.Tracer):
        return jnp.asarray(x)
    return np.asarray(x)


def _cast(x, dtype):
    """``x`` in ``dtype``; a NumPy array already in it is not copied."""
    return x.astype(dtype, copy=False) if isinstance(x, np.ndarray) else x.astype(dtype)


def _prepare(depth_m, intrinsics, raw_depth_m, dtype, depth_scale, min_depth_m, max_depth_m):
    """Checks shapes, dtypes and (when concrete) values; returns batched arrays and whether a batch axis was added."""
    _check_options(dtype, depth_scale, min_depth_m, max_depth_m)
    _check_depth_dtype(depth_m, "depth_m", depth_scale)
    _check_integer_depth(depth_m, "depth_m", dtype)
    compute = jax.dtypes.canonicalize_dtype(dtype)  # what the compiled call computes in (float32 unless x64)
    depth = _host_or_traced(depth_m)
    if depth.ndim not in (2, 3):
        raise ValueError(f"depth_m must have shape (H, W) or (B, H, W), got shape {tuple(depth.shape)}")
    squeeze = depth.ndim == 2
    if squeeze:
        depth = depth[None]
    b, h, w = depth.shape
    if h < 1 or w < 1:
        raise ValueError(f"depth_m must be a non-empty image, got shape {tuple(depth.shape)}")
    _check_intrinsics_dtype(intrinsics)
    kshape = tuple(np.shape(intrinsics))
    if kshape not in ((3, 3), (b, 3, 3)):
        raise ValueError(
            f"intrinsics must have shape (3, 3) or ({b}, 3, 3) to match depth_m {tuple(jnp.shape(depth_m))}, "
            f"got shape {kshape}"
        )
    if _is_concrete(intrinsics):
        # checked as given (float64), before jnp.asarray may cast it to float32 (where 1e39 is inf)
        _check_intrinsics(np.asarray(intrinsics, np.float64), dtype)
    k = _host_or_traced(intrinsics)
    k = (jnp if isinstance(k, jax.Array | jax.core.Tracer) else np).broadcast_to(k, (b, 3, 3))
    raw = None
    if raw_depth_m is not None:
        _check_depth_dtype(raw_depth_m, "raw_depth_m", depth_scale)
        _check_integer_depth(raw_depth_m, "raw_depth_m", dtype)
        raw = _host_or_traced(raw_depth_m)
        if raw.ndim == 2 and squeeze:
            raw = raw[None]
        if raw.shape != depth.shape:
            raise ValueError(
                f"raw_depth_m must have the same shape as depth_m {tuple(jnp.shape(depth_m))}, "
                f"got shape {tuple(jnp.shape(raw_depth_m))}"
            )
    depth = _cast(depth, compute)
    raw = None if raw is None else _cast(raw, compute)
    if depth_scale is not None:
        scale = np.asarray(depth_scale, compute) if _is_concrete(depth_scale) else jnp.asarray(depth_scale, compute)
        depth = depth * scale
        raw = None if raw is None else raw * scale
    k = _cast(k, compute)
    depth_range = np.asarray([min_depth_m, max_depth_m], compute)
    if not (_is_concrete(min_depth_m) and _is_concrete(max_depth_m)):
        depth_range = jnp.asarray([min_depth_m, max_depth_m], compute)
    return depth, k, raw, depth_range, squeeze


# ----------------------------------------------------------------------------------------------------------------------
# Running a batch on every core.

_POOL: dict[str, object] = {"pid": None, "size": 0, "pool": None}
_POOL_LOCK = threading.Lock()


def workers() -> int:
    """How many parts a concrete batch is split into on the CPU: the cores this process may run on (its affinity
    mask where the OS has one). ``PLACEJAX_HHA_WORKERS`` overrides it (1: one compiled call per batch)."""
    value = os.environ.get("PLACEJAX_HHA_WORKERS", "").strip()
    if value:
        try:
            n = int(value)
        except ValueError:
            raise ValueError(f"PLACEJAX_HHA_WORKERS must be a positive integer, got {value!r}") from None
        if n < 1:
            raise ValueError(f"PLACEJAX_HHA_WORKERS must be a positive integer, got {value!r}")
        return n
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _pool(n: int) -> ThreadPoolExecutor:
    """One thread pool per process (rebuilt after a fork, whose child inherits no running threads)."""
    with _POOL_LOCK:
        if _POOL["pid"] != os.getpid() or _POOL["size"] < n:
            pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="placejax-hha")
            _POOL.update(pid=os.getpid(), size=n, pool=pool)
        return _POOL["pool"]


def _check_height(height) -> None:
    if not isinstance(height, HeightRule):
        raise TypeError(f"height must be a placejax.hha.HeightRule, got {type(height).__name__}")


def _parts(depth, k, raw, depth_range) -> int:
    """How many parts a batch runs in: one per core for concrete CPU arrays, else 1 (one compiled program)."""
    arrays = [x for x in (depth, k, raw, depth_range) if x is not None]
    if depth.shape[0] <= 1 or jax.default_backend() != "cpu" or any(isinstance(x, jax.core.Tracer) for x in arrays):
        return 1
    if any(d.platform != "cpu" for x in arrays if isinstance(x, jax.Array) for d in x.devices()):
        return 1
    return min(depth.shape[0], workers())


def _run(depth, k, raw, depth_range, full: bool, height: HeightRule = REFERENCE_HEIGHT):
    """``_encode_batch`` on the whole batch, or, for concrete CPU inputs, on contiguous parts of it, one per core,
    each from its own thread.

    XLA CPU splits every kernel of one image between the cores, and the kernels of a 256² image are too small
    for that to pay (two threads took twice the CPU time of one per image); whole images on separate cores
    scale instead. Each image's program is the same in every part, so the result is bit-identical to one
    call. Traced inputs (a caller's ``jit``/``vmap``) and other backends keep one program.
    """
    _check_height(height)
    n = _parts(depth, k, raw, depth_range)
    if n == 1:
        return _encode_batch(depth, k, raw, depth_range, full=full, height_rule=height)
    bounds = np.linspace(0, depth.shape[0], n + 1).round().astype(int)

    def part(i):
        a, z = bounds[i], bounds[i + 1]
        part_raw = None if raw is None else raw[a:z]
        out = _encode_batch(depth[a:z], k[a:z], part_raw, depth_range, full=full, height_rule=height)
        return jax.block_until_ready(out)  # the work runs on this thread, beside the other parts

    outs = list(_pool(n).map(part, range(n)))
    return jax.tree.map(lambda *xs: jnp.concatenate(xs), *outs)


def encode_full(
    depth_m,
    intrinsics,
    raw_depth_m=None,
    *,
    depth_scale: float | None = None,
    min_depth_m: float = MIN_DEPTH_M,
    max_depth_m: float = MAX_DEPTH_M,
    dtype=jnp.float32,
    height: HeightRule = REFERENCE_HEIGHT,
) -> HHAResult:
    """HHA image plus its intermediates (normals, gravity, height, angle); see :class:`HHAResult`.

    Args, conventions, dtype rules and ``jit`` behaviour as in :func:`encode`.
    """
    depth, k, raw, depth_range, squeeze = _prepare(
        depth_m, intrinsics, raw_depth_m, dtype, depth_scale, min_depth_m, max_depth_m
    )
    out = _run(depth, k, raw, depth_range, full=True, height=height)
    if squeeze:
        out = jax.tree_util.tree_map(lambda x: x[0], out)
    return out


def encode(
    depth_m,
    intrinsics,
    raw_depth_m=None,
    *,
    depth_scale: float | None = None,
    min_depth_m: float = MIN_DEPTH_M,
    max_depth_m: float = MAX_DEPTH_M,
    dtype=jnp.float32,
    height: HeightRule = REFERENCE_HEIGHT,
) -> jax.Array:
    """HHA encoding (Gupta et al., ECCV 2014) of metric depth images, as the original implementation computes it.

    Compiled once per input shape and dtype; a batch runs as a loop over its images inside the compiled code, so
    that each image's working set stays in cache, and a concrete batch on the CPU is split into one contiguous
    part per core (:func:`workers`), each run from its own thread. The same result comes out eagerly, under a caller's
    ``jax.jit`` and under ``jax.vmap``: whether every pixel is valid (the fast path) is decided on the data inside
    the compiled code, never from a Python-level look at it.

    Args:
        depth_m: ``(H, W)`` or ``(B, H, W)`` z-depth along the optical axis. **Floating** arrays are metres.
            **Integer** arrays (e.g. ``uint16`` millimetres) need their unit as ``depth_scale`` (metres per unit,
            0.001 for millimetres), otherwise ``TypeError``; ``bool`` and complex arrays are refused
            (``TypeError``). Pixels outside the valid range ``[min_depth_m, max_depth_m]`` (NaN, ±inf, zero,
            negative, sensor junk such as 1e-9 or 1e30) count as missing: they are left out of every fit, the
            gravity estimate and the floor height, and come out as (0, 0, 0).
        intrinsics: ``(3, 3)`` pinhole matrix shared by all images, or ``(B, 3, 3)`` one per image, in the 0-based
            OpenCV pixel convention (pixel (row i, col j) has u = j, v = i). A camera given 1-based (MATLAB
            style) has centre (cx − 1, cy − 1) here. Must be finite with fx = K[0, 0] > 0 and fy = K[1, 1] > 0:
            concrete intrinsics that are not raise ``ValueError``; traced ones (inside a caller's ``jit`` or
            ``vmap``) cannot raise, and an image with unusable intrinsics comes out entirely missing (all-zero
            HHA, ``valid`` all False, gravity (0, 1, 0)). Check traced cameras with :func:`intrinsics_valid`.
        raw_depth_m: optional raw depth of the same shape and the same units/dtype rules: where it is 0 (or
            outside the valid range) the pixel is missing for the normal and gravity estimates (the reference's
            ``missing = RD == 0``), while disparity and height still use ``depth_m``. ``None``: only invalid
            ``depth_m`` pixels are missing (the right choice for dense, e.g. monocular, depth).
        depth_scale: metres per unit of ``depth_m`` and ``raw_depth_m`` (both are multiplied by it); required for
            integer depth, optional for floating depth.
        min_depth_m, max_depth_m: the valid depth range in metres, inclusive, after ``depth_scale``; default
            0.1 m to 1000 m. ``0 < min_depth_m < max_depth_m``; ``max_depth_m`` may be ``inf``.
        dtype: compute dtype, float32 or float64 (float16/bfloat16 are refused: ``TypeError``); float32
            reproduces the reference (the normal fits are centred for that reason). Concrete integer depth must
            convert to it exactly (at most 2**24 units for float32), otherwise ``ValueError``.
        height: the height channel's floor and centimetres per level (:class:`HeightRule`); the default is the
            reference's (the lowest point as the floor, 1 cm per level).

    Returns:
        ``uint8 (..., H, W, 3)`` channels in the order (disparity, height, angle): 31000 / max(Z_cm, 100),
        height above the estimated floor in cm, and the normal's angle with gravity in degrees + 38 (180° where
        the normal is undefined), each rounded half to even and capped at 255; (0, 0, 0) at missing pixels.

    Raises:
        TypeError: a bool, complex or non-numeric depth, integer depth without ``depth_scale``, a ``dtype``
            other than float32/float64, or a non-numeric scalar argument.
        ValueError: wrong shapes, non-positive or non-finite ``depth_scale``/``min_depth_m``, an empty depth
            range, concrete integer depth that the compute dtype cannot hold exactly, or (concrete) intrinsics
            that are not finite with focal lengths that are positive normal numbers in the compute dtype.

    Example:
        >>> import numpy as np
        >>> from placejax import hha
        >>> k = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
        >>> hha.encode(np.full((48, 64), 2.0), k).shape
        (48, 64, 3)
        >>> hha.encode(np.full((48, 64), 2000, np.uint16), k, depth_scale=0.001)[0, 0].tolist()  # millimetres
        [155, 177, 128]
    """
    depth, k, raw, depth_range, squeeze = _prepare(
        depth_m, intrinsics, raw_depth_m, dtype, depth_scale, min_depth_m, max_depth_m
    )
    out = _run(depth, k, raw, depth_range, full=False, height=height)  # the intermediates are never computed
    return out[0] if squeeze else out


def encode_stream(
    depths: Iterable[np.ndarray],
    intrinsics,
    *,
    batch_size: int = 32,
    depth_scale: float | None = None,
    min_depth_m: float = MIN_DEPTH_M,
    max_depth_m: float = MAX_DEPTH_M,
    dtype=jnp.float32,
    height: HeightRule = REFERENCE_HEIGHT,
) -> Iterator[np.ndarray]:
    """Encodes a stream of ``(H, W)`` depth images in fixed-size batches, in bounded memory.

    Every batch has the same shape (the last one is padded), so the encoder compiles once for the whole stream,
    and at most one batch of inputs and outputs is held at a time: a 100k-image dataset streams through.
    The arguments are checked when this is called, each image when it arrives (a differing shape or a dtype the
    rules of :func:`encode` refuse raises, naming the image's position in the stream).

    Args:
        depths: iterable of ``(H, W)`` depth images, all of one shape; or of ``(depth, raw_depth)`` pairs
            (``raw_depth`` may be ``None``). Units and dtype rules as in :func:`encode`.
        intrinsics: ``(3, 3)`` finite matrix with positive focal lengths, shared by all images (0-based).
        batch_size: images per compiled call, a positive int.
        depth_scale, min_depth_m, max_depth_m, dtype, height: as in :func:`encode`.

    Yields:
        ``uint8 (H, W, 3)`` HHA images, one per input, in order.
    """
    if isinstance(batch_size, bool) or not isinstance(batch_size, int | np.integer) or batch_size < 1:
        raise ValueError(f"batch_size must be a positive int, got {batch_size!r}")
    # Every argument is checked now, not when the first batch is full.
    _check_options(dtype, depth_scale, min_depth_m, max_depth_m)
    _check_intrinsics_dtype(intrinsics)
    if np.shape(intrinsics) != (3, 3):
        raise ValueError(f"intrinsics must have shape (3, 3) for encode_stream, got shape {np.shape(intrinsics)}")
    _check_intrinsics(np.asarray(intrinsics, np.float64), dtype)  # as given, before any cast to float32
    k = np.asarray(_as_intrinsics(intrinsics))
    _check_height(height)
    kwargs = dict(depth_scale=depth_scale, min_depth_m=min_depth_m, max_depth_m=max_depth_m, dtype=dtype, height=height)
    return _stream(iter(depths), k, int(batch_size), kwargs)


def _stream(depths: Iterator, k: np.ndarray, batch_size: int, kwargs: dict) -> Iterator[np.ndarray]:
    buf: list = []
    shape = None
    for n, item in enumerate(depths):
        depth, raw = item if isinstance(item, tuple) else (item, None)
        if isinstance(item, tuple) and len(item) != 2:
            raise ValueError(f"encode_stream: item {n} is a tuple of {len(item)}, expected (depth, raw_depth)")
        depth = np.asarray(depth)
        raw = None if raw is None else np.asarray(raw)
        try:
            _check_depth_dtype(depth, "depth_m", kwargs["depth_scale"])
            if raw is not None:
                _check_depth_dtype(raw, "raw_depth_m", kwargs["depth_scale"])
        except TypeError as e:
            raise TypeError(f"encode_stream: item {n}: {e}") from None
        shape = depth.shape if shape is None else shape
        if depth.ndim != 2 or depth.shape != shape or (raw is not None and raw.shape != shape):
            raise ValueError(
                f"encode_stream: item {n} has shape {depth.shape}"
                + ("" if raw is None else f" (raw {raw.shape})")
                + f", expected one (H, W) shape for the whole stream: {shape}"
            )
        buf.append((depth, raw))
        if len(buf) == batch_size:
            yield from _encode_chunk(buf, k, batch_size, kwargs)
            buf = []
    if buf:
        yield from _encode_chunk(buf, k, batch_size, kwargs)


def _encode_chunk(pairs, k, batch_size, kwargs):
    # One dtype per batch without changing any value: floats stay floats (metres), integers stay integers.
    depth = np.stack([d for d, _ in pairs])
    has_raw = any(r is not None for _, r in pairs)
    raw = np.stack([d if r is None else r for d, r in pairs]) if has_raw else None
    n = len(pairs)
    if n < batch_size:  # pad with copies of the last image so the compiled shape never changes
        depth = np.concatenate([depth, np.repeat(depth[-1:], batch_size - n, 0)])
        if raw is not None:
            raw = np.concatenate([raw, np.repeat(raw[-1:], batch_size - n, 0)])
    out = np.asarray(encode(depth, k, raw, **kwargs))
    yield from out[:n]
