"""The one lifecycle of the networks placejax trains itself (the depth network, the pretrained VGG16 trunks).

Train once into the cache (:func:`run_dir`, announced by :func:`announce_training`), record the result as a
weights record (an ``.npz`` of flat ``"a/b/leaf"`` arrays plus a JSON ``meta``: config, fingerprint, command,
quick check; written by ``placejax.io.write_npz``), verify it (the tests recompute the recorded quick check, and a
shipped record whose fingerprint is not the preset's is not used), and load it (:func:`read_record`,
:func:`load_shipped`). Records of the default presets ship inside the package, under ``placejax/depth/weights/``
and ``placejax/pretrain/weights/``, because a fresh machine cannot afford to train them; each file's SHA-256 is
recorded here (:data:`SHIPPED_SHA256`) and checked before the file is used. Trainings into one cache folder are
serialised (:func:`training_lock`): a second caller waits, then loads what the first trained.
"""

import contextlib
import hashlib
import importlib.resources
import io as _io
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any, NamedTuple

import numpy as np
from flax import traverse_util

from placejax import io

__all__ = [
    "SHIPPED_PACKAGES",
    "SHIPPED_SHA256",
    "ShippedWeightsError",
    "WeightsRecord",
    "announce_training",
    "load_shipped",
    "read_record",
    "run_dir",
    "shipped_file",
    "shipped_names",
    "training_lock",
]

# Packages whose ``weights/`` folder holds shipped records; a record's file name (without ``.npz``) is its name.
SHIPPED_PACKAGES = ("placejax.depth", "placejax.pretrain")
"""Packages whose ``weights/`` folder holds shipped records; a record's file name (without ``.npz``) is its name."""

# A file shipped in a weights/ folder is used only when its bytes have the digest recorded here; one shipped anew
# (``--export`` of experiments.train_depth / experiments.pretrain_trunk) needs its line here.
SHIPPED_SHA256 = {
    "simcampus_depth_default_128": "6ab86dd06a551f07a67d3c8a8ce7f37726e6e696464e0d1adaf66a07c5c8fa25",
    "simcampus_places_hha_predicted_w0125_s64": "563c51f021b710bd5e38b46fd0869d2e7058763a6f82d1c1eb176efd6b206afa",
    "simcampus_places_hha_w0125_s64": "c6cd093d788ed46b5d4a967ddc2933e3951246046c2765d70c2e48ebc24a85db",
    "simcampus_places_w0125_s64": "e1e4770fd6eaf5b9397ea389721561e7d9c0e66bc6ec33407408e1464f79874c",
}
"""Name → SHA-256 (hex) of each weights record shipped with placejax, checked by :func:`load_shipped` before use."""


class ShippedWeightsError(ValueError):
    """A shipped weights file whose bytes are not the ones placejax shipped (damaged or replaced), or one without a
    recorded digest; the message names the file and how to restore it."""


class WeightsRecord(NamedTuple):
    """Network variables and their record: what :func:`resolve`, :func:`read_record`, :func:`load_shipped`,
    ``placejax.weights.resolve("shipped:NAME")`` returns.

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
    ``"simcampus_places_w0125_s64"``), read with :func:`read_record` once its SHA-256 is the one recorded in
    :data:`SHIPPED_SHA256`.

    Raises:
        FileNotFoundError: no shipped record of that name.
        ShippedWeightsError: the file's bytes are not those placejax shipped, or no digest is recorded for it.
    """
    path = shipped_file(name)
    data = path.read_bytes()
    want = SHIPPED_SHA256.get(name)
    got = hashlib.sha256(data).hexdigest()
    if want is None:
        raise ShippedWeightsError(
            f"{path}: no SHA-256 recorded for shipped weights {name!r}; record {got} in "
            "placejax.weights._shipped.SHIPPED_SHA256 if this file is the one to ship"
        )
    if got != want:
        raise ShippedWeightsError(
            f"{path}: SHA-256 {got[:16]}… is not the {want[:16]}… placejax shipped (the file is damaged or was "
            "replaced); restore it: reinstall placejax (pip install --force-reinstall placejax), or in a source "
            f"checkout git checkout -- {Path(*Path(str(path)).parts[-4:])}"
        )
    return read_record(_io.BytesIO(data), what=f"shipped weights record {name!r}")


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


@contextlib.contextmanager
def training_lock(workdir: str | os.PathLike) -> Iterator[None]:
    """Exclusive use of a training's cache folder (``workdir``, created): a second process that trains into the same
    folder waits for the first, saying so on stderr, then finds the training done and loads it (two trainings at
    once collided in orbax's step folders). An ``flock`` on ``workdir/.lock`` (``placejax.io.run_lock``), dropped
    by the kernel when its holder dies.

    The processes of one multi-process run train together and do not lock (each would wait for the others at
    their first collective).
    """
    import jax

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    if jax.process_count() > 1:
        yield
        return
    with io.run_lock(workdir, wait=True):
        yield
