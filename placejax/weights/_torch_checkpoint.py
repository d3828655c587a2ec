"""Reads ``torch.save`` files into NumPy arrays without importing torch and without running their code.

A ``.pt``/``.pth`` file is a pickle, and unpickling an untrusted pickle can call any Python function. This
reader interprets the pickle itself (``_restricted_pickle``) instead of handing it to ``pickle.Unpickler``,
and treats every file as hostile input.

Promises, for any file whatsoever:
  * **Nothing in the file runs, and no file changes the reader.** Only ``collections.OrderedDict``,
    ``torch._utils._rebuild_tensor_v2`` / ``_rebuild_parameter`` and the ``torch.*Storage`` dtype markers are
    resolved, each to an immutable local stand-in whose call is interpreted here, never executed. Any other
    global (``os.system``, ``builtins.eval``, ``copyreg._reconstructor``, ...), calling anything that is not
    one of those rebuilders, BUILD on anything but a freshly made ``OrderedDict``, INST/OBJ/NEWOBJ(_EX), the
    extension registry (EXT1/2/4), text persistent ids and out-of-band buffers stop the load with
    ``UnsafeCheckpointError``. A load leaves no state behind that could change a later load.
  * **Bounded cost.** The tensor data held at once (storages read + arrays returned, views copied included:
    the materialisation budget) never exceeds ``max_bytes`` (``DEFAULT_MAX_BYTES`` = 4 GiB; a keyword
    argument of ``read_torch_checkpoint``). Before anything is allocated, each storage's declared size
    (element count × item size) must equal its zip record's size, the record's stored bytes must lie inside
    the file (uncompressed records: stored size == declared size), and a legacy storage must fit in the bytes
    left in the file. Compressed zip records (``torch.save`` writes none; deflate only, as ``torch.load``:
    bzip2, LZMA and encrypted records are refused) are inflated in bounded steps, only up to their declared
    size, and may expand at most 64×, each record and all storage records together (the decompression budget;
    1 MiB of expansion is exempt once per file, so a thousand small bombs cost what one does). Tensors are
    checked against their storage (offset, size, stride) and tensors whose strides make elements overlap
    (stride 0 over a dimension longer than 1, ...) are refused rather than expanded; identical views share
    one array, and the arrays returned hold at most twice the bytes of the storages they come from. The
    pickle is bounded in size (64 MiB), text-argument length, stack, MARK nesting, memo entries, objects
    created, container length and the hashing cost of dict keys (``PickleLimits``: tuple keys of at most 16
    items, integer keys within ±2**60, at most 1024 float or tuple keys); the state dict in depth (64),
    entries (2**20), key text (64 Mi characters), and a sub-dict may appear in it only once. Nothing recurses
    on file content, so no limit relies on Python's recursion limit.
  * **One error contract.** Every problem with the file's content raises ``TorchCheckpointError`` (a
    ``ValueError``) whose message starts with the file's path and says what is wrong;
    ``UnsafeCheckpointError`` (a subclass) when the file asks for something that could run code or change
    objects outside it. Tensor kinds that torch writes but this reader does not convert (complex, quantized,
    sparse, uint16/uint32/uint64, float8, tensor subclasses, ...) raise ``TorchCheckpointError`` naming the
    kind, not ``UnsafeCheckpointError``. Only a missing file (``FileNotFoundError``) or an invalid
    ``max_bytes`` (``ValueError``) raise anything else.

Limits: the zip central directory is parsed by ``zipfile`` before these checks (memory proportional to the
file's size); a hostile file can still make the reader allocate up to ``max_bytes`` (it can store that much
data, or compress it up to 64×), so lower ``max_bytes`` where that is too much.

Both container formats are read, told apart as ``torch.load`` does (``torch.serialization._is_zipfile``: a
zip local-file signature at byte 0 means zip, anything else legacy), so no file reads as a different
checkpoint here than in torch:
  * zip (PyTorch ≥ 1.6): ``<root>/data.pkl`` plus one raw storage per ``<root>/data/<key>``, where ``<root>``
    is the folder of the first record; little-endian unless ``<root>/byteorder`` is exactly ``big`` (values
    other than ``little``/``big`` are refused, as torch does). Duplicate record names are refused.
  * legacy (older files such as torchvision's ``vgg16-397923af.pth``): consecutive pickles (magic number,
    protocol, system info, the object, the storage keys) followed by each storage as an int64 element count
    and raw little-endian bytes. The older tar-based format (PyTorch < 0.4) is refused as unsupported.
"""

from __future__ import annotations

import io
import math
import os
import struct
import zipfile
from typing import Any, BinaryIO

import numpy as np

from placejax.weights._restricted_pickle import PickleRejected, describe
from placejax.weights._restricted_pickle import load as _load_pickle
from placejax.weights._torch_pickle import (
    _CHUNK,
    _COPY_FACTOR,
    _LEGACY_MAGIC,
    _LEGACY_PROTOCOL,
    _MAX_DEPTH,
    _MAX_ENTRIES,
    _MAX_KEY_CHARS,
    _MAX_RATIO,
    _MAX_RATIO_FREE,
    _PICKLE_LIMITS,
    _ZIP_SIGNATURE,
    DEFAULT_MAX_BYTES,
    TorchCheckpointError,
    UnsafeCheckpointError,
    _Hooks,
    _int_in,
    _short,
    _StorageRef,
    _TensorRef,
    _Unsupported,
    _unsupported_error,
)

__all__ = ["DEFAULT_MAX_BYTES", "TorchCheckpointError", "UnsafeCheckpointError", "read_torch_checkpoint"]

# --- reading the containers -----------------------------------------------------------------------------


class _Budget:
    """Counts the bytes of tensor data held, refusing any allocation that would pass ``max_bytes``."""

    def __init__(self, max_bytes: int, source: str):
        self.max_bytes = max_bytes
        self.used = 0
        self.storage_bytes = 0
        self.returned_bytes = 0
        self.source = source

    def take(self, n: int, what: str) -> None:
        if n > self.max_bytes - self.used:
            raise TorchCheckpointError(
                f"{self.source}: {what} needs {n} bytes, which would bring the tensor data held to "
                f"{self.used + n} bytes, over max_bytes={self.max_bytes}; pass a larger max_bytes to "
                "read_torch_checkpoint if the file is trusted and that much memory is available"
            )
        self.used += n


def _read_exact(f: BinaryIO, n: int) -> bytearray | None:
    """Reads exactly ``n`` bytes in bounded chunks into a fresh buffer; None if the stream ends first.

    Callers check ``n`` against the bytes the file can hold before calling: the buffer is allocated first.
    """
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        read = f.readinto(view[got : got + min(_CHUNK, n - got)])
        if not read:
            return None
        got += read
    return buf


class _Storages:
    """Reads each storage on first use, checking it against the budget before allocating."""

    def __init__(self, source: str, budget: _Budget, byteorder: str):
        self.source = source
        self.budget = budget
        self.byteorder = byteorder
        self.arrays: dict[str, np.ndarray] = {}
        self.given_away: set[str] = set()  # storages returned as an array themselves (no longer to be copied)

    def read_bytes(self, ref: _StorageRef, nbytes: int) -> bytearray:
        raise NotImplementedError

    def get(self, ref: _StorageRef) -> np.ndarray:
        if ref.key not in self.arrays:
            nbytes = ref.numel * ref.dtype.itemsize
            self.budget.take(nbytes, f"storage {ref.key} ({ref.numel} × {ref.dtype})")
            self.budget.storage_bytes += nbytes
            array = np.frombuffer(self.read_bytes(ref, nbytes), dtype=ref.dtype, count=ref.numel)
            if self.byteorder != "little" and ref.dtype.itemsize > 1:
                array.byteswap(inplace=True)  # in its own buffer: no second copy
            self.arrays[ref.key] = array
        return self.arrays[ref.key]


class _ZipStorages(_Storages):
    def __init__(self, source: str, budget: _Budget, byteorder: str, archive: zipfile.ZipFile, root: str):
        super().__init__(source, budget, byteorder)
        self.archive = archive
        self.root = root

    def check(self, refs: dict[str, _StorageRef]) -> None:
        """Every announced storage must be a record of exactly its declared size (nothing is read here), and
        the compressed ones together may expand at most ``_MAX_RATIO``× (``_MAX_RATIO_FREE`` bytes excepted)."""
        inflated = stored = 0
        for ref in refs.values():
            info = _member(self.archive, f"{self.root}data/{ref.key}", self.source)
            declared = ref.numel * ref.dtype.itemsize
            if info.file_size != declared:
                raise TorchCheckpointError(
                    f"{self.source}: storage {ref.key} is announced as {ref.numel} × {ref.dtype} "
                    f"({declared} bytes) but its record {info.filename} holds {info.file_size} bytes: corrupt file"
                )
            if info.compress_type != zipfile.ZIP_STORED:
                inflated += info.file_size
                stored += info.compress_size
        # Per record the ratio exempts small records; over the whole file the exemption is counted once, so
        # a thousand small bombs cost what one does.
        if inflated > max(_MAX_RATIO_FREE, _MAX_RATIO * stored):
            raise TorchCheckpointError(
                f"{self.source}: its compressed storage records would expand from {stored} to {inflated} bytes "
                f"in total, more than {_MAX_RATIO}× (the decompression budget): refused as a likely "
                "decompression bomb (torch.save writes uncompressed records; re-save the file with torch)"
            )

    def read_bytes(self, ref: _StorageRef, nbytes: int) -> bytearray:
        return _read_member(self.archive, f"{self.root}data/{ref.key}", nbytes, self.source)


class _LegacyStorages(_Storages):
    def __init__(self, source: str, budget: _Budget, f: BinaryIO, offsets: dict[str, int]):
        super().__init__(source, budget, "little")
        self.f = f
        self.offsets = offsets

    def read_bytes(self, ref: _StorageRef, nbytes: int) -> bytearray:
        self.f.seek(self.offsets[ref.key])
        data = _read_exact(self.f, nbytes)
        if data is None:
            raise TorchCheckpointError(f"{self.source}: file ends inside storage {ref.key}: truncated file")
        return data


def _member(archive: zipfile.ZipFile, name: str, source: str) -> zipfile.ZipInfo:
    try:
        return archive.getinfo(name)
    except KeyError:
        raise TorchCheckpointError(f"{source}: the zip archive has no record {_short(name)}: corrupt file") from None


def _read_member(archive: zipfile.ZipFile, name: str, limit: int, source: str) -> bytearray:
    """A zip record's bytes, decompressed only up to its declared size, which must not exceed ``limit``.

    Before anything is allocated the declared size is checked against what the file can hold: the record's
    stored bytes must lie inside the file, and may expand at most ``_MAX_RATIO``× if compressed.
    """
    info = _member(archive, name, source)
    if info.file_size > limit:
        raise TorchCheckpointError(
            f"{source}: record {_short(name)} declares {info.file_size} bytes, more than the {limit} expected"
        )
    if info.header_offset + info.compress_size > os.fstat(archive.fp.fileno()).st_size:
        raise TorchCheckpointError(
            f"{source}: record {_short(name)} extends past the end of the file: truncated or corrupt file"
        )
    if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        # torch.load (miniz) reads only these two; Python's zipfile would inflate bzip2 and LZMA in unbounded
        # steps (a few KB can become GBs before it cuts the output to the declared size).
        raise TorchCheckpointError(
            f"{source}: record {_short(name)} uses zip compression method {info.compress_type}; torch.save files "
            "hold stored or deflated records only (as torch.load reads them)"
        )
    if info.flag_bits & 0x1:
        raise TorchCheckpointError(f"{source}: record {_short(name)} is encrypted; torch.save never encrypts")
    if info.compress_type == zipfile.ZIP_STORED and info.file_size != info.compress_size:
        raise TorchCheckpointError(
            f"{source}: uncompressed record {_short(name)} declares {info.file_size} bytes but stores "
            f"{info.compress_size}: corrupt file"
        )
    if info.compress_type != zipfile.ZIP_STORED and info.file_size > max(
        _MAX_RATIO_FREE, _MAX_RATIO * info.compress_size
    ):
        raise TorchCheckpointError(
            f"{source}: compressed record {_short(name)} would expand from {info.compress_size} to "
            f"{info.file_size} bytes, more than {_MAX_RATIO}×: refused as a likely decompression bomb "
            "(torch.save writes uncompressed records; re-save the file with torch or store it uncompressed)"
        )
    try:
        with archive.open(info) as f:
            data = _read_exact(f, info.file_size)
            # zipfile stops at the declared size; a stream that still has data is inconsistent.
            overrun = data is not None and f.read(1) != b""
    except TorchCheckpointError:
        raise
    except Exception as err:  # zipfile reports damage with many exception types (BadZipFile, zlib.error, ...)
        raise TorchCheckpointError(
            f"{source}: damaged zip record {_short(name)} ({type(err).__name__}: {_short(str(err))}); "
            "truncated download?"
        ) from err
    if data is None or overrun:
        raise TorchCheckpointError(
            f"{source}: zip record {_short(name)} does not hold its declared {info.file_size} bytes: corrupt file"
        )
    return data


def _unpickle(f: BinaryIO, hooks: _Hooks, source: str, where: str) -> Any:
    try:
        return _load_pickle(f, hooks, _PICKLE_LIMITS)
    except PickleRejected as err:
        error = UnsafeCheckpointError if err.unsafe else TorchCheckpointError
        raise error(f"{source}: {err} (in {where})") from None


def _read_zip(path: str, f: BinaryIO, budget: _Budget) -> tuple[Any, _Storages]:
    try:
        archive = zipfile.ZipFile(f)
        infos = archive.infolist()
    except Exception as err:  # zipfile's parser raises BadZipFile, ValueError, struct.error, ...
        raise TorchCheckpointError(
            f"{path}: not a readable torch.save zip archive ({type(err).__name__}: {_short(str(err))}); truncated?"
        ) from err
    names = [info.filename for info in infos]
    if len(set(names)) != len(names):
        # Which copy a reader picks differs between implementations; refuse rather than guess.
        raise TorchCheckpointError(f"{path}: the zip archive holds several records of the same name: corrupt file")
    # caffe2/serialize/inline_container.cc: the archive's root folder is that of its first record.
    if not names or "/" not in names[0]:
        raise TorchCheckpointError(f"{path}: the zip archive's first record is not in a folder: not a torch.save file")
    root = names[0].split("/", 1)[0] + "/"
    byteorder = "little"
    if f"{root}byteorder" in names:
        raw = bytes(_read_member(archive, f"{root}byteorder", 16, path))
        if raw not in (b"little", b"big"):
            raise TorchCheckpointError(f"{path}: unknown byte order {raw!r} in {root}byteorder: corrupt file")
        byteorder = raw.decode()
    pickle_bytes = _read_member(archive, f"{root}data.pkl", _PICKLE_LIMITS.max_bytes, path)
    refs: dict[str, _StorageRef] = {}
    obj = _unpickle(io.BytesIO(pickle_bytes), _Hooks(refs), path, f"{root}data.pkl")
    storages = _ZipStorages(path, budget, byteorder, archive, root)
    storages.check(refs)
    return obj, storages


def _read_legacy(path: str, f: BinaryIO, budget: _Budget) -> tuple[Any, _Storages]:
    head = f.read(512)
    if len(head) == 512 and head[257:262] == b"ustar":
        raise TorchCheckpointError(f"{path}: a tar-based torch.save file (PyTorch < 0.4), which is not supported")
    f.seek(0)
    header = [_unpickle(f, _Hooks(None), path, "the legacy header") for _ in range(3)]
    if not (_int_in(header[0], 0, 1 << 80) and header[0] == _LEGACY_MAGIC):
        raise TorchCheckpointError(f"{path}: neither a zip archive nor a legacy torch.save file (bad magic number)")
    if not (type(header[1]) is int and header[1] == _LEGACY_PROTOCOL):
        raise TorchCheckpointError(f"{path}: unsupported legacy protocol version {describe(header[1])}")
    refs: dict[str, _StorageRef] = {}
    obj = _unpickle(f, _Hooks(refs), path, "the legacy object pickle")
    keys = _unpickle(f, _Hooks(None), path, "the legacy storage key list")
    if type(keys) is not list or not all(type(k) is str for k in keys) or len(set(keys)) != len(keys):
        raise TorchCheckpointError(f"{path}: the storage key list is {describe(keys)}, not a list of distinct names")
    if set(keys) != set(refs):
        raise TorchCheckpointError(f"{path}: the storage key list does not match the tensors; corrupt file")
    size = os.fstat(f.fileno()).st_size
    offsets = {}
    for key in keys:
        ref = refs[key]
        count_bytes = f.read(8)
        if len(count_bytes) != 8:
            raise TorchCheckpointError(f"{path}: file ends before storage {key}: truncated file")
        (count,) = struct.unpack("<q", count_bytes)
        if count != ref.numel:
            raise TorchCheckpointError(f"{path}: storage {key} has {count} elements, the pickle said {ref.numel}")
        nbytes = ref.numel * ref.dtype.itemsize
        offsets[key] = f.tell()
        if nbytes > size - offsets[key]:
            raise TorchCheckpointError(
                f"{path}: storage {key} declares {ref.numel} × {ref.dtype} = {nbytes} bytes but only "
                f"{size - offsets[key]} bytes are left in the file: truncated or corrupt file"
            )
        f.seek(nbytes, os.SEEK_CUR)
    return obj, _LegacyStorages(path, budget, f, offsets)


# --- from references to arrays --------------------------------------------------------------------------


def _overlapping(shape: tuple[int, ...], stride: tuple[int, ...]) -> bool:
    """False when no two indices can reach the same element (strides nest, as for any slice or permutation).

    A sufficient test: sorted by stride, each dimension's stride must exceed the span of all smaller ones.
    Views that pass it are exactly those reachable by slicing, transposing and permuting a contiguous tensor.
    """
    span = 0
    for stride_i, n in sorted((s, n) for n, s in zip(shape, stride, strict=True) if n > 1):
        if stride_i <= span:
            return True
        span += (n - 1) * stride_i
    return False


class _Tensors:
    """Turns tensor references into NumPy arrays, sharing one array between identical views (tied weights)."""

    def __init__(self, storages: _Storages, budget: _Budget, source: str):
        self.storages = storages
        self.budget = budget
        self.source = source
        self.done: dict[_TensorRef, np.ndarray] = {}

    def array(self, ref: _TensorRef, key: str) -> np.ndarray:
        if ref in self.done:
            return self.done[ref]
        where = f"{self.source}: tensor {_short(key)!r} (shape {ref.shape}, stride {ref.stride}, offset {ref.offset})"
        numel = math.prod(ref.shape)
        if numel == 0:
            return np.zeros(ref.shape, ref.storage.dtype)
        if _overlapping(ref.shape, ref.stride):
            raise TorchCheckpointError(
                f"{where} has strides that make elements overlap (an expanded or broadcast view); the reader "
                "refuses to expand it into new memory. Save a .contiguous() copy of it instead"
            )
        extent = ref.offset + sum((n - 1) * s for n, s in zip(ref.shape, ref.stride, strict=True))
        if extent >= ref.storage.numel:
            raise TorchCheckpointError(
                f"{where} overruns its storage {ref.storage.key} of {ref.storage.numel} elements: corrupt file"
            )
        flat = self.storages.get(ref.storage)
        nbytes = numel * flat.itemsize
        if self.budget.returned_bytes + nbytes > _COPY_FACTOR * self.budget.storage_bytes:
            raise TorchCheckpointError(
                f"{where}: the tensors would hold more than {_COPY_FACTOR}× the bytes of their storages; "
                "a state dict does not view the same data that many times: corrupt or malicious file"
            )
        self.budget.returned_bytes += nbytes
        contiguous = tuple(int(math.prod(ref.shape[i + 1 :])) for i in range(len(ref.shape)))
        whole = (
            ref.offset == 0
            and numel == flat.size
            and all(s == c for n, s, c in zip(ref.shape, ref.stride, contiguous, strict=True) if n > 1)
        )
        if whole and ref.storage.key not in self.storages.given_away:
            # The tensor is its storage: hand out the storage's own buffer instead of a copy.
            self.storages.given_away.add(ref.storage.key)
            out = flat.reshape(ref.shape)
        else:
            self.budget.take(nbytes, f"tensor {_short(key)!r}")
            view = np.lib.stride_tricks.as_strided(
                flat[ref.offset :],
                shape=ref.shape,
                strides=tuple(s * flat.itemsize for s in ref.stride),
                writeable=False,
            )
            out = np.array(view, order="C")  # an owned C-contiguous copy, whatever the strides
        self.done[ref] = out
        return out


def _flatten_state_dict(obj: dict, tensors: _Tensors, path: str) -> dict[str, np.ndarray]:
    """``{dotted key: array}`` in the file's order; iterative, with depth, entry and key-length bounds."""
    out: dict[str, np.ndarray] = {}
    entries = key_chars = 0
    stack: list[tuple[str, Any]] = [("", iter(obj.items()))]
    seen = {id(obj)}  # every dict walked: a state dict never holds the same sub-dict twice
    while stack:
        prefix, items = stack[-1]
        item = next(items, None)
        if item is None:
            stack.pop()
            continue
        k, v = item
        if not (type(k) is str or _int_in(k, -(1 << 63), 1 << 63)):
            raise TorchCheckpointError(f"{path}: state dict key {describe(k)} under {_short(prefix)!r} is not a name")
        key = f"{prefix}{k}"
        entries += 1
        key_chars += len(key)
        if entries > _MAX_ENTRIES or key_chars > _MAX_KEY_CHARS:
            raise TorchCheckpointError(
                f"{path}: the state dict has more than {_MAX_ENTRIES} entries or {_MAX_KEY_CHARS} characters "
                "of keys: corrupt or malicious file"
            )
        if isinstance(v, _TensorRef):
            out[key] = tensors.array(v, key)
        elif isinstance(v, dict):
            if id(v) in seen:
                # Also what a cycle looks like; refusing shared sub-dicts keeps the walk linear in the file.
                raise TorchCheckpointError(
                    f"{path}: state dict entry {_short(key)!r} is a dict already seen (it contains itself or "
                    "appears twice): corrupt or malicious file"
                )
            if len(stack) >= _MAX_DEPTH:
                raise TorchCheckpointError(
                    f"{path}: state dict nested deeper than {_MAX_DEPTH} levels at {_short(key)!r}"
                )
            seen.add(id(v))
            stack.append((f"{key}.", iter(v.items())))
        elif isinstance(v, _Unsupported):
            raise TorchCheckpointError(f"{path}: entry {_short(key)!r} {_unsupported_error(v)}")
        else:
            raise TorchCheckpointError(
                f"{path}: entry {_short(key)!r} is {describe(v)}, not a tensor; expected a state dict"
            )
    return out


def read_torch_checkpoint(path: str | os.PathLike, *, max_bytes: int = DEFAULT_MAX_BYTES) -> dict[str, np.ndarray]:
    """Reads the state dict of a ``torch.save`` file as NumPy arrays, safely and without torch.

    Safe for untrusted files: nothing in the file is executed, memory is bounded by ``max_bytes`` plus the
    fixed pickle limits, and every problem with the content is reported as ``TorchCheckpointError`` (see the
    module docstring for the exact promises).

    Args:
        path: a ``.pt``/``.pth`` file written by ``torch.save`` (zip or legacy format) holding a state
            dict, or a dict that keeps it under ``"model"`` or ``"state_dict"`` (e.g. next to an
            ``"optimizer"`` entry, whose pickle is checked but whose tensors are not read). Nested dicts of
            tensors are flattened with ``.``-joined keys.
        max_bytes: the most bytes of tensor data held at once, storages read plus arrays returned (default
            ``DEFAULT_MAX_BYTES``, 4 GiB). Raise it for larger trusted checkpoints.

    Returns:
        ``{key: array}`` in the file's order with the tensors' dtypes (bfloat16 via ``ml_dtypes``),
        C-contiguous and writable, in native byte order. Keys that are the same view of the same storage in
        the file (tied weights) share one array, as the tensors share memory after ``torch.load``.

    Raises:
        UnsafeCheckpointError: the pickle asks for anything beyond tensors and dicts (nothing is executed).
        TorchCheckpointError: truncated, corrupt, unsupported or over-limit file, or entries that are not
            tensors.
        FileNotFoundError: no such file.
        ValueError: ``max_bytes`` is not a non-negative int.

    Example:
        >>> state = read_torch_checkpoint("vgg16-397923af.pth")  # doctest: +SKIP
        >>> state["features.0.weight"].shape  # doctest: +SKIP
        (64, 3, 3, 3)
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no checkpoint file at {path}")
    if type(max_bytes) is not int or max_bytes < 0:
        raise ValueError(f"max_bytes must be a non-negative int, got {max_bytes!r}")
    budget = _Budget(max_bytes, path)
    try:
        with open(path, "rb") as f:
            is_zip = f.read(len(_ZIP_SIGNATURE)) == _ZIP_SIGNATURE
            f.seek(0)
            obj, storages = (_read_zip if is_zip else _read_legacy)(path, f, budget)
            if isinstance(obj, dict):
                for wrapper in ("model", "state_dict"):
                    if isinstance(obj.get(wrapper), dict):
                        obj = obj[wrapper]
                        break
            if not isinstance(obj, dict):
                raise TorchCheckpointError(f"{path}: holds {describe(obj)}, expected a state dict")
            return _flatten_state_dict(obj, _Tensors(storages, budget, path), path)
    except TorchCheckpointError:
        raise
    except Exception as err:
        # A net under the checks above: whatever else a hostile file provokes still honours the contract.
        raise TorchCheckpointError(
            f"{path}: could not be read ({type(err).__name__}: {_short(str(err))}); not a readable checkpoint"
        ) from err
