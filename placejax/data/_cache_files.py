"""The files of an array cache: its manifest, checksums, lock, partial build and commit (the primitives that
:mod:`placejax.data.cache` builds one-process caches from and :mod:`placejax.data._shared_build` several-process
ones)."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import fcntl
import hashlib
import json
import mmap
import os
import re
import shutil
import weakref
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from placejax import io

FORMAT_VERSION = 2  # 2: SHA-256 of every file in the manifest
_DATA = "data.npy"
_MANIFEST = "manifest.json"
_PROGRESS = "progress.json"
_SESSION_EXTRAS = ("utimes", "poses", "intrinsics")


class CacheError(RuntimeError):
    """A cache folder that is incomplete, stale or corrupt, or a producer that returned the wrong array."""


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def cache_digest(key: Mapping[str, Any]) -> str:
    """16 hex digits of the SHA-256 of the key's canonical JSON (sorted keys)."""
    try:
        text = _canonical(key)
    except (TypeError, ValueError) as e:
        raise TypeError(f"cache key must be JSON-serialisable (str, int, float, bool, lists, dicts): {e}") from None
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _safe_name(name: str) -> str:
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")
    if not safe:
        raise ValueError(f"cache name {name!r} has no usable characters")
    return safe


@dataclasses.dataclass(frozen=True)
class ArrayCache:
    """A complete cache: ``data`` is a read-only memmap ``(N, ...)``; ``extras`` small arrays loaded in RAM."""

    path: Path
    key: dict
    data: np.ndarray
    extras: dict[str, np.ndarray]


# Caches verified in this process (path, size, mtime): a cache is hashed once per process, not at every open.
_VERIFIED: set[tuple[str, int, int]] = set()

# The read-only memmaps of complete caches opened in this process, by id (weak: a map nobody holds is closed).
_OPEN_MAPS: weakref.WeakValueDictionary[int, np.memmap] = weakref.WeakValueDictionary()


def release_mapped_pages() -> int:
    """Drops this process's resident pages of every open cache memmap; returns the bytes of the maps advised.

    Reading a cache through its memory map leaves the pages read in the process's resident set (peak RSS counts
    them) for as long as the map is open, so a long run that reads many caches grows by their sizes. The files stay
    in the OS page cache: a later read maps the pages back without disk I/O, and the data are unchanged. Returns 0
    where ``madvise(MADV_DONTNEED)`` is not offered (the maps are left as they are).
    """
    advice = getattr(mmap, "MADV_DONTNEED", None)
    if advice is None:
        return 0
    released = 0
    for m in list(_OPEN_MAPS.values()):
        mm = getattr(m, "_mmap", None)
        if mm is None or mm.closed or not hasattr(mm, "madvise"):
            continue
        mm.madvise(advice)
        released += len(mm)
    return released


def _verify_checksums(path: Path, manifest: dict) -> None:
    sums = manifest.get("sha256")
    if not isinstance(sums, dict) or set(sums) != {_DATA, *(f"{e}.npy" for e in manifest["extras"])}:
        raise CacheError(f"{path / _MANIFEST}: no checksum for every file")
    for name, want in sorted(sums.items()):
        f = path / name
        try:
            st = f.stat()
        except OSError as e:
            raise CacheError(f"{f}: missing cache file ({e})") from None
        stamp = (str(f), st.st_size, st.st_mtime_ns)
        if stamp in _VERIFIED:
            continue
        if io.file_sha256(f) != want:
            raise CacheError(f"{f}: checksum mismatch (the file changed after the cache was written)")
        _VERIFIED.add(stamp)


def _manifest(key: Mapping, n: int, shape: tuple[int, ...], dtype: np.dtype, extras: Mapping) -> dict:
    return {
        "format_version": FORMAT_VERSION,
        "complete": True,
        "key": json.loads(_canonical(key)),
        "digest": cache_digest(key),
        "n": n,
        "shape": [n, *shape],
        "dtype": np.dtype(dtype).str,
        "extras": sorted(extras),
    }


def open_array_cache(path: str | os.PathLike, key: Mapping | None = None, *, verify: bool = True) -> ArrayCache:
    """Opens a complete cache folder; with ``key``, also checks it was built for that key.

    Args:
        path: the cache folder.
        key: the key it must have been built for.
        verify: check every file against the SHA-256 the manifest recorded (once per file per process), so
            bit rot or a file replaced by hand is found, and the builder rebuilds the cache instead of using it.

    Raises:
        CacheError: no complete manifest, a different key or format, a missing, corrupt or changed file, or a data
            file of the wrong size.
    """
    path = Path(path)
    mpath = path / _MANIFEST
    try:
        manifest = json.loads(mpath.read_text())
    except FileNotFoundError:
        raise CacheError(f"{path}: not a complete cache (no {_MANIFEST})") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CacheError(f"{mpath}: corrupt manifest ({e})") from None
    if not isinstance(manifest, dict) or not isinstance(manifest.get("extras", []), list):
        raise CacheError(f"{mpath}: corrupt manifest (not a JSON object)")
    # Every field read below, of its type: a flipped byte in a field's name must be this error, not a KeyError.
    kinds = {"shape": list, "dtype": str, "key": dict, "extras": list}
    wrong = [f for f, t in kinds.items() if not isinstance(manifest.get(f), t)]
    if wrong or not all(isinstance(n, str) for n in manifest["extras"]):
        raise CacheError(f"{mpath}: corrupt manifest (field(s) {wrong or ['extras']} missing or of another type)")
    if manifest.get("format_version") != FORMAT_VERSION or manifest.get("complete") is not True:
        raise CacheError(f"{mpath}: incomplete or format {manifest.get('format_version')} != {FORMAT_VERSION}")
    if key is not None and manifest.get("key") != json.loads(_canonical(key)):
        raise CacheError(f"{mpath}: stale cache, built for another key")
    if verify:
        _verify_checksums(path, manifest)
    try:
        data = np.load(path / _DATA, mmap_mode="r")
    except (OSError, ValueError) as e:
        raise CacheError(f"{path / _DATA}: unreadable cache data ({e})") from None
    if isinstance(data, np.memmap):  # an empty array is read into memory, not mapped
        _OPEN_MAPS[id(data)] = data
    if list(data.shape) != manifest["shape"] or data.dtype.str != manifest["dtype"]:
        raise CacheError(
            f"{path / _DATA}: holds {data.dtype} {data.shape}, manifest says {manifest['dtype']} {manifest['shape']}"
        )
    extras = {}
    for name in manifest["extras"]:
        try:
            extras[name] = np.load(path / f"{name}.npy")
        except (OSError, ValueError, EOFError) as e:
            raise CacheError(f"{path / name}.npy: missing or unreadable cache extra ({e})") from None
    return ArrayCache(path=path, key=manifest["key"], data=data, extras=extras)


@contextlib.contextmanager
def _locked(lock_path: Path):
    # flock is released by the kernel when the process dies, so a killed builder never leaves a stuck lock.
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    with open(lock_path, "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _discard(path: Path) -> None:
    """Removes a folder by renaming it aside first, so no reader ever sees it half-deleted."""
    if path.exists():
        trash = path.with_name(f".{path.name}.trash-{os.getpid()}")
        os.replace(path, trash)
        shutil.rmtree(trash)


def _open_partial(partial: Path, digest: str, n: int, shape: tuple[int, ...], dtype: np.dtype):
    """Returns ``(memmap, rows_done)``, resuming a previous build of the same key when one is usable."""
    data_path = partial / _DATA
    rows_done = 0
    if partial.is_dir():
        try:
            progress = json.loads((partial / _PROGRESS).read_text())
            mm = np.lib.format.open_memmap(data_path, mode="r+")
            if progress.get("digest") == digest and mm.shape == (n, *shape) and mm.dtype == dtype:
                rows_done = int(progress["rows_done"])
                if 0 <= rows_done <= n:
                    return mm, rows_done
            del mm
        except (OSError, ValueError, KeyError, TypeError, AttributeError, EOFError, json.JSONDecodeError):
            pass  # killed before the first marker, or foreign or corrupt content: start over
        _discard(partial)
    partial.mkdir(parents=True)
    mm = np.lib.format.open_memmap(data_path, mode="w+", dtype=dtype, shape=(n, *shape))
    reserve_space(data_path)
    return mm, 0


def reserve_space(path: Path) -> None:
    """Allocates the disk blocks of a (sparse) file now: a full disk is then an ``OSError`` (ENOSPC) naming the
    file here, instead of a SIGBUS later, when a write through its memory map finds no block to fill."""
    if not hasattr(os, "posix_fallocate"):  # not on macOS: the map's writes find out instead
        return
    with open(path, "r+b") as f:
        try:
            os.posix_fallocate(f.fileno(), 0, os.fstat(f.fileno()).st_size)
        except OSError as e:
            if e.errno in (errno.EOPNOTSUPP, errno.EINVAL):  # a file system without allocation: nothing to do
                return
            raise OSError(e.errno, f"{e.strerror} while reserving the cache file", str(path)) from None


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@dataclasses.dataclass(frozen=True)
class CacheShard:
    """This process's part in building caches together with the other processes of a job.

    Every process calls :func:`build_array_cache` (or :func:`cache_session`) for the same caches, in the same
    order, with the same arguments but its own ``CacheShard``; ``placejax.stages.Workspace.cache_shard`` is the
    JAX job's. The processes must see the cache root on one file system (a folder shared by the hosts).

    Attributes:
        index: this process, ``0 <= index < count``.
        count: the processes building together.
        barrier: ``barrier(name)`` returns once every process has called it; every process makes the same calls
            in the same order (``placejax.training.sync_processes``).
    """

    index: int
    count: int
    barrier: Callable[[str], None]

    def __post_init__(self):
        if not (isinstance(self.count, int) and isinstance(self.index, int) and 0 <= self.index < self.count):
            raise ValueError(
                f"CacheShard: need integers 0 <= index < count, got index={self.index}, count={self.count}"
            )


def shard_rows(n: int, chunk: int, index: int, count: int) -> tuple[int, int]:
    """Rows ``[lo, hi)`` that process ``index`` of ``count`` builds of an ``n``-row cache written ``chunk`` rows at a
    time: the ``ceil(n / chunk)`` chunks dealt out contiguously, shares differing by at most one chunk, every share
    starting on a chunk boundary (so ``fn`` sees the chunks of a one-process build). A share may be empty.

    >>> [shard_rows(10, 3, i, 2) for i in range(2)]
    [(0, 6), (6, 10)]
    """
    chunks = -(-n // chunk)
    return min(chunks * index // count * chunk, n), min(chunks * (index + 1) // count * chunk, n)


def _fill(mm, partial: Path, digest: str, lo: int, rows_done: int, fn, *, chunk: int, name: str, bar) -> None:
    """Computes rows ``rows_done..`` of ``mm`` (frames ``lo + row``) chunk by chunk, committing each chunk."""
    shape, dtype = mm.shape[1:], mm.dtype
    for start in range(rows_done, len(mm), chunk):
        stop = min(start + chunk, len(mm))
        a, b = lo + start, lo + stop
        block = np.asarray(fn(a, b))
        if block.shape != (b - a, *shape):
            raise CacheError(
                f"cache {name!r}: producer returned shape {block.shape} for frames {a}..{b - 1}, "
                f"expected {(b - a, *shape)}"
            )
        if block.dtype != dtype:
            if not np.can_cast(block.dtype, dtype, casting="same_kind"):
                raise CacheError(f"cache {name!r}: producer returned {block.dtype}, expected {dtype}")
            block = block.astype(dtype)
        mm[start:stop] = block
        # Data reaches the file before the marker that claims it, so a marker never overstates progress.
        mm.flush()
        io.write_json(partial / _PROGRESS, {"digest": digest, "rows_done": stop})
        bar.update(stop - start)


def _commit(root: Path, partial: Path, final: Path, full_key: dict, extras: Mapping | None) -> dict:
    """Writes the extras, the checksums and the manifest into ``partial`` (whose data file is complete) and renames
    it to ``final``; returns the manifest."""
    extras = {k: np.asarray(v) for k, v in (extras or {}).items()}
    for k, v in extras.items():
        np.save(partial / f"{k}.npy", v)
    # The manifest is written last inside the folder and the folder appears under its final name by an
    # atomic rename, so a complete-looking cache is always a complete one.
    n, shape = full_key["n"], tuple(full_key["shape"])
    manifest = _manifest(full_key, n, shape, np.dtype(full_key["dtype"]), extras)
    files = [partial / _DATA, *(partial / f"{k}.npy" for k in extras)]
    manifest["sha256"] = {f.name: io.file_sha256(f) for f in files}
    io.write_json(partial / _MANIFEST, manifest)
    (partial / _PROGRESS).unlink(missing_ok=True)
    _fsync_dir(partial)
    os.replace(partial, final)
    _fsync_dir(root)
    return manifest
