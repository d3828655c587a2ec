"""Reading image files with a budget: the header's dimensions are checked before anything is decoded.

A few hundred bytes of PNG or JPEG can claim 20000 × 20000 pixels, which OpenCV would decode into gigabytes
(its own limit, ``OPENCV_IO_MAX_IMAGE_PIXELS``, defaults to 2**30 pixels and is read once, when cv2 is first
imported, so it cannot be set from here). So the dimensions are read from the file's header here, for the formats
accepted (PNG, JPEG, BMP, GIF, WebP, TIFF, PNM), and checked against ``max_pixels`` before OpenCV sees the file;
other formats are refused rather than decoded blind.

Two steps for readers that know more about the image than a budget (the session folders know its size from
``camera.json``): :func:`read_encoded` reads the file and its header, :func:`decode` decodes it. :func:`read_image`
does both for a photograph (RGB uint8), as ``python -m placejax.classify`` reads its images.
"""

from __future__ import annotations

import dataclasses
import os
import re
import stat
import struct
from pathlib import Path

import numpy as np

__all__ = [
    "MAX_IMAGE_FILE_BYTES",
    "MAX_IMAGE_PIXELS",
    "EncodedImage",
    "ImageError",
    "decode",
    "image_dimensions",
    "read_encoded",
    "read_image",
]

MAX_IMAGE_PIXELS = 1 << 25
"""Default bound on an image's width × height (33.5 Mpx, e.g. 7000 × 4700); decoding one such RGB image holds
about 0.3 GB at once (the decoded image, its RGB copy)."""
MAX_IMAGE_FILE_BYTES = 256 << 20
"""Default bound on an image file's size, bytes (it is read whole before decoding)."""

_FORMATS = "PNG, JPEG, BMP, GIF, WebP, TIFF, PNM"
_HEAD_BYTES = 1 << 16
# JPEG start-of-frame markers (ITU T.81 table B.1): all SOFn except DHT (C4), JPG (C8) and DAC (CC).
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_PNM = re.compile(rb"P[1-6](?:\s|#[^\n]*\n)+(\d{1,12})(?:\s|#[^\n]*\n)+(\d{1,12})\s")


class ImageError(ValueError):
    """An image file that is not read: unknown format, a header without dimensions, or over a budget."""


def _png(d: bytes) -> tuple[int, int] | None:
    if len(d) >= 24 and d[12:16] == b"IHDR":
        return struct.unpack(">II", d[16:24])
    return None


def _jpeg(d: bytes) -> tuple[int, int] | None:
    i = 2
    while i + 4 <= len(d):
        if d[i] != 0xFF:
            return None
        marker = d[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # standalone markers
            i += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, or scan data before any frame header
            return None
        (length,) = struct.unpack(">H", d[i + 2 : i + 4])
        if marker in _SOF:
            if i + 9 > len(d):
                return None
            h, w = struct.unpack(">HH", d[i + 5 : i + 9])
            return (w, h) if h > 0 else None  # height 0: defined later by a DNL marker, refused
        i += 2 + length
    return None


def _bmp(d: bytes) -> tuple[int, int] | None:
    if len(d) < 26:
        return None
    (size,) = struct.unpack("<I", d[14:18])
    if size == 12:  # OS/2 BITMAPCOREHEADER
        return struct.unpack("<HH", d[18:22])
    w, h = struct.unpack("<ii", d[18:26])
    return abs(w), abs(h)  # a negative height means rows stored top-down


def _gif(d: bytes) -> tuple[int, int] | None:
    if len(d) < 13:
        return None
    w, h = struct.unpack("<HH", d[6:10])
    i = 13 + (3 << ((d[10] & 7) + 1) if d[10] & 0x80 else 0)
    while i < len(d):  # the first frame may reach beyond the logical screen
        if d[i] == 0x2C and i + 9 <= len(d):
            left, top, fw, fh = struct.unpack("<HHHH", d[i + 1 : i + 9])
            return max(w, left + fw), max(h, top + fh)
        if d[i] != 0x21 or i + 2 > len(d):
            return None
        i += 2  # extension introducer and label, then sub-blocks until a zero-length one
        while i < len(d) and d[i]:
            i += d[i] + 1
        i += 1
    return None


def _webp(d: bytes) -> tuple[int, int] | None:
    kind = d[12:16]
    if kind == b"VP8 " and len(d) >= 30:
        w, h = struct.unpack("<HH", d[26:30])
        return w & 0x3FFF, h & 0x3FFF
    if kind == b"VP8L" and len(d) >= 25:
        (bits,) = struct.unpack("<I", d[21:25])
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if kind == b"VP8X" and len(d) >= 30:
        return int.from_bytes(d[24:27], "little") + 1, int.from_bytes(d[27:30], "little") + 1
    return None


def _tiff(d: bytes) -> tuple[int, int] | None:
    order = "<" if d[:2] == b"II" else ">"
    if len(d) < 8:
        return None
    (ifd,) = struct.unpack(order + "I", d[4:8])
    if ifd + 2 > len(d):
        return None
    (count,) = struct.unpack(order + "H", d[ifd : ifd + 2])
    dims = {}
    for k in range(count):
        e = ifd + 2 + 12 * k
        if e + 12 > len(d):
            return None
        tag, kind = struct.unpack(order + "HH", d[e : e + 4])
        if tag in (256, 257):  # ImageWidth, ImageLength: SHORT (3) or LONG (4)
            if kind == 3:
                dims[tag] = struct.unpack(order + "H", d[e + 8 : e + 10])[0]
            elif kind == 4:
                dims[tag] = struct.unpack(order + "I", d[e + 8 : e + 12])[0]
    return (dims[256], dims[257]) if len(dims) == 2 else None


def image_dimensions(data: bytes) -> tuple[str, tuple[int, int] | None] | None:
    """``(format, (width, height))`` read from an image file's header, without decoding it.

    Args:
        data: the file's first bytes (the whole file for JPEG, GIF and TIFF, whose dimensions may come late).

    Returns:
        The format's name and its dimensions in pixels (None where the header holds none that can be trusted),
        or None for a format not accepted here.
    """
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "PNG", _png(data)
    if data[:3] == b"\xff\xd8\xff":
        return "JPEG", _jpeg(data)
    if data[:2] == b"BM":
        return "BMP", _bmp(data)
    if data[:6] in (b"GIF87a", b"GIF89a"):
        return "GIF", _gif(data)
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "WebP", _webp(data)
    if data[:4] in (b"II*\x00", b"MM\x00*"):
        return "TIFF", _tiff(data)
    if re.match(rb"P[1-6]", data[:2]):
        m = _PNM.match(data[:4096])
        return "PNM", (int(m.group(1)), int(m.group(2))) if m else None
    return None


@dataclasses.dataclass(frozen=True)
class EncodedImage:
    """An image file read whole but not decoded, with the dimensions its header declares.

    Attributes:
        path: the file.
        data: uint8 ``(bytes,)`` the file's content.
        kind: the format's name (``"PNG"``, ``"JPEG"``, ...).
        width, height: pixels, from the header; ``width * height`` is within the budget it was read with.
    """

    path: Path
    data: np.ndarray
    kind: str
    width: int
    height: int


def read_encoded(
    path: str | os.PathLike, *, max_pixels: int = MAX_IMAGE_PIXELS, max_file_bytes: int = MAX_IMAGE_FILE_BYTES
) -> EncodedImage:
    """Reads an image file and checks the dimensions its header declares, decoding nothing.

    Args:
        path: a PNG, JPEG, BMP, GIF, WebP, TIFF or PNM file.
        max_pixels: the most pixels (width × height) the header may declare.
        max_file_bytes: the largest file read.

    Returns:
        The file's bytes and its header's format and dimensions.

    Raises:
        FileNotFoundError: no such file.
        ImageError: unreadable, another format, a header without dimensions, an empty image or over a budget;
            the message starts with the file and names the limit.
    """
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such file") from None
    except OSError as e:  # a name too long for the file system, a folder without permission, ...
        raise ImageError(f"{path}: cannot be read ({e.strerror or e})") from None
    if not stat.S_ISREG(st.st_mode):
        raise ImageError(f"{path}: not a regular file")
    if st.st_size > max_file_bytes:
        raise ImageError(
            f"{path}: a file of {st.st_size} bytes, more than the limit of {max_file_bytes} bytes for an image"
        )
    try:
        data = np.fromfile(p, np.uint8)
    except OSError as e:
        raise ImageError(f"{path}: cannot be read ({e.strerror or e})") from None
    # Most headers sit in the first bytes; JPEG, GIF and TIFF may give their size later (one more copy then).
    found = image_dimensions(data[:_HEAD_BYTES].tobytes()) if data.size else None
    if found is not None and found[1] is None and data.size > _HEAD_BYTES:
        found = image_dimensions(data.tobytes())
    if found is None:
        raise ImageError(f"{path}: not an image file in a format read here ({_FORMATS})")
    kind, dims = found
    if dims is None:
        raise ImageError(f"{path}: a {kind} file whose header gives no usable image size: truncated or corrupt")
    w, h = dims
    if w < 1 or h < 1 or w * h > max_pixels:
        raise ImageError(
            f"{path}: its {kind} header declares {w} × {h} pixels, beyond the limit of {max_pixels} pixels (max_pixels)"
            if w * h > max_pixels
            else f"{path}: its {kind} header declares an empty image ({w} × {h})"
        )
    return EncodedImage(p, data, kind, int(w), int(h))


def decode(image: EncodedImage, flags: int | None = None) -> np.ndarray:
    """Decodes an image read by :func:`read_encoded` with OpenCV (BGR channel order, as ``cv2.imdecode``).

    Args:
        image: the file read.
        flags: ``cv2.IMREAD_*`` (default ``cv2.IMREAD_COLOR``: uint8 ``(H, W, 3)``).

    Returns:
        The decoded array, at most the header's ``width × height`` pixels.

    Raises:
        ImageError: OpenCV cannot decode the file (damaged data behind a valid header), or the decoded size is not
            the header's.
    """
    import cv2

    flags = cv2.IMREAD_COLOR if flags is None else flags
    # OpenCV logs its own warnings about damaged files to stderr; the error raised here says it in one line.
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        img = cv2.imdecode(image.data, flags)
    except cv2.error as e:
        msg = str(e).strip().splitlines()[-1]
        raise ImageError(f"{image.path}: OpenCV cannot decode this {image.kind} file ({msg})") from None
    finally:
        cv2.utils.logging.setLogLevel(level)
    if img is None:
        raise ImageError(f"{image.path}: OpenCV cannot decode this {image.kind} file (damaged or truncated data)")
    if img.shape[0] * img.shape[1] > image.width * image.height:  # the header lied (only a corrupt file can)
        raise ImageError(
            f"{image.path}: decoded to {img.shape[1]} × {img.shape[0]} pixels, more than its {image.kind} header's "
            f"{image.width} × {image.height}"
        )
    return img


def read_image(
    path: str | os.PathLike, *, max_pixels: int = MAX_IMAGE_PIXELS, max_file_bytes: int = MAX_IMAGE_FILE_BYTES
) -> np.ndarray:
    """uint8 ``(H, W, 3)`` RGB of an image file, its size checked from its header before decoding.

    Args:
        path: a PNG, JPEG, BMP, GIF (first frame), WebP, TIFF (first page) or PNM file.
        max_pixels: the most pixels (width × height) the header may declare.
        max_file_bytes: the largest file read.

    Returns:
        uint8 ``(H, W, 3)``, RGB.

    Raises:
        FileNotFoundError: no such file.
        ImageError: another format, a header without dimensions, over a budget, or undecodable; the message
            names the file and the limit.
    """
    import cv2

    img = decode(read_encoded(path, max_pixels=max_pixels, max_file_bytes=max_file_bytes), cv2.IMREAD_COLOR)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ImageError(f"{path}: not an image file OpenCV can decode as colour")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
