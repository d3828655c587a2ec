"""One self-describing file for a classifier: a zip of ``manifest.json`` and one ``.npy`` per array.

The manifest names the format and its version, the library versions that wrote it, everything needed to rebuild
the models (config, grid, preprocessing) and, per array, its shape, dtype and SHA-256 of its bytes. Reading checks
all of it and refuses the file with an :class:`ArtefactError` naming the file and what is wrong. Writing goes to
a temporary file beside the target, fsynced, then renamed: a reader never sees half a file.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from placejax.io import atomic_write

FORMAT = "placejax.PlaceClassifier"
VERSION = 1
_MANIFEST = "manifest.json"


class ArtefactError(ValueError):
    """A classifier file that cannot be used: not one, corrupt, truncated, or of another format version."""


def _digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def write_artefact(path: str | os.PathLike, manifest: dict[str, Any], arrays: dict[str, np.ndarray]) -> Path:
    """Writes ``manifest`` (JSON-able) and ``arrays`` (flat name → array) to ``path`` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    table = {k: {"shape": list(a.shape), "dtype": a.dtype.str, "sha256": _digest(a)} for k, a in arrays.items()}
    full = {"format": FORMAT, "version": VERSION, **manifest, "arrays": table}
    with atomic_write(path) as f, zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED) as z:
        z.writestr(_MANIFEST, json.dumps(full, indent=2, sort_keys=True))
        for k, a in arrays.items():
            buf = io.BytesIO()
            np.save(buf, a, allow_pickle=False)
            z.writestr(f"arrays/{k}.npy", buf.getvalue())
    return path


def read_artefact(path: str | os.PathLike) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``(manifest, arrays)`` of a file written by :func:`write_artefact`, every array checked.

    Raises:
        FileNotFoundError: no such file.
        ArtefactError: anything else wrong, with the file's name in the message.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"classifier file {path} does not exist")
    try:
        z = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as e:
        raise ArtefactError(f"{path} is not a placejax classifier file (not a zip archive: {e})") from None
    with z:
        try:
            manifest = json.loads(z.read(_MANIFEST))
        except KeyError:
            raise ArtefactError(f"{path} is not a placejax classifier file (no {_MANIFEST})") from None
        except (json.JSONDecodeError, zipfile.BadZipFile, OSError) as e:
            raise ArtefactError(f"{path}: unreadable {_MANIFEST} ({e})") from None
        if manifest.get("format") != FORMAT:
            raise ArtefactError(f"{path}: format {manifest.get('format')!r}, expected {FORMAT!r}")
        if manifest.get("version") != VERSION:
            raise ArtefactError(
                f"{path}: format version {manifest.get('version')!r}; this placejax reads version {VERSION}"
            )
        arrays = {}
        for name, meta in manifest.get("arrays", {}).items():
            try:
                raw = z.read(f"arrays/{name}.npy")
                a = np.load(io.BytesIO(raw), allow_pickle=False)
            except KeyError:
                raise ArtefactError(f"{path}: array {name!r} listed in the manifest is missing") from None
            except (ValueError, OSError, zipfile.BadZipFile, EOFError) as e:
                raise ArtefactError(f"{path}: array {name!r} is corrupt ({e})") from None
            if list(a.shape) != meta["shape"] or a.dtype.str != meta["dtype"]:
                raise ArtefactError(
                    f"{path}: array {name!r} has shape {list(a.shape)} dtype {a.dtype.str}, the manifest says "
                    f"shape {meta['shape']} dtype {meta['dtype']}"
                )
            if _digest(a) != meta["sha256"]:
                raise ArtefactError(f"{path}: array {name!r} fails its SHA-256 check (the file is corrupt)")
            arrays[name] = a
    return manifest, arrays


def flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, np.ndarray]:
    """Nested dict of arrays → ``{"a/b/c": array}``."""
    out = {}
    for k, v in tree.items():
        if "/" in str(k):
            raise ValueError(f"parameter name {k!r} contains '/'")
        if isinstance(v, dict) or hasattr(v, "items"):
            out.update(flatten(dict(v), f"{prefix}{k}/"))
        else:
            out[f"{prefix}{k}"] = np.asarray(v)
    return out


def unflatten(flat: dict[str, np.ndarray], prefix: str) -> dict[str, Any]:
    """The sub-tree under ``prefix/`` of a flat dict, nested again."""
    out: dict[str, Any] = {}
    for k, v in flat.items():
        if not k.startswith(prefix + "/"):
            continue
        *parents, leaf = k[len(prefix) + 1 :].split("/")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = v
    return out
