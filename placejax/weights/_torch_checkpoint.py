"""Reads ``torch.save`` files into NumPy arrays without importing torch and without running their code.

A ``.pt``/``.pth`` file is a pickle, and unpickling an untrusted pickle can call any Python function. Here the
unpickler resolves only the handful of globals a state dict of tensors needs (``collections.OrderedDict``,
``torch._utils._rebuild_tensor_v2``/``_rebuild_parameter`` and the ``torch.*Storage`` dtype markers), each
mapped to a harmless local stand-in; any other global (``os.system``, ``builtins.eval``, ...) stops the load
with ``UnsafeCheckpointError`` before it is called.

Both container formats are read:
  * zip (PyTorch ≥ 1.6): ``<root>/data.pkl`` plus one raw little-endian storage per ``<root>/data/<key>``.
  * legacy (older files such as torchvision's ``vgg16-397923af.pth``): consecutive pickles (magic number,
    protocol, system info, the object, the storage keys) followed by each storage as an int64 element count
    and raw bytes.
"""

from __future__ import annotations

import io
import os
import pickle
import struct
import zipfile
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, BinaryIO

import ml_dtypes
import numpy as np

__all__ = ["TorchCheckpointError", "UnsafeCheckpointError", "read_torch_checkpoint"]

# torch/serialization.py: MAGIC_NUMBER and PROTOCOL_VERSION of the legacy format.
_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
_LEGACY_PROTOCOL = 1001

_STORAGE_DTYPES: dict[str, np.dtype] = {
    "FloatStorage": np.dtype("<f4"),
    "DoubleStorage": np.dtype("<f8"),
    "HalfStorage": np.dtype("<f2"),
    "BFloat16Storage": np.dtype(ml_dtypes.bfloat16),
    "LongStorage": np.dtype("<i8"),
    "IntStorage": np.dtype("<i4"),
    "ShortStorage": np.dtype("<i2"),
    "CharStorage": np.dtype("i1"),
    "ByteStorage": np.dtype("u1"),
    "BoolStorage": np.dtype("?"),
}


class TorchCheckpointError(ValueError):
    """The file is not a readable ``torch.save`` checkpoint (truncated, corrupt or unsupported)."""


class UnsafeCheckpointError(TorchCheckpointError):
    """The checkpoint's pickle asks for a global outside the allow-list; nothing it names was called."""


@dataclass(frozen=True)
class _StorageType:
    """Stand-in for ``torch.FloatStorage`` & co.: only its element dtype matters."""

    dtype: np.dtype


@dataclass(frozen=True)
class _TensorRef:
    """A tensor whose storage bytes may not have been read yet (legacy files store them after the pickle)."""

    storage_key: str
    offset: int
    shape: tuple[int, ...]
    stride: tuple[int, ...]


def _rebuild_tensor_v2(storage, storage_offset, size, stride, requires_grad=False, backward_hooks=None, *_):
    del requires_grad, backward_hooks  # autograd state has no meaning for arrays
    if not isinstance(storage, str):
        raise TorchCheckpointError(
            f"tensor rebuilt from a non-storage object of type {type(storage).__name__}"
        )
    return _TensorRef(
        storage, int(storage_offset), tuple(int(s) for s in size), tuple(int(s) for s in stride)
    )


def _rebuild_parameter(data, requires_grad=False, backward_hooks=None, *_):
    del requires_grad, backward_hooks
    return data


def _ordered_dict(*args):
    return OrderedDict(*args)


_ALLOWED: dict[tuple[str, str], Callable[..., Any] | _StorageType] = {
    ("collections", "OrderedDict"): _ordered_dict,
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor_v2,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    **{("torch", name): _StorageType(dtype) for name, dtype in _STORAGE_DTYPES.items()},
}


class _SafeUnpickler(pickle.Unpickler):
    """Resolves only allow-listed globals; storages become keys into a table filled by the caller."""

    def __init__(self, file: BinaryIO, source: str, storages: dict[str, tuple[np.dtype, int]]):
        super().__init__(file)
        self._source = source
        self._storages = storages  # key -> (dtype, element count) as announced by the pickle

    def find_class(self, module: str, name: str) -> Any:
        try:
            return _ALLOWED[(module, name)]
        except KeyError:
            raise UnsafeCheckpointError(
                f"{self._source}: refusing to load global '{module}.{name}': a weights file needs only "
                "tensors "
                "and dicts, and this name could run code. The file is not a plain state dict, or it is "
                "malicious; nothing was executed."
            ) from None

    def persistent_load(self, pid: Any) -> str:
        # zip: ('storage', type, key, location, numel); legacy: (..., numel, view_metadata).
        if not (isinstance(pid, tuple) and len(pid) in (5, 6) and pid[0] in ("storage", b"storage")):
            raise UnsafeCheckpointError(f"{self._source}: unsupported persistent id {pid!r:.80}")
        storage_type, key, numel = pid[1], str(pid[2]), int(pid[4])
        if not isinstance(storage_type, _StorageType):
            raise TorchCheckpointError(f"{self._source}: storage {key} has unknown type {storage_type!r:.60}")
        if len(pid) == 6 and pid[5] is not None:
            raise TorchCheckpointError(
                f"{self._source}: legacy storage views are not supported (storage {key})"
            )
        self._storages[key] = (storage_type.dtype, numel)
        return key


def _materialise(obj: Any, storages: Mapping[str, np.ndarray], source: str) -> Any:
    """Replaces every ``_TensorRef`` (in dicts, lists, tuples) by a NumPy array copied out of its storage."""
    if isinstance(obj, _TensorRef):
        flat = storages[obj.storage_key]
        extent = obj.offset + sum((n - 1) * s for n, s in zip(obj.shape, obj.stride, strict=True) if n > 0)
        if obj.offset < 0 or any(s < 0 for s in obj.stride) or (0 not in obj.shape and extent >= flat.size):
            raise TorchCheckpointError(
                f"{source}: tensor of shape {obj.shape} (offset {obj.offset}, stride {obj.stride}) "
                "overruns its "
                f"storage {obj.storage_key} of {flat.size} elements: the file is corrupt"
            )
        if 0 in obj.shape:
            return np.zeros(obj.shape, flat.dtype)
        view = np.lib.stride_tricks.as_strided(
            flat[obj.offset :],
            shape=obj.shape,
            strides=tuple(s * flat.itemsize for s in obj.stride),
            writeable=False,
        )
        return np.array(view, order="C")  # an owned C-contiguous copy, whatever the strides
    if isinstance(obj, dict):
        out = type(obj)() if isinstance(obj, OrderedDict) else {}
        for k, v in obj.items():
            out[k] = _materialise(v, storages, source)
        return out
    if isinstance(obj, (list, tuple)):
        return type(obj)(_materialise(v, storages, source) for v in obj)
    return obj


def _read_zip(path: str) -> Any:
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as err:
        raise TorchCheckpointError(
            f"{path}: not a readable torch.save zip archive ({err}); truncated?"
        ) from err
    with archive:
        pickles = [n for n in archive.namelist() if n.endswith("/data.pkl") or n == "data.pkl"]
        if len(pickles) != 1:
            raise TorchCheckpointError(f"{path}: expected one data.pkl in the zip archive, found {pickles}")
        root = pickles[0][: -len("data.pkl")]
        byteorder = "little"
        if f"{root}byteorder" in archive.namelist():
            byteorder = archive.read(f"{root}byteorder").decode().strip()
        announced: dict[str, tuple[np.dtype, int]] = {}
        try:
            obj = _SafeUnpickler(io.BytesIO(archive.read(pickles[0])), path, announced).load()
            storages = {}
            for key, (dtype, numel) in announced.items():
                raw = archive.read(f"{root}data/{key}")
                storages[key] = _from_bytes(
                    raw, dtype.newbyteorder("<" if byteorder == "little" else ">"), numel, path, key
                )
        except (zipfile.BadZipFile, KeyError, EOFError, OSError) as err:
            raise TorchCheckpointError(f"{path}: damaged zip archive ({err}); truncated download?") from err
        except pickle.UnpicklingError as err:
            raise TorchCheckpointError(f"{path}: corrupt pickle in {pickles[0]} ({err})") from err
    return _materialise(obj, storages, path)


def _from_bytes(raw: bytes, dtype: np.dtype, numel: int, source: str, key: str) -> np.ndarray:
    if len(raw) < numel * dtype.itemsize:
        raise TorchCheckpointError(
            f"{source}: storage {key} holds {len(raw)} bytes, expected {numel} × {dtype.itemsize}: "
            "truncated file"
        )
    return np.frombuffer(raw, dtype=dtype, count=numel)


def _read_legacy(path: str) -> Any:
    with open(path, "rb") as f:
        try:
            header = [_SafeUnpickler(f, path, {}).load() for _ in range(3)]
            if header[0] != _LEGACY_MAGIC or header[1] != _LEGACY_PROTOCOL:
                raise TorchCheckpointError(
                    f"{path}: neither a zip archive nor a legacy torch.save file (bad magic number)"
                )
            announced: dict[str, tuple[np.dtype, int]] = {}
            obj = _SafeUnpickler(f, path, announced).load()
            keys = _SafeUnpickler(f, path, {}).load()
        except UnsafeCheckpointError:
            raise
        except (pickle.UnpicklingError, EOFError, ValueError, IndexError, TypeError) as err:
            if isinstance(err, TorchCheckpointError):
                raise
            raise TorchCheckpointError(f"{path}: not a readable torch.save file ({err}); truncated?") from err
        if not isinstance(keys, list) or set(map(str, keys)) != set(announced):
            raise TorchCheckpointError(
                f"{path}: the storage key list does not match the tensors; corrupt file"
            )
        storages = {}
        for key in map(str, keys):
            dtype, numel = announced[key]
            count_bytes = f.read(8)
            if len(count_bytes) != 8:
                raise TorchCheckpointError(f"{path}: file ends before storage {key}: truncated file")
            (count,) = struct.unpack("<q", count_bytes)
            if count != numel:
                raise TorchCheckpointError(f"{path}: storage {key} has {count} elements, pickle said {numel}")
            storages[key] = _from_bytes(f.read(numel * dtype.itemsize), dtype, numel, path, key)
    return _materialise(obj, storages, path)


def _flatten_state_dict(obj: Any, path: str, prefix: str = "") -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for k, v in obj.items():
        key = f"{prefix}{k}"
        if isinstance(v, np.ndarray):
            out[key] = v
        elif isinstance(v, dict):
            out.update(_flatten_state_dict(v, path, f"{key}."))
        else:
            raise TorchCheckpointError(
                f"{path}: entry {key!r} is a {type(v).__name__}, not a tensor; expected a state dict"
            )
    return out


def read_torch_checkpoint(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Reads the state dict of a ``torch.save`` file as NumPy arrays, safely and without torch.

    Args:
        path: a ``.pt``/``.pth`` file written by ``torch.save`` (zip or legacy format) holding a state
            dict, or a dict that keeps it under ``"model"`` or ``"state_dict"`` (e.g. next to an
            ``"optimizer"`` entry). Nested dicts of tensors are flattened with ``.``-joined keys.

    Returns:
        ``{key: array}`` in the file's order with the tensors' dtypes (bfloat16 via ``ml_dtypes``),
        C-contiguous copies in native byte order.

    Raises:
        UnsafeCheckpointError: the pickle references anything beyond tensors and dicts (nothing is executed).
        TorchCheckpointError: truncated, corrupt or unsupported file, or entries that are not tensors.
        FileNotFoundError: no such file.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no checkpoint file at {path}")
    obj = _read_zip(path) if zipfile.is_zipfile(path) else _read_legacy(path)
    if isinstance(obj, dict):
        for wrapper in ("model", "state_dict"):
            if isinstance(obj.get(wrapper), dict):
                obj = obj[wrapper]
                break
    if not isinstance(obj, dict):
        raise TorchCheckpointError(f"{path}: holds a {type(obj).__name__}, expected a state dict")
    return _flatten_state_dict(obj, path)
