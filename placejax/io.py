"""Atomic file writes: a reader sees either the old file or the complete new one, never a half-written one.

Every file placejax writes (results, configs, grids, caches' manifests, converted weights, figures, benchmark
reports) goes through :func:`atomic_write`: the content is written to a temporary file in the target's folder,
flushed to disk, given ordinary permissions (``0o666`` minus the process umask, as ``open()`` would), then
renamed over the target. The temporary file lives beside the target because a rename is only atomic within one
filesystem; after a crash it is a dot-file ending in ``.tmp`` that no reader looks at.

Example::

    from placejax import io
    io.write_json("run/results.json", {"top1": 0.42})
    with io.atomic_write("run/table.md", "w") as f:
        f.write("| a | b |\\n")
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import socket
import stat
import sys
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import IO, Any

import numpy as np

__all__ = [
    "NPZ_MAX_BYTES",
    "NPZ_META_KEY",
    "NpzError",
    "atomic_write",
    "check_write_target",
    "file_kind",
    "file_sha256",
    "read_npz",
    "run_lock",
    "save_figure",
    "write_bytes",
    "write_json",
    "write_npz",
    "write_text",
]


# Errors of the write itself (a full disk or quota, a file over the size limit, an I/O error), which Python reports
# without the file's name.
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO})


def _umask() -> int:
    # os.umask can only be read by setting it; restore it at once (no thread in placejax changes it).
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def file_kind(mode: int) -> str:
    """What an ``st_mode`` is, for a message: ``"regular file"``, ``"folder"``, ``"FIFO"``, ``"socket"``, ..."""
    for test, name in (
        (stat.S_ISREG, "regular file"),
        (stat.S_ISDIR, "folder"),
        (stat.S_ISLNK, "symbolic link"),
        (stat.S_ISCHR, "character device"),
        (stat.S_ISBLK, "block device"),
        (stat.S_ISFIFO, "FIFO"),
        (stat.S_ISSOCK, "socket"),
    ):
        if test(mode):
            return name
    return "special file"


def check_write_target(path: str | os.PathLike) -> None:
    """Refuses a target that exists and is not a regular file: a rename would replace a device, a FIFO, a socket or
    a symbolic link (not the file it points to) with the new file — as root, ``/dev/null`` itself.

    Raises:
        FileExistsError: naming the path and what it is.
    """
    try:
        mode = os.lstat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return
    except OSError:
        return  # unreadable: the write itself will say why
    if not stat.S_ISREG(mode):
        raise FileExistsError(
            errno.EEXIST,
            f"exists and is a {file_kind(mode)}, not a regular file: placejax writes only new or regular files",
            str(path),
        )


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO[Any]]:
    """Opens a temporary file that replaces ``path`` when the ``with`` block ends without an exception.

    Args:
        path: the target (its folder is created).
        mode: ``"wb"`` (default) or ``"w"`` (UTF-8 text).

    Yields:
        The open temporary file. On an exception it is removed and ``path`` is left as it was.

    Raises:
        FileExistsError: ``path`` exists and is not a regular file (:func:`check_write_target`).
        OSError: the write failed; a full disk (``ENOSPC``, ``EDQUOT``), ``EFBIG`` or ``EIO`` with ``path`` as its
            ``filename`` and "... while writing" in its ``strerror`` (Python's own error names no file).
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"mode must be 'wb' or 'w', got {mode!r}")
    path = Path(path)
    check_write_target(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode, **({"encoding": "utf-8"} if mode == "w" else {})) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        # mkstemp creates the file 0600; a result file should be readable like any other file the user writes.
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        if e.errno in _WRITE_ERRNOS and e.filename is None:  # write() and fsync() name no file: name the target
            raise OSError(e.errno, f"{os.strerror(e.errno)} while writing", str(path)) from e
        raise
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Atomically writes ``data`` to ``path``."""
    with atomic_write(path) as f:
        f.write(data)


def write_text(path: str | os.PathLike, text: str) -> None:
    """Atomically writes ``text`` (UTF-8) to ``path``."""
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Atomically writes ``obj`` as indented, key-sorted JSON (equal objects give equal bytes)."""
    write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


# The entry of an ``.npz`` that holds its record (JSON as uint8 bytes) in files written with ``meta=``.
NPZ_META_KEY = "meta"
"""The entry of an ``.npz`` written with ``meta=`` that holds the record (key-sorted JSON as uint8 bytes)."""


def write_npz(
    path: str | os.PathLike,
    arrays: Mapping[str, np.ndarray],
    *,
    compressed: bool = False,
    meta: Mapping[str, Any] | None = None,
) -> None:
    """Atomically writes ``arrays`` as an ``.npz`` (uncompressed unless ``compressed``), with ``meta`` as key-sorted
    JSON under :data:`NPZ_META_KEY` when given (what :func:`read_npz` returns)."""
    arrays = dict(arrays)
    if meta is not None:
        arrays[NPZ_META_KEY] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), np.uint8)
    with atomic_write(path) as f:
        (np.savez_compressed if compressed else np.savez)(f, **arrays)


NPZ_MAX_BYTES = 4 << 30
"""Default budget of `read_npz`: the arrays of one ``.npz`` may hold at most this many bytes (4 GiB)."""
_NPZ_MAX_EXPANSION = 64  # deflate expands real weights 1-3x; a bomb expands ~1000x
_NPZ_EXPANSION_FREE = 1 << 20


class NpzError(ValueError):
    """An ``.npz`` file that is not a plain, bounded numpy archive; the message names the file and the limit."""


def _check_npz(source: str | os.PathLike | IO[bytes], max_bytes: int) -> None:
    # Checked from the zip directory and each member's .npy header before numpy allocates anything: zipfile
    # stops a member at its declared size, so the declared sizes bound the decompressed bytes, and a header whose
    # shape needs more bytes than its member holds is refused instead of allocated.
    import zipfile

    name = getattr(source, "name", source) if not isinstance(source, str | os.PathLike) else os.fspath(source)
    try:
        zf = zipfile.ZipFile(source)
    except (zipfile.BadZipFile, OSError) as e:
        raise NpzError(f"{name}: not an .npz archive ({e})") from e
    with zf:
        infos = zf.infolist()
        declared = sum(i.file_size for i in infos)
        packed = sum(i.compress_size for i in infos)
        if declared > max_bytes:
            raise NpzError(f"{name}: members declare {declared} bytes, over the budget of {max_bytes} (max_bytes=)")
        if declared > _NPZ_EXPANSION_FREE + _NPZ_MAX_EXPANSION * packed:
            raise NpzError(f"{name}: members expand {declared} / {packed} bytes, over {_NPZ_MAX_EXPANSION}x")
        for i in infos:
            if i.flag_bits & 0x1 or i.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
                raise NpzError(f"{name}: member {i.filename!r} is encrypted or not stored/deflated")
            if not i.filename.endswith(".npy"):
                continue
            with zf.open(i) as f:
                try:
                    version = np.lib.format.read_magic(f)
                    read_header = {(1, 0): np.lib.format.read_array_header_1_0}.get(
                        version, np.lib.format.read_array_header_2_0
                    )
                    shape, _, dtype = read_header(f)
                except (ValueError, SyntaxError) as e:
                    raise NpzError(f"{name}: member {i.filename!r} has a bad .npy header ({e})") from e
                if dtype.hasobject:
                    raise NpzError(f"{name}: member {i.filename!r} holds Python objects")
                need = int(np.prod(shape, dtype=object)) * dtype.itemsize
                if need > i.file_size:
                    raise NpzError(
                        f"{name}: member {i.filename!r} declares shape {shape} ({need} bytes) in {i.file_size} bytes"
                    )
    if hasattr(source, "seek"):
        source.seek(0)


def read_npz(
    source: str | os.PathLike | IO[bytes], *, max_bytes: int = NPZ_MAX_BYTES
) -> tuple[dict[str, np.ndarray], dict[str, Any] | None]:
    """``(arrays, meta)`` of an ``.npz`` (a path or a binary file object); ``meta`` is None when it has none.

    The one reader of placejax's npz records: ``placejax.weights.read_record`` (weights records: the shipped
    depth network and trunks, exported ones) builds on it. A file from elsewhere is read within a budget checked
    before anything is allocated: at most ``max_bytes`` of arrays, deflate expanding at most 64x, no encrypted
    or otherwise compressed members, no Python objects, and every ``.npy`` header's shape within its member.

    Raises:
        NpzError: the file breaks one of those rules (the message names the file and the limit).
    """
    _check_npz(source, max_bytes)
    with np.load(source) as z:
        meta = json.loads(bytes(z[NPZ_META_KEY]).decode()) if NPZ_META_KEY in z.files else None
        arrays = {k: np.asarray(z[k]) for k in z.files if k != NPZ_META_KEY}
    return arrays, meta


def save_figure(fig: Any, path: str | os.PathLike, **savefig_kwargs: Any) -> None:
    """Atomically saves a matplotlib figure; the format comes from ``path``'s suffix."""
    fmt = Path(path).suffix.lstrip(".") or "png"
    with atomic_write(path) as f:
        fig.savefig(f, format=fmt, **savefig_kwargs)


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes (hex), read in 4 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


@contextlib.contextmanager
def run_lock(folder: str | os.PathLike, *, hint: str = "use another folder", wait: bool = False) -> Iterator[None]:
    """Exclusive use of a folder by one process: a second holder fails at once (or, with ``wait``, waits its turn)
    instead of colliding later.

    The lock is an ``flock`` on ``folder/.lock`` (which names the holder: pid and host), so the kernel drops it
    when its process dies, however it dies; a stale ``.lock`` file left behind locks nothing. Not reentrant: a
    process that takes the lock of a folder it already holds fails (or waits forever) like any other.

    Args:
        folder: an existing folder.
        hint: what the error message tells the second run to do instead (e.g. which option names the folder).
        wait: block until the holder is done, after saying on stderr whom it waits for (Ctrl-C stops waiting).

    Raises:
        RuntimeError: another process holds the lock and ``wait`` is False (the message names it).
    """
    folder = Path(folder)
    with open(folder / ".lock", "a+") as f:  # held open for the whole block: closing it releases the lock
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            if not wait:
                message = f"{folder} is in use by another run ({holder}); wait for it to finish, or {hint}"
                raise RuntimeError(message) from None
            print(f"placejax: {folder} is in use ({holder}); waiting for it to finish", file=sys.stderr, flush=True)
            fcntl.flock(f, fcntl.LOCK_EX)
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        f.flush()
        yield
