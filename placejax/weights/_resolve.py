"""One way to name weights: ``registry:NAME``, ``shipped:NAME`` or a path, for every network placejax loads.

- ``registry:NAME``: official weights of ``placejax.weights.REGISTRY`` (downloaded once, converted, cached).
- ``shipped:NAME``: a record shipped inside the package (the depth network, the pretrained VGG16 trunks).
- a path ending in ``.npz``: a placejax weights record (``placejax.io.write_npz(..., meta=...)``, e.g. written by
  ``placejax.depth.save_shipped`` or ``placejax.pretrain.save_trunk``).
- any other path: a ``torch.save`` file, read by the safe reader and converted by the caller's ``convert``.
"""

from __future__ import annotations

import functools
import hashlib
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from placejax import io
from placejax.weights._registry import REGISTRY, load
from placejax.weights._shipped import WeightsRecord, read_record, shipped_file
from placejax.weights._shipped import load_shipped as _load_shipped
from placejax.weights._torch_checkpoint import read_torch_checkpoint

__all__ = ["REGISTRY_PREFIX", "SHIPPED_PREFIX", "identity", "resolve"]

REGISTRY_PREFIX = "registry:"
"""The prefix of a registry weights spec, ``"registry:"``."""
SHIPPED_PREFIX = "shipped:"
"""The prefix of a shipped weights spec, ``"shipped:"``."""


def _spec(spec: str | os.PathLike, default: str | None) -> str:
    spec = os.fspath(spec)
    if not isinstance(spec, str):
        raise TypeError(f"a weights spec is a str or a path, got {type(spec).__name__}")
    if spec:
        return spec
    if default is None:
        raise ValueError("empty weights spec: name 'registry:NAME', 'shipped:NAME' or a file path")
    return default


def _registry_name(spec: str) -> str:
    name = spec[len(REGISTRY_PREFIX) :]
    if name not in REGISTRY:
        raise KeyError(f"weights spec {spec!r}: unknown registry name {name!r}; registered: {sorted(REGISTRY)}")
    return name


def resolve(
    spec: str | os.PathLike,
    *,
    convert: Callable[[Mapping[str, np.ndarray]], dict[str, Any]] | None = None,
    default: str | None = None,
) -> WeightsRecord:
    """The variables (and record) that a weights spec names.

    Args:
        spec: ``"registry:NAME"`` (``placejax.weights.load(NAME)``), ``"shipped:NAME"``
            (``placejax.weights.load_shipped(NAME)``), the path of an ``.npz`` weights record, or the path of a
            ``torch.save`` file (converted by ``convert``).
        convert: state dict → Flax variables, for ``torch.save`` files, e.g.
            ``functools.partial(placejax.weights.convert_midas_small, model=MidasSmall())``.
        default: the spec an empty ``spec`` stands for (e.g. ``"registry:vgg16_imagenet"``); without it an empty
            spec is an error.

    Returns:
        A :class:`WeightsRecord` ``(variables, meta)``: NumPy float32 trees (``{"params": ..., ...}`` for
        registry and converted weights, the tree stored in a record otherwise); ``meta`` is the record's, or
        ``{"registry": NAME}`` / ``{"sha256": ...}`` for registry and torch files.

    Raises:
        KeyError: an unknown registry name.
        FileNotFoundError: an unknown shipped name, or no file at the path.
        ValueError: an empty spec without a default, an ``.npz`` that is not a weights record, or a
            ``torch.save`` file without ``convert``.

    Example::

        variables, meta = placejax.weights.resolve("shipped:simcampus_depth_default_128")
        model = placejax.depth.TrainedDepth.from_record((variables, meta)).model  # a log-metric network
        log_depth = placejax.depth.apply(variables, rgb_uint8, model=model, size=128, square=True)
        depth_m = placejax.depth.depth_from_log(log_depth)
    """
    spec = _spec(spec, default)
    if spec.startswith(REGISTRY_PREFIX):
        name = _registry_name(spec)
        return WeightsRecord(load(name), {"registry": name})
    if spec.startswith(SHIPPED_PREFIX):
        return _load_shipped(spec[len(SHIPPED_PREFIX) :])
    path = Path(spec).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"weights file {spec!r} not found")
    if path.suffix == ".npz":
        return read_record(path)
    if convert is None:
        raise ValueError(f"{spec}: a torch.save file needs a converter (resolve(spec, convert=...))")
    return WeightsRecord(convert(read_torch_checkpoint(path)), {"sha256": io.file_sha256(path)})


@functools.lru_cache(maxsize=8)
def _file_sha256(path: str, size: int, mtime_ns: int) -> str:
    del size, mtime_ns  # part of the cache key only: a replaced file is hashed again
    return io.file_sha256(path)


def identity(spec: str | os.PathLike, *, default: str | None = None) -> dict[str, str]:
    """What identifies the weights a spec names, for cache keys: ``{"registry": NAME}``, ``{"shipped": spec,
    "sha256": ...}`` of the packaged file, or ``{"sha256": ...}`` of a file (not its path: a moved file is the same
    weights, a replaced one is not; hashes are remembered per path, size and modification time).

    Args:
        spec: as :func:`resolve`.
        default: as :func:`resolve`.

    Raises:
        KeyError / FileNotFoundError / ValueError: as :func:`resolve`.
    """
    spec = _spec(spec, default)
    if spec.startswith(REGISTRY_PREFIX):
        return {"registry": _registry_name(spec)}
    if spec.startswith(SHIPPED_PREFIX):
        res = shipped_file(spec[len(SHIPPED_PREFIX) :])
        return {"shipped": spec, "sha256": hashlib.sha256(res.read_bytes()).hexdigest()}
    p = Path(spec).expanduser()
    if not p.is_file():
        raise FileNotFoundError(f"weights file {spec!r} not found")
    st = p.stat()
    return {"sha256": _file_sha256(str(p.resolve()), st.st_size, st.st_mtime_ns)}
