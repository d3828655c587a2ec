"""A cache built by several processes together (``build_array_cache(..., shard=CacheShard(...))``): each computes
its share of the rows into its own resumable part, process 0 copies the parts in row order into the cache and
commits it exactly as a one-process build does (``placejax.data.cache``'s module docstring has the layout)."""

from __future__ import annotations

import glob
import json
import math
import os
from pathlib import Path

import numpy as np

from placejax import progress as _progress
from placejax.data import _cache_files as files

__all__ = ["build_shared"]


def build_shared(
    shard: files.CacheShard, root: Path, stem: str, full_key: dict, fn, *, chunk: int, extras, desc: str, progress: bool
) -> files.ArrayCache:
    """``build_array_cache`` by ``shard.count`` processes: this process's share, then process 0 commits."""
    final, digest, n = root / stem, files.cache_digest(full_key), full_key["n"]
    shape, dtype = tuple(full_key["shape"]), np.dtype(full_key["dtype"])
    try:
        files.open_array_cache(final, full_key)
        done = True
    except files.CacheError:
        done = False
    lo, hi = files.shard_rows(n, chunk, shard.index, shard.count)
    if not done and hi > lo:
        part = f"{stem}.shard{shard.index}of{shard.count}"
        # Another job building the same cache in the same root waits here for this share rather than write it too.
        with files._locked(root / f".{part}.lock"):
            mm, rows_done = files._open_partial(root / f"{part}.partial", digest, hi - lo, shape, dtype)
            label = f"{desc} [{shard.index + 1}/{shard.count}]"
            with _progress.bar(total=hi - lo, initial=rows_done, desc=label, unit="frame", disable=not progress) as bar:
                files._fill(mm, root / f"{part}.partial", digest, lo, rows_done, fn, chunk=chunk, name=stem, bar=bar)
            mm.flush()
            del mm
    # The cache is only written after this barrier, so every process has decided on the same state whether it
    # exists, and all of them pass the same barriers.
    shard.barrier(f"cache {stem}: shares built")
    if shard.index == 0:
        if not done:
            _assemble(shard.count, root, stem, full_key, chunk, extras)
        # This count's parts, a killed build's of another count, or those of a kill between commit and clean-up.
        for part in root.glob(f"{glob.escape(stem)}.shard*of*.partial"):
            files._discard(part)
    shard.barrier(f"cache {stem}: committed")
    return files.open_array_cache(final, full_key)


def _assemble(count: int, root: Path, stem: str, full_key: dict, chunk: int, extras) -> None:
    """Process 0 of a shared build: the shares copied in row order into one data file, and the cache committed."""
    final, partial, digest, n = root / stem, root / f"{stem}.partial", files.cache_digest(full_key), full_key["n"]
    shape, dtype = tuple(full_key["shape"]), np.dtype(full_key["dtype"])
    with files._locked(root / f".{stem}.lock"):
        complete = False
        if final.exists():
            try:  # another job may have finished it meanwhile
                files.open_array_cache(final, full_key)
                complete = True
            except files.CacheError:
                files._discard(final)
        if not complete:
            files._discard(partial)  # an assembly that was killed, or a one-process build of the same cache
            partial.mkdir(parents=True)
            # open_memmap writes the header a one-process build writes; the rows are then copied behind it.
            mm = np.lib.format.open_memmap(partial / files._DATA, mode="w+", dtype=dtype, shape=(n, *shape))
            files.reserve_space(partial / files._DATA)
            offset, row_bytes = mm.offset, mm.itemsize * math.prod(shape)
            del mm
            with open(partial / files._DATA, "r+b") as out:
                for i in range(count):
                    lo, hi = files.shard_rows(n, chunk, i, count)
                    if hi > lo:
                        part = root / f"{stem}.shard{i}of{count}.partial"
                        _copy_share(part, digest, hi - lo, shape, dtype, out, offset + lo * row_bytes)
                out.flush()
                os.fsync(out.fileno())
            manifest = files._commit(root, partial, final, full_key, extras)
            for f in manifest["sha256"]:  # hashed just now: this process need not read them again to open them
                st = (final / f).stat()
                files._VERIFIED.add((str(final / f), st.st_size, st.st_mtime_ns))


def _copy_share(part: Path, digest: str, rows: int, shape: tuple, dtype: np.dtype, out, at: int) -> None:
    """Appends the data of one process's finished share (``rows`` rows) to ``out`` at byte ``at``."""
    try:
        marker = json.loads((part / files._PROGRESS).read_text())
        src = np.load(part / files._DATA, mmap_mode="r")
    except (OSError, ValueError, EOFError) as e:
        raise files.CacheError(f"{part}: missing or unreadable share of a shared cache build ({e})") from None
    finished = isinstance(marker, dict) and marker.get("digest") == digest and marker.get("rows_done") == rows
    if not finished or src.shape != (rows, *shape) or src.dtype != dtype:
        raise files.CacheError(
            f"{part}: not a finished share of {rows} rows {dtype} {shape} (progress {marker}): the process that "
            "builds it did not finish it"
        )
    start, size = src.offset, src.nbytes
    del src
    with open(part / files._DATA, "rb") as f:
        f.seek(start)
        out.seek(at)
        while size:
            block = f.read(min(size, 1 << 24))
            if not block:
                raise files.CacheError(f"{part / files._DATA}: shorter than its header says")
            out.write(block)
            size -= len(block)
