"""The restricted pickle machine's view of a ``torch.save`` file: the limits, the error types, and the immutable
stand-ins and hooks that the few globals a checkpoint may name are resolved to (``_torch_checkpoint`` reads the
containers and builds the arrays; the promises are in its docstring)."""

from __future__ import annotations

import re
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import ml_dtypes
import numpy as np

from placejax.weights._restricted_pickle import MAX_INT_KEY, PickleLimits, PickleRejected, describe

DEFAULT_MAX_BYTES = 4 << 30
"""Default bound on the tensor data ``read_torch_checkpoint`` holds at once (storages read + arrays returned).

About twice a checkpoint's tensor bytes are needed when its tensors are views that must be copied; tensors
that are exactly their storage (the usual case) are returned without a copy."""

# torch/serialization.py: MAGIC_NUMBER and PROTOCOL_VERSION of the legacy format.
_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
_LEGACY_PROTOCOL = 1001
# torch/serialization.py, _is_zipfile: torch decides "zip" from these first bytes only.
_ZIP_SIGNATURE = b"PK\x03\x04"

_PICKLE_LIMITS = PickleLimits()
_MAX_NDIM = 64
_MAX_ELEMENTS = 1 << 62
_MAX_DEPTH = 64
_MAX_ENTRIES = 1 << 20
_MAX_KEY_CHARS = 64 << 20
_COPY_FACTOR = 2  # returned bytes ≤ _COPY_FACTOR × storage bytes read
# torch.save never compresses records; re-zipped float weights shrink by ~1.1×. A deflate bomb reaches ~1000×.
_MAX_RATIO = 64
_MAX_RATIO_FREE = 1 << 20  # small records (a few zero buffers) may compress better than _MAX_RATIO
_CHUNK = 16 << 20  # read granularity: bounds the temporary buffer of each read
_STORAGE_KEY = re.compile(r"[0-9A-Za-z_]{1,64}")

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
    """The file is not a readable ``torch.save`` checkpoint (truncated, corrupt, too large or unsupported)."""


class UnsafeCheckpointError(TorchCheckpointError):
    """The file asks for something that could run code or change objects outside it; nothing was called."""


# --- stand-ins: immutable (frozen, slotted), and only ever handed to the restricted pickle machine ---------


@dataclass(frozen=True, slots=True)
class _StorageType:
    """Stand-in for ``torch.FloatStorage`` & co.: only its element dtype matters."""

    name: str
    dtype: np.dtype


@dataclass(frozen=True, slots=True)
class _Function:
    """Stand-in for an allowed callable; what a call does is decided by ``_Hooks.call`` from the name."""

    name: str


@dataclass(frozen=True, slots=True)
class _Unsupported:
    """A global torch writes for tensors this reader does not convert; an error as soon as it is used."""

    qualname: str
    kind: str


@dataclass(frozen=True, slots=True)
class _StorageRef:
    key: str
    dtype: np.dtype
    numel: int


@dataclass(frozen=True, slots=True)
class _TensorRef:
    """A tensor whose storage bytes have not been read yet (legacy files store them after the pickle)."""

    storage: _StorageRef
    offset: int
    shape: tuple[int, ...]
    stride: tuple[int, ...]


_ORDERED_DICT = _Function("collections.OrderedDict")
_REBUILD_TENSOR = _Function("torch._utils._rebuild_tensor_v2")
_REBUILD_PARAMETER = _Function("torch._utils._rebuild_parameter")

_ALLOWED: dict[tuple[str, str], _Function | _StorageType] = {
    ("collections", "OrderedDict"): _ORDERED_DICT,
    ("torch._utils", "_rebuild_tensor_v2"): _REBUILD_TENSOR,
    ("torch._utils", "_rebuild_parameter"): _REBUILD_PARAMETER,
    **{("torch", name): _StorageType(name, dtype) for name, dtype in _STORAGE_DTYPES.items()},
}

# Globals that torch.save writes for tensor kinds this reader does not convert (torch/_utils.py,
# torch/_tensor.py, torch/serialization.py, the torch.* dtype/layout/qscheme objects of torch 2.13).
_UNSUPPORTED_REBUILDERS = {
    "_rebuild_tensor": "old-style tensor",
    "_rebuild_tensor_v3": "tensor of a newer dtype (uint16/32/64, float8, ...)",
    "_rebuild_qtensor": "quantized tensor",
    "_rebuild_sparse_tensor": "sparse tensor",
    "_rebuild_nested_tensor": "nested tensor",
    "_rebuild_wrapper_subclass": "tensor subclass",
    "_rebuild_from_type_v2": "tensor subclass or tensor with Python attributes",
    "_rebuild_parameter_with_state": "parameter with Python attributes",
    "_rebuild_device_tensor_from_numpy": "device tensor",
    "_rebuild_device_tensor_from_cpu_tensor": "device tensor",
    "_rebuild_meta_tensor_no_storage": "meta tensor",
    "_rebuild_xla_tensor": "XLA tensor",
}
_TORCH_LAYOUTS = {"sparse_coo", "sparse_csr", "sparse_csc", "sparse_bsr", "sparse_bsc", "_mkldnn", "jagged"}
_TORCH_QSCHEMES = {
    "per_tensor_affine",
    "per_channel_affine",
    "per_tensor_symmetric",
    "per_channel_symmetric",
    "per_channel_affine_float_qparams",
}
_TORCH_DTYPE = re.compile(
    r"(u?int[1-7]|uint(16|32|64)|bits\w*|float8_\w+|float4_\w+|complex(32|64|128)|c(float|double|half)"
    r"|q(u?int(8|32)|uint(2x4|4x2)))"
)


def _unsupported_kind(module: str, name: str) -> str | None:
    if module in ("torch._utils", "torch._tensor") and name in _UNSUPPORTED_REBUILDERS:
        return _UNSUPPORTED_REBUILDERS[name]
    if (module, name) == ("torch.serialization", "_get_layout") or (module == "torch" and name in _TORCH_LAYOUTS):
        return "sparse or non-strided tensor"
    if module == "torch" and name in _TORCH_QSCHEMES:
        return "quantized tensor"
    if module == "torch" and name.endswith("Storage") and name.isidentifier():
        if name.startswith("Complex"):
            return "complex tensor"
        if name.startswith("Q"):
            return "quantized tensor"
        return "tensor with an untyped storage (newer dtypes such as uint16 or float8)"
    if module == "torch.storage" and name in ("UntypedStorage", "TypedStorage"):
        return "tensor with an untyped storage (newer dtypes such as uint16 or float8)"
    if module == "torch" and _TORCH_DTYPE.fullmatch(name):
        return f"tensor of dtype torch.{name}"
    if module == "torch" and name == "Size":
        return "sparse or non-strided tensor"
    return None


def _short(text: str, limit: int = 80) -> str:
    return text if len(text) <= limit else text[:limit] + "…"


def _int_in(value: Any, low: int, high: int) -> bool:
    return type(value) is int and low <= value <= high


class _Hooks:
    """Decides, for the restricted pickle machine, what each global, persistent id, call and BUILD may do."""

    def __init__(self, storages: dict[str, _StorageRef] | None):
        self.storages = storages  # None: this pickle may not reference storages (legacy headers, key list)

    def find_class(self, module: str, name: str) -> Any:
        allowed = _ALLOWED.get((module, name))
        if allowed is not None:
            return allowed
        kind = _unsupported_kind(module, name)
        if kind is not None:
            return _Unsupported(f"{module}.{name}", kind)
        raise PickleRejected(
            f"refusing to load global '{_short(module)}.{_short(name)}': a weights file needs only tensors "
            "and dicts, and this name could run code. The file is not a plain state dict, or it is malicious; "
            "nothing was executed",
            unsafe=True,
        )

    def persistent_load(self, pid: Any) -> _StorageRef | _Unsupported:
        # zip: ('storage', type, key, location, numel); legacy: the same plus view_metadata.
        if self.storages is None or type(pid) is not tuple or len(pid) not in (5, 6):
            raise PickleRejected(f"unsupported persistent id ({describe(pid)})")
        if pid[0] not in ("storage", b"storage"):
            raise PickleRejected(f"unsupported persistent id of type {describe(pid[0])}")
        storage_type, key, numel = pid[1], pid[2], pid[4]
        if isinstance(storage_type, _Unsupported):
            # Not an error yet: the rebuild call it goes into may name the exact dtype (_rebuild_tensor_v3).
            return storage_type
        if not isinstance(storage_type, _StorageType):
            raise PickleRejected(f"storage of unknown type ({describe(storage_type)})")
        if type(key) is not str or not _STORAGE_KEY.fullmatch(key):
            raise PickleRejected(f"storage key {describe(key)} is not a short alphanumeric name")
        if not _int_in(numel, 0, _MAX_ELEMENTS):
            raise PickleRejected(f"storage {key} has an invalid element count ({describe(numel)})")
        if len(pid) == 6 and pid[5] is not None:
            raise PickleRejected(f"legacy storage views are not supported (storage {key})")
        ref = _StorageRef(key, storage_type.dtype, numel)
        known = self.storages.setdefault(key, ref)
        if known != ref:
            raise PickleRejected(
                f"storage {key} is announced twice with different types or sizes "
                f"({known.dtype}×{known.numel}, then {ref.dtype}×{ref.numel})"
            )
        return known

    def call(self, func: Any, args: tuple) -> Any:
        markers = [a for a in (func, *args) if isinstance(a, _Unsupported)]
        if markers:
            # The most specific marker first: a dtype (torch.uint16) says more than an UntypedStorage.
            raise _unsupported_error(min(markers, key=lambda m: not m.kind.startswith("tensor of dtype")))
        if func is _ORDERED_DICT:
            return _ordered_dict(args)
        if func is _REBUILD_TENSOR:
            return _rebuild_tensor_v2(args)
        if func is _REBUILD_PARAMETER:
            if not 1 <= len(args) <= 4 or not isinstance(args[0], _TensorRef):
                raise PickleRejected(f"_rebuild_parameter called with {describe(args)} instead of a tensor")
            return args[0]
        raise PickleRejected(
            f"refusing to call {describe(func)}: only tensor and dict rebuilders are called", unsafe=True
        )

    def build(self, target: Any, state: Any) -> None:
        # torch pickles a state dict as OrderedDict plus BUILD with {'_metadata': ...} (module versions); that
        # metadata has no meaning for arrays and is dropped. BUILD on anything else would set attributes.
        if type(target) is OrderedDict and (state is None or type(state) is dict):
            return
        raise PickleRejected(
            f"refusing BUILD on {describe(target)}: it would set the state of an object outside plain data",
            unsafe=True,
        )


def _unsupported_error(marker: _Unsupported) -> PickleRejected:
    return PickleRejected(
        f"holds a {marker.kind} (torch's '{marker.qualname}'), which this reader does not convert; the file "
        "looks like an ordinary torch.save checkpoint (nothing unsafe was found up to here). Convert such "
        "tensors to a plain dtype before saving, or load the file with torch"
    )


def _ordered_dict(args: tuple) -> OrderedDict:
    if args == ():
        return OrderedDict()
    if len(args) == 1 and type(args[0]) is list:
        out: OrderedDict = OrderedDict()
        for pair in args[0]:
            if type(pair) not in (tuple, list) or len(pair) != 2 or not isinstance(pair[0], (str, int)):
                raise PickleRejected(f"OrderedDict built from {describe(pair)} instead of a (key, value) pair")
            if isinstance(pair[0], int) and not -MAX_INT_KEY <= pair[0] <= MAX_INT_KEY:
                # the rule of the pickle machine's own dicts: such ints can be made to collide (quadratic insertion)
                raise PickleRejected(f"OrderedDict key {describe(pair[0])} is an integer outside ±2**60")
            out[pair[0]] = pair[1]
        return out
    raise PickleRejected(f"OrderedDict called with {describe(args)}")


def _int_tuple(value: Any, what: str) -> tuple[int, ...]:
    if type(value) not in (tuple, list) or len(value) > _MAX_NDIM:
        raise PickleRejected(f"tensor {what} is {describe(value)}, not a tuple of at most {_MAX_NDIM} integers")
    for v in value:
        if not _int_in(v, 0, _MAX_ELEMENTS):
            shown = ", ".join(describe(x, 20) for x in value[:8]) + (", …" if len(value) > 8 else "")
            raise PickleRejected(
                f"tensor {what} ({shown}{',' if len(value) == 1 else ''}) holds {describe(v)}, "
                "not an element count in [0, 2**62]"
            )
    return tuple(value)


def _rebuild_tensor_v2(args: tuple) -> _TensorRef:
    # torch/_utils.py: _rebuild_tensor_v2(storage, storage_offset, size, stride, requires_grad,
    # backward_hooks, metadata=None). Autograd state and (empty) hooks have no meaning for arrays.
    if not 4 <= len(args) <= 7:
        raise PickleRejected(f"_rebuild_tensor_v2 called with {len(args)} arguments")
    storage, offset = args[0], args[1]
    if not isinstance(storage, _StorageRef):
        raise PickleRejected(f"tensor rebuilt from {describe(storage)} instead of a storage")
    if not _int_in(offset, 0, _MAX_ELEMENTS):
        raise PickleRejected(f"tensor has an invalid storage offset ({describe(offset)})")
    shape, stride = _int_tuple(args[2], "size"), _int_tuple(args[3], "stride")
    if len(shape) != len(stride):
        raise PickleRejected(f"tensor size {shape} and stride {stride} differ in length")
    if len(args) == 7 and args[6] not in (None, {}):
        raise PickleRejected(f"tensor carries metadata ({describe(args[6])}), which this reader does not support")
    return _TensorRef(storage, offset, shape, stride)
