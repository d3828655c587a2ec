"""One self-describing file for a classifier: a zip of ``manifest.json`` and one ``.npy`` per array.

The manifest names the format and its version, the library versions that wrote it, everything needed to rebuild
the models (config, grid, preprocessing) and, per array, its shape, dtype and SHA-256 of its bytes; the member
``manifest.sha256`` holds the SHA-256 of the manifest's own bytes (format version 2; version 1 files, written
before it existed, are still read, their manifest covered by the zip's CRC only). Writing goes to a temporary file
beside the target, fsynced, then renamed: a reader never sees half a file.

Reading treats the file as hostile and refuses anything wrong with an :class:`ArtefactError` naming the file and
the field, before allocating what the file declares:

  * the manifest is at most ``MAX_MANIFEST_BYTES``, strict UTF-8 JSON nested at most ``MAX_JSON_DEPTH`` deep,
    without duplicate keys, and (version 2) matches its checksum; its whole array table is validated (known
    dtypes, at most ``MAX_ARRAYS`` names of safe characters, no name inside another's folder, 64-digit hex
    digests) and, through ``validate``, the rest of it, before any array is read;
  * the arrays together declare at most ``max_bytes`` (default ``DEFAULT_MAX_BYTES``), checked on the table
    before reading; each member must be unencrypted, inside
    the file, at most its ``.npy`` header plus its declared data (stored or deflated only: Python's zipfile
    inflates bzip2 and LZMA in unbounded steps), and all compressed members together may
    expand at most ``MAX_INFLATION``× (1 MiB exempt); each ``.npy`` header is parsed and checked against the
    table before the data is touched, and each array is read once into its own buffer (no further copies).
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from placejax.io import atomic_write

FORMAT = "placejax.PlaceClassifier"
VERSION = 2
READABLE_VERSIONS = (1, 2)
_MANIFEST = "manifest.json"
_MANIFEST_SHA = "manifest.sha256"

DEFAULT_MAX_BYTES = 4 << 30
"""Default bound on the bytes of array data a classifier file may declare (two full-width VGG16s and a depth
network take about 1.2 GB)."""
MAX_MANIFEST_BYTES = 16 << 20
"""Bound on ``manifest.json`` (a real one is ~100 KB, most of it the config and the unknown-place scores)."""
MAX_JSON_DEPTH = 32
MAX_ARRAYS = 1 << 14
MAX_NDIM = 8
MAX_INFLATION = 64
_INFLATION_FREE = 1 << 20
_NPY_HEADER_MAX = 1 << 16  # numpy writes headers of at most a few hundred bytes; it reads up to 10000
_CHUNK = 16 << 20
# The dtypes a parameter may have (np.dtype(...).str); anything else (objects, structures, void) is refused.
_DTYPES = frozenset(
    {"|b1", "|i1", "|u1"}
    | {f"{order}{kind}{size}" for order in "<>" for kind in "iu" for size in (2, 4, 8)}
    | {f"{order}f{size}" for order in "<>" for size in (2, 4, 8)}
)
_NAME = re.compile(r"[A-Za-z0-9_.\-]{1,128}(/[A-Za-z0-9_.\-]{1,128}){0,15}")
_HEX64 = re.compile(r"[0-9a-f]{64}")
# zipfile inflates deflate in bounded steps but bzip2 and LZMA in unbounded ones (a few KB can become GBs
# before it cuts the output to the declared size), so only these two are read; the writer uses the first.
_COMPRESSIONS = {zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED}


class ArtefactError(ValueError):
    """A classifier file that cannot be used: not one, corrupt, truncated, over a budget, of another format
    version, or with a manifest that breaks its schema; the message names the file and the field."""


def _digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def write_artefact(path: str | os.PathLike, manifest: dict[str, Any], arrays: dict[str, np.ndarray]) -> Path:
    """Writes ``manifest`` (JSON-able) and ``arrays`` (flat name → array) to ``path`` atomically.

    Args:
        path: the file to write (its folder is created).
        manifest: JSON-able fields; ``format``, ``version`` and ``arrays`` are added here.
        arrays: ``{"a/b/c": array}`` of plain numeric arrays, stored C-contiguous as ``.npy``.

    Returns:
        ``path`` as a ``Path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # np.ascontiguousarray alone would turn a 0-d array into shape (1,)
    arrays = {k: np.ascontiguousarray(v).reshape(np.shape(v)) for k, v in arrays.items()}
    table = {k: {"shape": list(a.shape), "dtype": a.dtype.str, "sha256": _digest(a)} for k, a in arrays.items()}
    full = {"format": FORMAT, "version": VERSION, **manifest, "arrays": table}
    text = json.dumps(full, indent=2, sort_keys=True).encode()
    with atomic_write(path) as f, zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED) as z:
        z.writestr(_MANIFEST, text)
        z.writestr(_MANIFEST_SHA, hashlib.sha256(text).hexdigest())
        for k, a in arrays.items():
            buf = io.BytesIO()
            np.save(buf, a, allow_pickle=False)
            z.writestr(f"arrays/{k}.npy", buf.getvalue())
    return path


# ---------------------------------------------------------------------------------------------------- reading


class _Archive:
    """A zip read with bounded cost: each member checked against the file before its bytes are allocated."""

    def __init__(self, path: Path, f: BinaryIO):
        self.path = path
        self.size = os.fstat(f.fileno()).st_size
        try:
            self.zip = zipfile.ZipFile(f)
            infos = self.zip.infolist()
        except Exception as e:  # BadZipFile, ValueError, struct.error, ... from zipfile's parser
            raise ArtefactError(f"{path} is not a placejax classifier file (not a zip archive: {e})") from None
        self.infos = {i.filename: i for i in infos}
        if len(self.infos) != len(infos):
            raise ArtefactError(f"{path}: the zip archive holds several members of one name: corrupt file")
        self.inflated = self.stored = 0

    def read(self, name: str, limit: int, what: str) -> bytearray:
        info = self.infos.get(name)
        if info is None:
            raise KeyError(name)
        p = self.path
        if info.flag_bits & 0x1:
            raise ArtefactError(f"{p}: {what} ({name}) is encrypted; classifier files are never encrypted")
        if info.compress_type not in _COMPRESSIONS:
            raise ArtefactError(
                f"{p}: {what} ({name}) uses zip compression method {info.compress_type}, which is not read "
                "(only stored and deflate are: bzip2 and LZMA cannot be inflated in bounded steps)"
            )
        if info.file_size > limit:
            raise ArtefactError(f"{p}: {what} ({name}) declares {info.file_size} bytes, more than its limit of {limit}")
        if info.header_offset + info.compress_size > self.size:
            raise ArtefactError(f"{p}: {what} ({name}) extends past the end of the file: truncated or corrupt")
        if info.compress_type == zipfile.ZIP_STORED and info.compress_size != info.file_size:
            raise ArtefactError(f"{p}: {what} ({name}) stores {info.compress_size} bytes but declares {info.file_size}")
        if info.compress_type != zipfile.ZIP_STORED:
            self.inflated += info.file_size
            self.stored += info.compress_size
            if self.inflated > max(_INFLATION_FREE, MAX_INFLATION * self.stored):
                raise ArtefactError(
                    f"{p}: {what} ({name}) would bring the bytes inflated from compressed members to "
                    f"{self.inflated} from {self.stored} stored, more than {MAX_INFLATION}×: refused as a likely "
                    "decompression bomb (PlaceClassifier.save stores members uncompressed)"
                )
        buf = bytearray(info.file_size)
        view = memoryview(buf)
        try:
            with self.zip.open(info) as f:
                got = 0
                while got < len(buf):
                    n = f.readinto(view[got : got + min(_CHUNK, len(buf) - got)])
                    if not n:
                        break
                    got += n
                overrun = f.read(1) != b""  # the last read also makes zipfile check the CRC
        except Exception as e:  # BadZipFile (CRC), zlib.error, EOFError, OSError, LZMAError, ...
            raise ArtefactError(f"{p}: {what} ({name}) is damaged ({type(e).__name__}: {e})") from None
        if got != len(buf) or overrun:
            raise ArtefactError(f"{p}: {what} ({name}) does not hold its declared {len(buf)} bytes: corrupt file")
        return buf


# A JSON string, escapes included; an unterminated one runs to the end of the text. Written so that it never fails
# to match at a quote: a pattern that can fail there is retried at every later quote, which made text such as
# '"' + '\\"' * n quadratic (40,000 pairs, 80 KB, took a minute).
_JSON_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"?', re.S)


def _json_depth(raw: bytes) -> int:
    """Deepest nesting of ``[``/``{`` in JSON text (strings blanked first); linear time, no recursion."""
    text = _JSON_STRING.sub(b'""', raw)
    step = np.frombuffer(text, np.uint8)
    delta = np.isin(step, (ord("["), ord("{"))).astype(np.int64) - np.isin(step, (ord("]"), ord("}")))
    return int(np.cumsum(delta).max(initial=0))


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out = dict(pairs)
    if len(out) != len(pairs):
        seen: set[str] = set()
        dup = next(k for k, _ in pairs if k in seen or seen.add(k))
        raise ValueError(f"key {dup[:80]!r} appears twice in one object")
    return out


def _parse_manifest(path: Path, raw: bytes) -> dict[str, Any]:
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ArtefactError(f"{path}: {_MANIFEST} is not UTF-8 text ({e})") from None
    depth = _json_depth(raw)
    if depth > MAX_JSON_DEPTH:
        raise ArtefactError(f"{path}: {_MANIFEST} is nested {depth} levels deep, more than {MAX_JSON_DEPTH}")
    try:
        manifest = json.loads(text, object_pairs_hook=_no_duplicates)
    except (ValueError, RecursionError) as e:  # JSONDecodeError, duplicate keys, integers of > 4300 digits
        raise ArtefactError(f"{path}: unreadable {_MANIFEST} ({e})") from None
    if type(manifest) is not dict:
        raise ArtefactError(f"{path}: {_MANIFEST} holds a JSON {type(manifest).__name__}, expected an object")
    return manifest


def _check_table(path: Path, manifest: dict[str, Any], max_bytes: int) -> dict[str, tuple[tuple[int, ...], str, str]]:
    """``{name: (shape, dtype, sha256)}`` of the manifest's ``arrays`` table, fully validated."""
    table = manifest.get("arrays")
    if type(table) is not dict:
        raise ArtefactError(f"{path}: manifest field 'arrays' is {type(table).__name__}, expected an object")
    if len(table) > MAX_ARRAYS:
        raise ArtefactError(f"{path}: manifest field 'arrays' lists {len(table)} arrays, more than {MAX_ARRAYS}")
    out = {}
    total = 0
    for name, meta in table.items():
        field = f"arrays[{name[:80]!r}]"
        if not _NAME.fullmatch(name) or any(part in (".", "..") for part in name.split("/")):
            raise ArtefactError(
                f"{path}: manifest field {field}: not a parameter name ('/'-separated parts of letters, digits, "
                "'_', '.', '-')"
            )
        if type(meta) is not dict or set(meta) != {"shape", "dtype", "sha256"}:
            keys = sorted(meta)[:8] if type(meta) is dict else type(meta).__name__
            raise ArtefactError(f"{path}: manifest field {field} must hold exactly shape, dtype, sha256; got {keys}")
        shape, dtype, sha = meta["shape"], meta["dtype"], meta["sha256"]
        if (
            type(shape) is not list
            or len(shape) > MAX_NDIM
            or not all(type(n) is int and 0 <= n < 1 << 40 for n in shape)
        ):
            raise ArtefactError(
                f"{path}: manifest field {field}.shape must be a list of at most {MAX_NDIM} sizes in [0, 2**40)"
            )
        if type(dtype) is not str or dtype not in _DTYPES:
            raise ArtefactError(
                f"{path}: manifest field {field}.dtype is {str(dtype)[:40]!r}, not a plain numeric dtype"
            )
        if type(sha) is not str or not _HEX64.fullmatch(sha):
            raise ArtefactError(f"{path}: manifest field {field}.sha256 is not 64 lowercase hex digits")
        total += math.prod(shape) * np.dtype(dtype).itemsize
        if total > max_bytes:
            raise ArtefactError(
                f"{path}: manifest field 'arrays' declares more than max_bytes={max_bytes} bytes of arrays "
                f"(at {field}); pass a larger max_bytes if the file is trusted"
            )
        out[name] = (tuple(shape), dtype, sha)
    for name in out:
        parts = name.split("/")
        for i in range(1, len(parts)):
            folder = "/".join(parts[:i])
            if folder in out:
                raise ArtefactError(
                    f"{path}: manifest field 'arrays' names both {folder!r} and {name!r}: one array cannot also "
                    "be a folder"
                )
    return out


def _read_array(path: Path, archive: _Archive, name: str, shape: tuple[int, ...], dtype: str, sha: str) -> np.ndarray:
    what = f"array {name!r}"
    nbytes = math.prod(shape) * np.dtype(dtype).itemsize
    try:
        buf = archive.read(f"arrays/{name}.npy", nbytes + _NPY_HEADER_MAX, what)
    except KeyError:
        raise ArtefactError(f"{path}: {what} listed in the manifest is missing") from None
    stream = io.BytesIO(buf)
    try:
        major, _ = np.lib.format.read_magic(stream)
        if major not in (1, 2, 3):
            raise ValueError(f"unknown .npy format version {major}")
        reader = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
        have_shape, fortran, have_dtype = reader(stream, max_header_size=_NPY_HEADER_MAX)
    except Exception as e:  # ValueError and SyntaxError from numpy's header parser
        raise ArtefactError(f"{path}: {what} is corrupt (bad .npy header: {e})") from None
    if tuple(have_shape) != shape or have_dtype.str != dtype:
        raise ArtefactError(
            f"{path}: {what} has shape {list(have_shape)} dtype {have_dtype.str}, the manifest says "
            f"shape {list(shape)} dtype {dtype}"
        )
    offset = stream.tell()
    if len(buf) - offset != nbytes:
        raise ArtefactError(f"{path}: {what} holds {len(buf) - offset} data bytes, its shape needs {nbytes}")
    a = np.frombuffer(buf, np.dtype(dtype), math.prod(shape), offset).reshape(shape, order="F" if fortran else "C")
    digest = _digest(a) if fortran else hashlib.sha256(memoryview(buf)[offset:]).hexdigest()
    if digest != sha:
        raise ArtefactError(f"{path}: {what} fails its SHA-256 check (the file is corrupt)")
    return a


def read_artefact(
    path: str | os.PathLike,
    *,
    max_bytes: int = DEFAULT_MAX_BYTES,
    validate: Callable[[dict[str, Any], str], None] | None = None,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``(manifest, arrays)`` of a file written by :func:`write_artefact`, everything checked before use.

    Args:
        path: the classifier file.
        max_bytes: the most bytes of array data the file may declare (checked before any array is read).
        validate: called as ``validate(manifest, str(path))`` after the generic checks and before any array is
            read; raises :class:`ArtefactError` for a manifest its caller cannot use.

    Returns:
        The manifest (a dict) and ``{name: array}`` (writable, C- or as-stored order).

    Raises:
        FileNotFoundError: no such file.
        ArtefactError: anything else wrong, with the file's name (and the field) in the message.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"classifier file {path} does not exist")
    if type(max_bytes) is not int or max_bytes < 0:
        raise ValueError(f"max_bytes must be a non-negative int, got {max_bytes!r}")
    with open(path, "rb") as f:
        archive = _Archive(path, f)
        with archive.zip:
            try:
                raw = bytes(archive.read(_MANIFEST, MAX_MANIFEST_BYTES, _MANIFEST))
            except KeyError:
                raise ArtefactError(f"{path} is not a placejax classifier file (no {_MANIFEST})") from None
            manifest = _parse_manifest(path, raw)
            if manifest.get("format") != FORMAT:
                raise ArtefactError(f"{path}: format {str(manifest.get('format'))[:80]!r}, expected {FORMAT!r}")
            version = manifest.get("version")
            if type(version) is not int or version not in READABLE_VERSIONS:
                raise ArtefactError(
                    f"{path}: format version {str(version)[:20]!r}; this placejax reads versions "
                    f"{', '.join(map(str, READABLE_VERSIONS))}"
                )
            if version >= 2 or _MANIFEST_SHA in archive.infos:
                try:
                    want = bytes(archive.read(_MANIFEST_SHA, 64, _MANIFEST_SHA)).decode("ascii", "replace")
                except KeyError:
                    raise ArtefactError(f"{path}: no {_MANIFEST_SHA} (version {version} files have one)") from None
                if want != hashlib.sha256(raw).hexdigest():
                    raise ArtefactError(f"{path}: {_MANIFEST} fails its SHA-256 check ({_MANIFEST_SHA}): corrupt file")
            table = _check_table(path, manifest, max_bytes)
            if validate is not None:
                validate(manifest, str(path))
            arrays = {name: _read_array(path, archive, name, *spec) for name, spec in table.items()}
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
    """The sub-tree under ``prefix/`` of a flat dict, nested again (names must not clash: see ``read_artefact``)."""
    out: dict[str, Any] = {}
    for k, v in flat.items():
        if not k.startswith(prefix + "/"):
            continue
        *parents, leaf = k[len(prefix) + 1 :].split("/")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ArtefactError(f"array {k!r} lies inside array {p!r}")
        if leaf in node:
            raise ArtefactError(f"array {k!r} is also a folder of arrays")
        node[leaf] = v
    return out
