"""The one lifecycle of the networks placejax trains itself (the depth network, the pretrained VGG16 trunks).

Train once into the cache (:func:`run_dir`, announced by :func:`announce_training`), record the result as a
weights record (an ``.npz`` of flat ``"a/b/leaf"`` arrays plus a JSON ``meta``: config, fingerprint, command,
quick check; written by ``placejax.io.write_npz``), verify it (the tests recompute the recorded quick check, and a
shipped record whose fingerprint is not the preset's is not used), and load it (:func:`read_record`,
:func:`load_shipped`). Records of the default presets ship inside the package, under ``placejax/depth/weights/``
and ``placejax/pretrain/weights/``, because a fresh machine cannot afford to train them.
"""

import importlib.resources
import io as _io
import os
import sys
from pathlib import Path
from typing import IO, Any, NamedTuple

import numpy as np
from flax import traverse_util

from placejax import io

__all__ = [
    "SHIPPED_PACKAGES",
    "WeightsRecord",
    "announce_training",
    "load_shipped",
    "read_record",
    "run_dir",
    "shipped_file",
    "shipped_names",
]

# Packages whose ``weights/`` folder holds shipped records; a record's file name (without ``.npz``) is its name.
SHIPPED_PACKAGES = ("placejax.depth", "placejax.pretrain")
"""Packages whose ``weights/`` folder holds shipped records; a record's file name (without ``.npz``) is its name."""


class WeightsRecord(NamedTuple):
    """Network variables and their record: what :func:`resolve`, :func:`read_record`, :func:`load_shipped`,
    ``placejax.depth.load_shipped`` and ``placejax.pretrain.load_shipped`` return.

    A tuple, so ``variables, meta = record`` works.

    Attributes:
        variables: nested dict of NumPy arrays (float32 for floating-point leaves), e.g.
            ``{"params": ..., "batch_stats": ...}`` of a ``MidasSmall`` or ``{"trunk": ...}`` of a VGG16 trunk.
        meta: the record: for placejax-trained networks the config, its fingerprint, the command and the quick
            check; for registry weights ``{"registry": NAME, ...}``; for a converted torch file its SHA-256.
    """

    variables: dict[str, Any]
    meta: dict[str, Any]


def read_record(source: str | os.PathLike | IO[bytes], *, what: str = "placejax weights record") -> WeightsRecord:
    """Reads an ``.npz`` weights record (a path or a binary file object) written with ``placejax.io.write_npz(...,
    meta=...)``: flat ``"a/b/leaf"`` keys become a nested tree, floating-point arrays float32 (shipped depth
    networks store their parameters in float16).

    Raises:
        ValueError: the file has no ``meta`` entry (not a weights record); the message names the source.
    """
    flat, meta = io.read_npz(source)
    if meta is None:
        raise ValueError(f"{source}: not a {what} (no 'meta' entry)")
    arrays = {k: v.astype(np.float32) if np.issubdtype(v.dtype, np.floating) else v for k, v in flat.items()}
    return WeightsRecord(traverse_util.unflatten_dict(arrays, sep="/"), meta)


def shipped_names() -> dict[str, str]:
    """``{name: package}`` of every record shipped with placejax (``<package>/weights/<name>.npz``)."""
    out = {}
    for package in SHIPPED_PACKAGES:
        folder = importlib.resources.files(package) / "weights"
        if folder.is_dir():
            out.update({f.name[: -len(".npz")]: package for f in folder.iterdir() if f.name.endswith(".npz")})
    return out


def shipped_file(name: str):
    """The packaged file of the shipped record ``name`` (an ``importlib.resources`` traversable).

    Raises:
        FileNotFoundError: no shipped record of that name (the message lists those there are).
    """
    names = shipped_names()
    if name not in names:
        raise FileNotFoundError(f"no shipped weights {name!r}; placejax ships {sorted(names)}")
    return importlib.resources.files(names[name]) / "weights" / f"{name}.npz"


def load_shipped(name: str) -> WeightsRecord:
    """The record ``name`` shipped with placejax (e.g. ``"simcampus_depth_default_128"`` or
    ``"simcampus_places_w0125_s64"``), read with :func:`read_record`."""
    with shipped_file(name).open("rb") as f:
        return read_record(_io.BytesIO(f.read()), what=f"shipped weights record {name!r}")


def run_dir(kind: str, preset: str, fingerprint: str, root: str | os.PathLike | None = None) -> Path:
    """The cache folder of a training run: ``<root>/<kind>/<preset>-<fingerprint>``.

    Args:
        kind: what is trained (``"depth"``, ``"pretrain"``).
        preset: the preset's name.
        fingerprint: the hash of everything in the config that changes the weights.
        root: cache root; default ``placejax.weights.cache_dir()`` (``$PLACEJAX_CACHE`` or ``~/.cache/placejax``).
    """
    from placejax.weights._registry import cache_dir

    return (cache_dir() if root is None else Path(root)) / kind / f"{preset}-{fingerprint}"


def announce_training(what: str, preset: str, detail: str, minutes: float | None, workdir: Path) -> None:
    """Tells the user on stderr that ``what`` (e.g. ``"the depth network"``) is about to be trained, how long the
    preset takes (``minutes`` on 2 CPU cores, when measured) and where it is cached."""
    took = f"about {minutes} min on 2 CPU cores" if minutes else "its length depends on the preset"
    print(
        f"placejax: training {what} '{preset}' ({detail}, {took}); cached in {workdir} (interrupt and rerun to resume)",
        file=sys.stderr,
    )
