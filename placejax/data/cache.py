"""On-disk caches of per-frame arrays: written once, chunk by chunk, atomically, resumable after a kill.

Two entry points share one mechanism:

* :func:`cache_session` — a session's images decoded, made upright, undistorted and resized once into a memory-
  mapped ``uint8 (N, H, W, 3)`` array with its utimes, poses and intrinsics. Works for any
  :class:`~placejax.data.Session` (NCLT, SimCampus, ...). Returns a :class:`CachedSession`, itself a Session.
* :func:`build_array_cache` — any derived per-frame array (depth maps, HHA images, conv features) produced by a
  function of a frame range.

Layout under ``root``::

    <name>-<digest>/            complete cache (only ever appears by an atomic rename)
        manifest.json           key, shapes, dtypes, SHA-256 of every file, "complete": true
        data.npy                the (N, ...) array, read back with np.load(mmap_mode="r")
        <extra>.npy             small per-session arrays (utimes, poses, intrinsics)
    <name>-<digest>.partial/    build in progress: data.npy + progress.json (rows done), resumed on rerun
    <name>-<digest>.shard<i>of<n>.partial/   process i's share of a build by n processes (same two files)
    .<name>-<digest>.lock       serialises concurrent builders of the same cache

``digest`` hashes the key (the settings and the identity of the source), so a cache built with other settings or
from another source is simply a different folder and is never read; the manifest's key is checked again on open.
A cache whose files no longer match the checksums in its manifest (bit rot, a file edited or truncated by
hand), or whose manifest or extras are missing or corrupt, is discarded and rebuilt by the next builder.
A kill at any point leaves either the complete folder or a ``.partial`` one; the rerun continues from the last
chunk whose progress marker was written (after the chunk's data was flushed) and produces the same bytes as an
uninterrupted build.

Several processes of a job (one or several hosts, a work directory they share) build a cache together when the
caller passes a :class:`CacheShard` (``placejax.stages.Workspace.cache_shard``): process ``i`` of ``n`` computes
a contiguous, chunk-aligned share of the rows (:func:`shard_rows`) into its own resumable part, the processes meet
at a barrier, process 0 copies the parts in row order into the data file, hashes it and commits the cache as a
one-process build does, and after a second barrier every process opens it. ``fn`` is called on the same chunks
as in a one-process build, so the cache holds the same bytes (data, extras and manifest) whatever ``n``.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from placejax import progress as _progress
from placejax.data import camera as _camera
from placejax.data._cache_files import (
    _SESSION_EXTRAS,
    ArrayCache,
    CacheError,
    CacheShard,
    _commit,
    _discard,
    _fill,
    _locked,
    _open_partial,
    _safe_name,
    cache_digest,
    open_array_cache,
    release_mapped_pages,
    shard_rows,
)
from placejax.data._shared_build import build_shared
from placejax.data.session import Session, session_identity

__all__ = [
    "ArrayCache",
    "CacheError",
    "CacheShard",
    "CachedSession",
    "build_array_cache",
    "cache_digest",
    "cache_session",
    "open_array_cache",
    "open_session_cache",
    "release_mapped_pages",
    "session_identity",
    "shard_rows",
]


def build_array_cache(
    root: str | os.PathLike,
    name: str,
    n: int,
    fn: Callable[[int, int], np.ndarray],
    shape: tuple[int, ...],
    dtype: Any,
    *,
    key: Mapping[str, Any],
    extras: Mapping[str, np.ndarray] | None = None,
    chunk: int = 64,
    progress: bool = True,
    desc: str | None = None,
    shard: CacheShard | None = None,
) -> ArrayCache:
    """Builds (or reuses) the cache of ``n`` per-frame arrays ``fn(start, stop)`` under ``root``.

    Example (an HHA cache the experiment could build from a depth cache)::

        hha = build_array_cache(root, "WI-hha", len(depth.data), lambda a, b: encode(depth.data[a:b]),
                                (224, 224, 3), np.uint8, key={"depth": depth.key, "hha": hha_settings})

    Args:
        root: folder holding caches.
        name: human-readable cache name (session name + what it holds); sanitised for the filesystem.
        n: number of frames.
        fn: ``fn(start, stop)`` → array ``(stop - start, *shape)`` of frames ``start..stop-1``; must be
            deterministic, which is what makes a resumed build equal to an uninterrupted one.
        shape: per-frame shape.
        dtype: array dtype.
        key: everything that determines the content (settings, identity of the source), JSON-serialisable.
            Different keys live in different folders.
        extras: small arrays stored beside the data (e.g. utimes); part of the cache, not of the key.
        chunk: frames per write; progress is committed after each chunk.
        progress: show progress (``placejax.progress``).
        desc: bar label, default ``name``.
        shard: with ``count > 1``, this process's part in a build by several processes that all make this call
            (see the module docstring): ``fn`` is called only on this process's rows, and the call returns once
            every process has built its share and process 0 has committed the cache. ``None`` (or ``count == 1``):
            this process builds the whole cache, and other processes asking for it meanwhile wait for its lock.

    Returns:
        The complete cache with ``data`` memory-mapped read-only.
    """
    if n < 1 or chunk < 1:
        raise ValueError(f"cache {name!r}: need n >= 1 frames and chunk >= 1, got n={n}, chunk={chunk}")
    for k in extras or {}:
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", k) or k == "data":
            raise ValueError(f"cache {name!r}: extra name {k!r} must be an identifier other than 'data'")
    shape = tuple(int(s) for s in shape)
    dtype = np.dtype(dtype)
    full_key = {"user": dict(key), "n": int(n), "shape": list(shape), "dtype": dtype.str}
    digest = cache_digest(full_key)
    root = Path(root)
    stem = f"{_safe_name(name)}-{digest}"
    final, partial = root / stem, root / f"{stem}.partial"
    if shard is not None and shard.count > 1:
        return build_shared(
            shard, root, stem, full_key, fn, chunk=chunk, extras=extras, desc=desc or name, progress=progress
        )

    with contextlib.suppress(CacheError):
        return open_array_cache(final, full_key)
    with _locked(root / f".{stem}.lock"):
        if final.exists():
            try:  # another process may have finished it while we waited for the lock
                return open_array_cache(final, full_key)
            except CacheError:
                _discard(final)  # never trust a folder without a matching complete manifest
        mm, rows_done = _open_partial(partial, digest, n, shape, dtype)
        bar = _progress.bar(total=n, initial=rows_done, desc=desc or name, unit="frame", disable=not progress)
        with bar:
            _fill(mm, partial, digest, 0, rows_done, fn, chunk=chunk, name=name, bar=bar)
        mm.flush()
        del mm
        _commit(root, partial, final, full_key, extras)
    return open_array_cache(final, full_key)


class CachedSession:
    """A session read back from its cache; satisfies :class:`~placejax.data.Session`.

    Attributes:
        name, utimes, poses, intrinsics, image_shape: as in :class:`~placejax.data.Session` (intrinsics are
            those of the cached, resized images).
        images: read-only memmap ``uint8 (N, H, W, 3)``; slicing it reads only the frames asked for.
        path: the cache folder.
        key: what the cache was built from.
    """

    def __init__(self, cache: ArrayCache):
        self._cache = cache
        self.path = cache.path
        self.key = cache.key
        self.name = cache.key["user"]["name"]
        self.images = cache.data
        self.utimes = cache.extras["utimes"]
        self.poses = cache.extras["poses"]
        self.intrinsics = cache.extras["intrinsics"]
        self.image_shape = tuple(int(s) for s in self.images.shape[1:3])

    def __len__(self) -> int:
        return len(self.images)

    def image(self, i: int) -> np.ndarray:
        """Upright RGB ``uint8 (H, W, 3)`` of frame ``i`` (a copy, read from disk)."""
        return np.array(self.images[i])

    def __repr__(self) -> str:
        return f"CachedSession({self.name!r}, {len(self)} frames, image_shape={self.image_shape}, path={self.path})"


def cache_session(
    session: Session,
    root: str | os.PathLike,
    *,
    image_size: tuple[int, int] | None = None,
    chunk: int = 64,
    workers: int | None = None,
    progress: bool = True,
    shard: CacheShard | None = None,
) -> CachedSession:
    """Caches a session's upright RGB images at ``image_size`` (default: as the session returns them).

    The session does the decoding, rotation and undistortion (its own settings are part of its identity); the
    cache resizes (area averaging when shrinking) and transforms the intrinsics to match. Rerunning with the
    same session and settings reuses the cache; a killed build resumes.

    Args:
        session: any Session.
        root: cache folder.
        image_size: ``(H, W)`` of the cached images.
        chunk: frames per committed write.
        workers: threads decoding frames in parallel (OpenCV releases the GIL); default ``os.cpu_count()``
            up to 8. Frame order and the result do not depend on it.
        progress: show progress (``placejax.progress``).
        shard: this process's part in a build shared by several processes (:func:`build_array_cache`): it
            decodes only its share of the frames.

    Returns:
        The cached session (memory-mapped images).
    """
    src_hw = tuple(int(s) for s in session.image_shape)
    hw = tuple(int(s) for s in image_size) if image_size is not None else src_hw
    key = {
        "kind": "session_images",
        "name": session.name,
        "source": session_identity(session),
        "image_size": list(hw),
        "resize": "cv2.INTER_AREA when shrinking else INTER_LINEAR",
    }

    def frame(i: int) -> np.ndarray:
        img = session.image(i)
        if img.shape != (*src_hw, 3) or img.dtype != np.uint8:
            raise CacheError(
                f"session {session.name!r} frame {i}: image is {img.dtype} {img.shape}, expected uint8 {(*src_hw, 3)}"
            )
        return _camera.resize_image(img, hw)

    n_workers = workers if workers is not None else min(8, os.cpu_count() or 1)
    pool = ThreadPoolExecutor(n_workers) if n_workers > 1 else None

    def frames(start: int, stop: int) -> np.ndarray:
        images = pool.map(frame, range(start, stop)) if pool is not None else map(frame, range(start, stop))
        return np.stack(list(images))

    extras = {
        "utimes": np.asarray(session.utimes, dtype=np.int64),
        "poses": np.asarray(session.poses, dtype=np.float64),
        "intrinsics": _camera.resize_intrinsics(session.intrinsics, src_hw, hw),
    }
    try:
        cache = build_array_cache(
            root,
            f"{session.name}-rgb{hw[0]}x{hw[1]}",
            len(session),
            frames,
            (*hw, 3),
            np.uint8,
            key=key,
            extras=extras,
            chunk=chunk,
            progress=progress,
            desc=f"cache {session.name} {hw[0]}×{hw[1]}",
            shard=shard,
        )
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    return CachedSession(cache)


def open_session_cache(path: str | os.PathLike) -> CachedSession:
    """Reopens a complete session cache folder (e.g. one recorded next to an experiment's results)."""
    cache = open_array_cache(path)
    missing = [k for k in _SESSION_EXTRAS if k not in cache.extras]
    if missing or cache.key.get("user", {}).get("kind") != "session_images":
        raise CacheError(f"{path}: not a session image cache (missing {missing or 'kind'})")
    return CachedSession(cache)
