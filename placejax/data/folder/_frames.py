"""Image and depth files of a session folder, each header checked against ``camera.json`` before it is decoded."""

from __future__ import annotations

import os
import stat
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from placejax.data import images
from placejax.data.folder._errors import FolderFormatError, _err, _quote
from placejax.data.folder._limits import FolderLimits
from placejax.io import file_kind

__all__ = ["DEPTH_DIR", "DEPTH_SUFFIXES"]

DEPTH_DIR = "depth"
"""The optional folder of a session's depth files."""
DEPTH_SUFFIXES = (".png", ".npy", ".tif", ".tiff")
"""Suffixes of depth files: uint16 millimetre PNGs, float metre ``.npy`` and TIFF files."""
_FLOATS = (np.float16, np.float32, np.float64)


def present(path: Path, kind: str = "file") -> bool:
    """Whether an optional entry of a session folder is there: ``False`` when nothing is at ``path``, ``True`` for a
    regular file (``kind="file"``) or a folder (``kind="folder"``), symbolic links followed.

    Raises:
        FolderFormatError: something else is there (a FIFO, a device, a socket, a folder where a file belongs or a
            file where a folder does): it is named, never read as absent (which would change silently what is
            trained or tested).
    """
    try:
        mode = path.stat().st_mode
    except (FileNotFoundError, NotADirectoryError):
        return False
    except OSError as e:
        raise _err(path, None, f"cannot be read ({e.strerror or e})") from None
    if (stat.S_ISREG(mode) and kind == "file") or (stat.S_ISDIR(mode) and kind == "folder"):
        return True
    what = file_kind(mode)
    raise _err(path, None, f"is a {what}, not a {'regular file' if kind == 'file' else 'folder'}: remove or replace it")


def _is_file(path: Path) -> bool:
    """``path.is_file()``, a file name the file system refuses (too long, ...) a :class:`FolderFormatError`."""
    try:
        return path.is_file()
    except OSError as e:
        raise _err(path.parent, None, f"cannot look for {_quote(path.name)} ({e.strerror or e})") from None


def _encoded(path: Path, what: str, shape: tuple[int, int], limits: FolderLimits) -> images.EncodedImage:
    try:
        enc = images.read_encoded(path, max_pixels=limits.max_image_pixels, max_file_bytes=limits.max_image_file_bytes)
    except FileNotFoundError:
        raise _err(path, None, f"{what} file missing") from None
    except images.ImageError as e:
        raise _err(path, None, str(e).removeprefix(f"{path}: ")) from None
    if (enc.height, enc.width) != shape:
        raise _err(
            path,
            None,
            f"{what} is {enc.width} x {enc.height} (W x H), camera.json says {shape[1]} x {shape[0]} "
            "(images of different sizes?)",
        )
    return enc


def _decoded(enc: images.EncodedImage) -> np.ndarray:
    try:
        return images.decode(enc, cv2.IMREAD_UNCHANGED)
    except images.ImageError as e:
        raise _err(enc.path, None, f"unreadable or truncated image ({str(e).removeprefix(f'{enc.path}: ')})") from None


def _decode_image(path: Path, shape: tuple[int, int], limits: FolderLimits) -> np.ndarray:
    """RGB uint8 ``(H, W, 3)`` of an image file (grey images repeated, alpha dropped).

    Args:
        path: the file.
        shape: ``(H, W)`` that ``camera.json`` gives; the header must declare it.
        limits: the file-size and pixel budgets.

    Raises:
        FolderFormatError: naming the file: missing, over a budget, another size, undecodable, not 8-bit.
    """
    img = _decoded(_encoded(path, "image", shape, limits))
    if img.dtype != np.uint8:
        raise _err(path, None, f"expected an 8-bit image, got {img.dtype}")
    if img.ndim == 2:
        return np.ascontiguousarray(np.repeat(img[:, :, None], 3, axis=2))
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    if img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    raise _err(path, None, f"expected a grey, RGB or RGBA image, got {img.shape[2]} channels")


def _npy(path: Path, shape: tuple[int, int], limits: FolderLimits) -> np.ndarray:
    """A 2-D float ``.npy`` of ``shape``, its header read and checked before the array is."""
    try:
        size = path.stat().st_size
        if size > limits.max_image_file_bytes + 4096:  # a whole header's worth more than the image budget
            raise _err(path, None, f"a file of {size} bytes, more than {limits.max_image_file_bytes} (depth file)")
        with path.open("rb") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                dims, fortran, dtype = np.lib.format.read_array_header_1_0(f)
            elif version == (2, 0):
                dims, fortran, dtype = np.lib.format.read_array_header_2_0(f)
            else:
                raise _err(path, None, f".npy format version {version}, expected 1.0 or 2.0")
            if dtype not in _FLOATS or len(dims) != 2:
                raise _err(path, None, f"expected a 2-D float array of metres, got {dtype} {tuple(dims)}")
            if int(np.prod(dims, dtype=object)) > limits.max_image_pixels:
                raise _err(path, None, f"declares {tuple(dims)}, more than {limits.max_image_pixels} values")
            if tuple(dims) != shape:
                raise _err(
                    path,
                    None,
                    f"depth is {dims[1]} x {dims[0]} (W x H), camera.json says {shape[1]} x {shape[0]}",
                )
            if size < f.tell() + dtype.itemsize * shape[0] * shape[1]:
                raise _err(path, None, f"truncated: {size} bytes for a {dtype} array of {tuple(dims)}")
            d = np.fromfile(f, dtype, count=shape[0] * shape[1])
    except FolderFormatError:
        raise
    except (ValueError, OSError) as e:  # numpy's header parser, a file that vanished or cannot be read
        raise _err(path, None, f"unreadable depth array ({str(e)[:200]})") from None
    return d.reshape(shape, order="F" if fortran else "C").astype(np.float32)


def _decode_depth(path: Path, shape: tuple[int, int], limits: FolderLimits) -> np.ndarray:
    """float32 metres ``(H, W)`` of a depth file (uint16 PNG millimetres, or float .npy / .tiff metres).

    Args:
        path: the file.
        shape: ``(H, W)`` of the images (``camera.json``); the file's header must declare it.
        limits: the file-size and pixel budgets.

    Raises:
        FolderFormatError: naming the file: missing, over a budget, another size or kind, undecodable.
    """
    if not _is_file(path):
        raise _err(path, None, "depth file missing")
    if path.suffix.lower() == ".npy":
        return _npy(path, shape, limits)
    d = _decoded(_encoded(path, "depth", shape, limits))
    if d.ndim != 2:
        raise _err(path, None, f"expected a 1-channel depth image, got shape {d.shape}")
    if d.dtype == np.uint16:
        return d.astype(np.float32) / np.float32(1000.0)  # millimetres, as TUM RGB-D writes them; 0 = missing
    if d.dtype in (np.float32, np.float64):
        return d.astype(np.float32)
    raise _err(path, None, f"expected uint16 millimetres or float metres, got {d.dtype}")


def _depth_files(folder: Path, files: Sequence[Path], limits: FolderLimits) -> tuple[Path, ...] | None:
    """The depth file of every image (``depth/<image stem>.png``, ``.npy`` or ``.tif(f)``), or None without
    ``depth/``."""
    d = folder / DEPTH_DIR
    if not present(d, "folder"):
        return None
    names = []
    try:
        with os.scandir(d) as it:
            for e in it:
                if os.path.splitext(e.name)[1].lower() in DEPTH_SUFFIXES:
                    if len(names) == limits.max_images:
                        raise _err(d, None, f"more than {limits.max_images} depth files (FolderLimits.max_images)")
                    names.append(e.name)
    except OSError as e:
        raise _err(d, None, f"cannot be listed ({e.strerror or e})") from None
    by_stem: dict[str, Path] = {}
    for name in sorted(names):
        stem = os.path.splitext(name)[0]
        if stem in by_stem:
            raise _err(d / name, None, f"two depth files for image {stem!r}: {by_stem[stem].name} and {name}")
        by_stem[stem] = d / name
    out = []
    for f in files:
        if f.stem not in by_stem:
            raise _err(d, None, f"no depth file for image {f.name} (expected {f.stem}.png, .npy or .tiff)")
        out.append(by_stem[f.stem])
    return tuple(out)
