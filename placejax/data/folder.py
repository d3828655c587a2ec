"""Your own recordings: one folder per session in a small documented format (``docs/own-data.md``).

A session folder holds::

    camera.json          image size, fx fy cx cy, optional OpenCV distortion, camera height (or "unknown")
    images/              the images, any format OpenCV reads
    images.csv           optional: ``file,timestamp`` (file relative to the session folder, timestamp in s);
                         without it every image's name is its timestamp (``1327251905.811462.png``: seconds,
                         ``1327251905811462.png``: an integer in ``camera.json``'s ``name_time_unit``, default µs)
    poses_tum.txt        TUM RGB-D trajectory ``timestamp tx ty tz qx qy qz qw`` (camera-to-world, metres), or
    poses_kitti.txt      KITTI odometry poses: 12 numbers per line (row-major 3 × 4 camera-to-world), one per image
    depth/               optional: ``<image stem>.png`` (uint16 millimetres, 0 = missing) or ``.npy`` / ``.tiff``
                         (float32 metres), one per image
    odometry.csv         optional wheel odometry: ``timestamp,x,y,yaw`` (s, m, m, rad) or ``timestamp,travelled_m``

Typical use::

    from placejax.data import folder
    s = folder.load_session("/data/campus/2026-01-10")
    print(s.report)                # kept / dropped frame counts
    s.image(0), s.poses[0]         # upright RGB uint8 (H, W, 3); x, y (m), yaw (rad)

Poses are interpolated to every image timestamp (position linearly, orientation by slerp) between the two
trajectory samples around it; an image before the first or after the last sample, or farther than
``tolerance_s`` from its nearest sample, is dropped and counted in :attr:`FolderSession.report`. Every other
defect (unsorted or duplicate timestamps, a missing or unreadable image, a NaN or non-unit quaternion, images of
different sizes, a missing camera field, an empty session) raises :class:`FolderFormatError` whose message
starts with ``file:line:`` (or ``file:`` when no line is to blame).

The planar pose a session reports is ``(x, y, yaw)``: the camera position on the two horizontal world axes and
the heading of its optical axis (camera +z) measured from the first towards the second. ``camera.json``'s
``vertical_axis`` says which world axis is vertical: ``"z"`` (default; z up or down, as in TUM RGB-D, NCLT's
NED frame or any map frame), ``"y"`` (the first camera's frame of visual odometry, e.g. KITTI's ground truth:
horizontal axes z, x) or ``"x"``.
"""

from __future__ import annotations

import dataclasses
import decimal
import hashlib
import itertools
import json
import math
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path

import cv2
import numpy as np

from placejax import io
from placejax.data import camera as _camera

__all__ = [
    "CAMERA_FILE",
    "CameraSpec",
    "FolderFormatError",
    "FolderReport",
    "FolderSession",
    "Trajectory",
    "format_timestamp",
    "interpolate_poses",
    "load_session",
    "load_sessions",
    "matrix_to_quaternion",
    "parse_timestamp",
    "planar_poses",
    "quaternion_to_matrix",
    "read_camera",
    "read_image_table",
    "read_kitti_poses",
    "read_odometry",
    "read_tum",
    "write_poses",
    "write_session",
]

CAMERA_FILE = "camera.json"
"""The file name of a session folder's camera (intrinsics and image size, JSON)."""
_CAMERA_YAML = ("camera.yaml", "camera.yml")
IMAGES_DIR = "images"
IMAGE_TABLE = "images.csv"
TUM_FILE = "poses_tum.txt"
KITTI_FILE = "poses_kitti.txt"
DEPTH_DIR = "depth"
ODOMETRY_FILE = "odometry.csv"
# Suffixes taken as images in images/ when there is no images.csv (what cv2.imread decodes).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm", ".jp2")
_DEPTH_SUFFIXES = (".png", ".npy", ".tif", ".tiff")
_TIME_UNITS = {"s": 0, "ms": 3, "us": 6, "ns": 9}  # decimal places below the second
# A quaternion whose norm is farther than this from 1 is an error, not rounding (TUM files carry 4–7 digits).
QUATERNION_NORM_TOLERANCE = 1e-3
_MAX_US = 2**62
# Plain ASCII decimals (Decimal() alone would also take "1_000", "NaN" and non-ASCII digits).
_DECIMAL = re.compile(r"\+?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


class FolderFormatError(ValueError):
    """A malformed session folder; the message starts with ``path:line:`` or ``path:``."""


def _err(path: Path | str, line: int | None, msg: str) -> FolderFormatError:
    return FolderFormatError(f"{path}:{line}: {msg}" if line is not None else f"{path}: {msg}")


# --------------------------------------------------------------------------------------------------- timestamps


def parse_timestamp(text: str, unit: str = "s") -> int:
    """An exact timestamp in integer microseconds from its decimal text (no float rounding on the way).

    Args:
        text: a decimal number, e.g. ``"1327251905.811462"``.
        unit: unit of ``text``: ``"s"``, ``"ms"``, ``"us"`` or ``"ns"``.

    Returns:
        int µs, rounded half to even below the microsecond.

    Raises:
        ValueError: not a finite, non-negative decimal number, or beyond 2**62 µs.

    Example:
        >>> parse_timestamp("1327251905.811462"), parse_timestamp("1500", "ns")
        (1327251905811462, 2)
    """
    if unit not in _TIME_UNITS:
        raise ValueError(f"time unit must be one of {tuple(_TIME_UNITS)}, got {unit!r}")
    if not _DECIMAL.fullmatch(text.strip()):
        raise ValueError(f"timestamp {text!r} is not a non-negative decimal number")
    d = decimal.Decimal(text.strip())
    us = d.scaleb(6 - _TIME_UNITS[unit]).to_integral_value(rounding=decimal.ROUND_HALF_EVEN)
    if us >= _MAX_US:
        raise ValueError(f"timestamp {text!r} is out of range (>= 2**62 µs)")
    return int(us)


def format_timestamp(us: int) -> str:
    """``us`` microseconds as exact decimal seconds (``"1327251905.811462"``), what the writers use."""
    us = int(us)
    return f"{us // 1_000_000}.{us % 1_000_000:06d}"


def _check_increasing(utimes: Sequence[int], lines: Sequence[int], path: Path, what: str) -> None:
    for k in range(1, len(utimes)):
        if utimes[k] <= utimes[k - 1]:
            kind = "duplicate" if utimes[k] == utimes[k - 1] else "unsorted"
            raise _err(
                path,
                lines[k],
                f"{kind} {what} timestamp {format_timestamp(utimes[k])} s (line {lines[k - 1]} has "
                f"{format_timestamp(utimes[k - 1])} s); timestamps must strictly increase",
            )


def _data_lines(path: Path) -> Iterable[tuple[int, str]]:
    """``(line number, text)`` of every non-blank, non-comment (``#``) line."""
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise _err(path, None, "not a text file") from None
    for n, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield n, s


# --------------------------------------------------------------------------------------------------- rotations


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions in TUM order ``(qx, qy, qz, qw)``.

    Args:
        q: float ``(..., 4)``; normalised here.

    Returns:
        float64 ``(..., 3, 3)``.
    """
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` in TUM order ``(qx, qy, qz, qw)``, ``qw >= 0``, of rotations ``(..., 3, 3)``.

    Shepperd's method: the largest of the four diagonal combinations is the pivot, so no division by a small
    number.
    """
    r = np.asarray(r, np.float64)
    shape = r.shape[:-2]
    r = r.reshape(-1, 3, 3)
    out = np.empty((len(r), 4))
    for k, m in enumerate(r):
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        pivots = [tr, m[0, 0], m[1, 1], m[2, 2]]
        i = int(np.argmax(pivots))
        if i == 0:
            s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
            q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
        elif i == 1:
            s = 2.0 * math.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0))
            q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
        elif i == 2:
            s = 2.0 * math.sqrt(max(1.0 - m[0, 0] + m[1, 1] - m[2, 2], 0.0))
            q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
        else:
            s = 2.0 * math.sqrt(max(1.0 - m[0, 0] - m[1, 1] + m[2, 2], 0.0))
            q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
        q = np.asarray(q)
        q /= np.linalg.norm(q)
        out[k] = -q if q[3] < 0 else q
    return out.reshape(*shape, 4)


def _slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical interpolation ``(N, 4)`` between unit quaternions ``(N, 4)`` at ``t (N,)`` in [0, 1]."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)  # the shorter arc
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    sin = np.sin(theta)
    near = sin < 1e-9
    safe = np.where(near, 1.0, sin)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


_VERTICAL = {"z": (0, 1), "x": (1, 2), "y": (2, 0)}  # horizontal axes (first, second), right-handed cyclic order


def planar_poses(positions: np.ndarray, rotations: np.ndarray, vertical_axis: str = "z") -> np.ndarray:
    """``(N, 3)`` planar poses x, y (m), yaw (rad) of camera-to-world poses.

    Args:
        positions: float ``(N, 3)`` camera centres in the world frame, metres.
        rotations: float ``(N, 3, 3)`` camera-to-world rotations (OpenCV camera axes: x right, y down, z forward).
        vertical_axis: the world axis that is vertical, ``"z"``, ``"y"`` or ``"x"``.

    Returns:
        float64 ``(N, 3)``: the two horizontal coordinates and ``atan2`` of the optical axis on them.

    Example:
        >>> r = np.array([[[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]])   # a level camera looking along +x, z up
        >>> planar_poses(np.array([[1.0, 2, 3]]), r).tolist()
        [[1.0, 2.0, 0.0]]
    """
    if vertical_axis not in _VERTICAL:
        raise ValueError(f"vertical_axis must be one of {tuple(_VERTICAL)}, got {vertical_axis!r}")
    a, b = _VERTICAL[vertical_axis]
    positions, rotations = np.asarray(positions, np.float64), np.asarray(rotations, np.float64)
    fwd = rotations[:, :, 2]
    return np.stack([positions[:, a], positions[:, b], np.arctan2(fwd[:, b], fwd[:, a])], -1)


# --------------------------------------------------------------------------------------------------- parsers


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """Camera-to-world poses at strictly increasing times.

    Attributes:
        utimes: int64 ``(M,)`` µs (KITTI files: ``-1``, they are matched to images by order).
        positions: float64 ``(M, 3)`` metres.
        quaternions: float64 ``(M, 4)`` unit ``(qx, qy, qz, qw)``.
        lines: int64 ``(M,)`` line of each pose in ``path``.
        path: the file read.
    """

    utimes: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    lines: np.ndarray
    path: Path

    def __len__(self) -> int:
        return len(self.positions)


def _floats(path: Path, n: int, fields: list[str], what: str) -> list[float]:
    try:
        values = [float(f) for f in fields]
    except ValueError:
        raise _err(path, n, f"{what}: non-number in {' '.join(fields)!r}") from None
    return values


def _unit_quaternion(path: Path, n: int, q: list[float]) -> list[float]:
    norm = math.sqrt(sum(v * v for v in q))
    if not all(math.isfinite(v) for v in q):
        raise _err(path, n, f"quaternion (qx qy qz qw) = {q} is not finite")
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise _err(path, n, f"quaternion (qx qy qz qw) = {q} has norm {norm:.6g}, not 1 (±{QUATERNION_NORM_TOLERANCE})")
    return [v / norm for v in q]


def read_tum(path: str | os.PathLike) -> Trajectory:
    """Reads a TUM RGB-D trajectory: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments allowed.

    Args:
        path: the file. Timestamps in seconds (any number of decimals, read exactly to the µs); position in
            metres; orientation a unit quaternion, camera-to-world.

    Returns:
        :class:`Trajectory` (quaternions normalised).

    Raises:
        FolderFormatError: ``path:line:`` for a line without 8 numbers, a NaN or infinite value, a quaternion
            whose norm is not 1 (±1e-3), an unsorted or duplicate timestamp; ``path:`` for a missing or empty
            file.
    """
    path = Path(path)
    if not path.is_file():
        raise _err(path, None, "trajectory file not found")
    ts, pos, quat, lines = [], [], [], []
    for n, line in _data_lines(path):
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise _err(path, n, f"expected 8 values 'timestamp tx ty tz qx qy qz qw', got {len(fields)}")
        try:
            t = parse_timestamp(fields[0])
        except ValueError as e:
            raise _err(path, n, str(e)) from None
        v = _floats(path, n, fields[1:], "pose")
        if not all(math.isfinite(x) for x in v[:3]):
            raise _err(path, n, f"position (tx ty tz) = {v[:3]} is not finite")
        ts.append(t)
        pos.append(v[:3])
        quat.append(_unit_quaternion(path, n, v[3:]))
        lines.append(n)
    if not ts:
        raise _err(path, None, "no pose in the trajectory file (empty session)")
    _check_increasing(ts, lines, path, "pose")
    return Trajectory(
        np.array(ts, np.int64), np.array(pos, np.float64), np.array(quat, np.float64), np.array(lines), path
    )


def read_kitti_poses(path: str | os.PathLike) -> Trajectory:
    """Reads KITTI odometry poses: 12 numbers per line, the row-major 3 × 4 camera-to-world ``[R | t]``.

    Returns:
        :class:`Trajectory` with ``utimes`` all ``-1`` (line ``k`` is the pose of the ``k``-th image).

    Raises:
        FolderFormatError: ``path:line:`` for a line without 12 finite numbers or a rotation that is not
            orthonormal with determinant 1 (±1e-3); ``path:`` for a missing or empty file.
    """
    path = Path(path)
    if not path.is_file():
        raise _err(path, None, "pose file not found")
    pos, quat, lines = [], [], []
    for n, line in _data_lines(path):
        fields = line.split()
        if len(fields) != 12:
            raise _err(path, n, f"expected 12 numbers (a row-major 3 x 4 [R | t]), got {len(fields)}")
        m = np.array(_floats(path, n, fields, "pose")).reshape(3, 4)
        if not np.isfinite(m).all():
            raise _err(path, n, "pose is not finite")
        r = m[:, :3]
        err = np.abs(r @ r.T - np.eye(3)).max()
        if err > QUATERNION_NORM_TOLERANCE or abs(np.linalg.det(r) - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise _err(path, n, f"rotation is not orthonormal with determinant 1 (|R Rᵀ − I| = {err:.3g})")
        pos.append(m[:, 3])
        quat.append(matrix_to_quaternion(r))
        lines.append(n)
    if not pos:
        raise _err(path, None, "no pose in the pose file (empty session)")
    return Trajectory(np.full(len(pos), -1, np.int64), np.array(pos, np.float64), np.array(quat), np.array(lines), path)


def read_image_table(path: str | os.PathLike) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Reads ``images.csv``: a header ``file,timestamp``, then one image per line (timestamp in seconds).

    Returns:
        ``(files, utimes int64 (N,) µs, lines int64 (N,))``; files as written (relative to the table's folder).

    Raises:
        FolderFormatError: ``path:line:`` for a wrong header, a line without 2 fields, a bad, unsorted or
            duplicate timestamp, or a file named twice; ``path:`` for a file without rows.
    """
    path = Path(path)
    rows = list(_data_lines(path))
    if not rows:
        raise _err(path, None, "empty image table (expected a header 'file,timestamp' and one line per image)")
    n0, header = rows[0]
    if [h.strip().lower() for h in header.split(",")] != ["file", "timestamp"]:
        raise _err(path, n0, f"header must be 'file,timestamp', got {header!r}")
    files, ts, lines, seen = [], [], [], {}
    for n, line in rows[1:]:
        fields = [f.strip() for f in line.rsplit(",", 1)]
        if len(fields) != 2 or not fields[0]:
            raise _err(path, n, f"expected 'file,timestamp', got {line!r}")
        if fields[0] in seen:
            raise _err(path, n, f"image {fields[0]!r} already listed at line {seen[fields[0]]}")
        seen[fields[0]] = n
        try:
            ts.append(parse_timestamp(fields[1]))
        except ValueError as e:
            raise _err(path, n, str(e)) from None
        files.append(fields[0])
        lines.append(n)
    if not files:
        raise _err(path, None, "no image listed (empty session)")
    _check_increasing(ts, lines, path, "image")
    return files, np.array(ts, np.int64), np.array(lines, np.int64)


def _images_from_names(folder: Path, unit: str) -> tuple[list[str], np.ndarray, np.ndarray]:
    images = folder / IMAGES_DIR
    if not images.is_dir():
        raise _err(folder, None, f"no {IMAGE_TABLE} and no {IMAGES_DIR}/ folder (see docs/own-data.md)")
    entries = []
    for p in sorted(images.iterdir()):
        if p.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        stem = p.stem
        decimal_point = re.fullmatch(r"\d+\.\d+", stem) is not None
        if not (decimal_point or stem.isdigit()):
            raise _err(p, None, f"image name is not a timestamp (and there is no {IMAGE_TABLE} to give one)")
        try:
            t = parse_timestamp(stem, "s" if decimal_point else unit)
        except ValueError as e:
            raise _err(p, None, str(e)) from None
        entries.append((t, f"{IMAGES_DIR}/{p.name}"))
    if not entries:
        raise _err(images, None, "no image (empty session)")
    entries.sort()
    for (t0, f0), (t1, f1) in itertools.pairwise(entries):
        if t0 == t1:
            raise _err(folder / f1, None, f"same timestamp as {f0} (duplicate timestamp)")
    return [f for _, f in entries], np.array([t for t, _ in entries], np.int64), np.full(len(entries), -1)


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    """What ``camera.json`` says.

    Attributes:
        width, height: image size, pixels.
        intrinsics: float64 ``(3, 3)`` from fx, fy, cx, cy (0-based pixel centres, OpenCV convention).
        distortion: OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``; empty: none.
        camera_height_m: camera height above the ground in metres, or None ("unknown": HHA estimates the floor).
        vertical_axis: the vertical world axis of the poses, ``"z"``, ``"y"`` or ``"x"``.
        name_time_unit: unit of integer timestamps in image names (``"us"`` default).
    """

    width: int
    height: int
    intrinsics: np.ndarray
    distortion: tuple[float, ...] = ()
    camera_height_m: float | None = None
    vertical_axis: str = "z"
    name_time_unit: str = "us"

    def to_dict(self) -> dict:
        """The ``camera.json`` content (exact floats: Python's shortest round-trip repr)."""
        k = self.intrinsics
        return {
            "width": self.width,
            "height": self.height,
            "fx": float(k[0, 0]),
            "fy": float(k[1, 1]),
            "cx": float(k[0, 2]),
            "cy": float(k[1, 2]),
            "distortion": [float(v) for v in self.distortion],
            "camera_height_m": "unknown" if self.camera_height_m is None else float(self.camera_height_m),
            "vertical_axis": self.vertical_axis,
            "name_time_unit": self.name_time_unit,
        }


_CAMERA_FIELDS = ("width", "height", "fx", "fy", "cx", "cy", "camera_height_m")
_CAMERA_OPTIONAL = ("distortion", "vertical_axis", "name_time_unit")


def _real(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def read_camera(path: str | os.PathLike) -> CameraSpec:
    """Reads ``camera.json`` (or ``camera.yaml``).

    Fields: ``width``, ``height`` (pixels), ``fx``, ``fy``, ``cx``, ``cy`` (pixels, 0-based centres),
    ``camera_height_m`` (metres above the ground, or ``"unknown"``); optional ``distortion`` (OpenCV
    coefficients, 4, 5 or 8 numbers), ``vertical_axis`` (``"z"``), ``name_time_unit`` (``"us"``).

    Raises:
        FolderFormatError: ``path:`` naming a missing, unknown or invalid field (or ``path:line:`` for bad JSON).
    """
    path = Path(path)
    if not path.is_file():
        raise _err(path, None, "camera file not found")
    text = path.read_text()
    if path.suffix.lower() == ".json":
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise _err(path, e.lineno, f"malformed JSON ({e.msg})") from None
    else:
        import yaml  # PyYAML ships with ml-collections, a placejax dependency

        try:
            d = yaml.safe_load(text)
        except yaml.YAMLError as e:
            mark = getattr(e, "problem_mark", None)
            raise _err(path, None if mark is None else mark.line + 1, f"malformed YAML ({e})") from None
    if not isinstance(d, dict):
        raise _err(path, None, "expected a mapping of camera fields")
    missing = [f for f in _CAMERA_FIELDS if f not in d]
    if missing:
        raise _err(path, None, f"missing camera field(s) {missing} (required: {list(_CAMERA_FIELDS)})")
    unknown = sorted(set(d) - set(_CAMERA_FIELDS) - set(_CAMERA_OPTIONAL))
    if unknown:
        raise _err(
            path, None, f"unknown camera field(s) {unknown} (allowed: {list(_CAMERA_FIELDS + _CAMERA_OPTIONAL)})"
        )
    for f in ("width", "height"):
        if isinstance(d[f], bool) or not isinstance(d[f], int) or d[f] < 1:
            raise _err(path, None, f"{f} must be a positive int (pixels), got {d[f]!r}")
    for f in ("fx", "fy", "cx", "cy"):
        if not _real(d[f]):
            raise _err(path, None, f"{f} must be a finite number (pixels), got {d[f]!r}")
    if not (d["fx"] > 0 and d["fy"] > 0):
        raise _err(path, None, f"fx and fy must be positive, got {d['fx']!r}, {d['fy']!r}")
    h = d["camera_height_m"]
    if h != "unknown" and not (_real(h) and h > 0):
        raise _err(path, None, f"camera_height_m must be a positive number of metres or 'unknown', got {h!r}")
    dist = d.get("distortion") or []
    if not isinstance(dist, list) or len(dist) not in (0, 4, 5, 8) or not all(_real(v) for v in dist):
        raise _err(path, None, f"distortion must be 4, 5 or 8 OpenCV coefficients (k1 k2 p1 p2 k3 ...), got {dist!r}")
    axis = d.get("vertical_axis", "z")
    if axis not in _VERTICAL:
        raise _err(path, None, f"vertical_axis must be one of {list(_VERTICAL)}, got {axis!r}")
    unit = d.get("name_time_unit", "us")
    if unit not in _TIME_UNITS:
        raise _err(path, None, f"name_time_unit must be one of {list(_TIME_UNITS)}, got {unit!r}")
    k = np.array([[d["fx"], 0.0, d["cx"]], [0.0, d["fy"], d["cy"]], [0.0, 0.0, 1.0]], np.float64)
    return CameraSpec(
        width=d["width"],
        height=d["height"],
        intrinsics=k,
        distortion=tuple(float(v) for v in dist),
        camera_height_m=None if h == "unknown" else float(h),
        vertical_axis=axis,
        name_time_unit=unit,
    )


_ODOMETRY_HEADERS = (("timestamp", "x", "y", "yaw"), ("timestamp", "travelled_m"))


def read_odometry(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """Reads ``odometry.csv``: wheel odometry as poses or as an odometer.

    Two forms, told apart by the header: ``timestamp,x,y,yaw`` (seconds, metres, metres, radians: the odometry
    frame's pose) or ``timestamp,travelled_m`` (seconds, metres travelled since any origin: an odometer, which
    must not decrease).

    Returns:
        ``(utimes int64 (M,) µs, values float64 (M, 3) or (M, 1), header)``.

    Raises:
        FolderFormatError: ``path:line:`` for another header, a bad line, a non-finite value, an unsorted or
            duplicate timestamp, a decreasing odometer; ``path:`` for no rows.
    """
    path = Path(path)
    rows = list(_data_lines(path))
    header = tuple(h.strip().lower() for h in rows[0][1].split(",")) if rows else ()
    if header not in _ODOMETRY_HEADERS:
        raise _err(path, rows[0][0] if rows else None, "header must be 'timestamp,x,y,yaw' or 'timestamp,travelled_m'")
    ts, vals, lines = [], [], []
    for n, line in rows[1:]:
        fields = line.split(",")
        if len(fields) != len(header):
            raise _err(path, n, f"expected {len(header)} values {','.join(header)!r}, got {len(fields)}")
        try:
            ts.append(parse_timestamp(fields[0]))
        except ValueError as e:
            raise _err(path, n, str(e)) from None
        v = _floats(path, n, fields[1:], "odometry")
        if not all(math.isfinite(x) for x in v):
            raise _err(path, n, f"odometry {v} is not finite")
        if len(v) == 1 and vals and v[0] < vals[-1][0]:
            raise _err(path, n, f"travelled_m {v[0]!r} is below the previous line's {vals[-1][0]!r} (an odometer)")
        vals.append(v)
        lines.append(n)
    if not ts:
        raise _err(path, None, "no odometry row")
    _check_increasing(ts, lines, path, "odometry")
    return np.array(ts, np.int64), np.array(vals, np.float64), header


def _interp(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """``np.interp`` whose value at a sample's exact time is that sample, bit for bit."""
    out = np.interp(x.astype(np.float64), xp.astype(np.float64), fp)
    idx = np.clip(np.searchsorted(xp, x), 0, len(xp) - 1)
    hit = xp[idx] == x
    out[hit] = fp[idx[hit]]
    return out


# --------------------------------------------------------------------------------------------------- matching


def interpolate_poses(
    frame_utimes: np.ndarray, trajectory: Trajectory, tolerance_us: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Camera poses at frame times: position linear, orientation slerp between the two samples around each frame.

    Args:
        frame_utimes: int64 ``(N,)`` µs.
        trajectory: sorted poses (:func:`read_tum`).
        tolerance_us: largest accepted gap between a frame and its nearest pose sample, µs.

    Returns:
        ``(positions (N, 3), quaternions (N, 4), outside bool (N,), too_far bool (N,))``: frames before the first
        or after the last sample are ``outside``; frames inside whose nearest sample is farther than the
        tolerance are ``too_far`` (their poses are still filled in, but should be dropped). A frame at a sample's
        exact time gets that sample's pose bit for bit.
    """
    t = np.asarray(trajectory.utimes, np.int64)
    f = np.asarray(frame_utimes, np.int64)
    n = len(t)
    idx = np.searchsorted(t, f)  # first sample at or after the frame
    right, left = np.clip(idx, 0, n - 1), np.clip(idx - 1, 0, n - 1)
    span = (t[right] - t[left]).astype(np.float64)
    w = np.clip(np.where(span > 0, (f - t[left]) / np.where(span > 0, span, 1.0), 0.0), 0.0, 1.0)
    p0, p1 = trajectory.positions[left], trajectory.positions[right]
    pos = p0 + w[:, None] * (p1 - p0)
    quat = _slerp(trajectory.quaternions[left], trajectory.quaternions[right], w)
    # Exact sample times keep the sample, untouched by the arithmetic above.
    hit = t[right] == f
    pos[hit] = trajectory.positions[right[hit]]
    quat[hit] = trajectory.quaternions[right[hit]]
    nearest = np.minimum(np.abs(f - t[left]), np.abs(t[right] - f))
    outside = (f < t[0]) | (f > t[-1])
    too_far = ~outside & (nearest > tolerance_us)
    return pos, quat, outside, too_far


# --------------------------------------------------------------------------------------------------- the session


@dataclasses.dataclass(frozen=True)
class FolderReport:
    """Per-session frame accounting: every listed image is kept or counted under one reason.

    Attributes:
        name: the session.
        n_images: images listed (after ``stride``).
        n_kept: frames in the session.
        n_outside_poses: dropped: before the first or after the last pose.
        n_no_pose: dropped: nearest pose farther than the tolerance (a gap in the trajectory).
        n_pose_rows: poses in the trajectory file.
        max_pose_gap_s: the largest time between consecutive poses, seconds (0 for KITTI files).
        n_no_odometry: kept frames outside the odometry table (``odometry`` rows NaN, ``travelled_m`` clamped).
        n_over_max_frames: dropped: matched, but beyond ``max_frames``.
    """

    name: str
    n_images: int
    n_kept: int
    n_outside_poses: int
    n_no_pose: int
    n_pose_rows: int
    max_pose_gap_s: float
    n_no_odometry: int = 0
    n_over_max_frames: int = 0

    @property
    def n_dropped(self) -> int:
        """Images listed but not in the session."""
        return self.n_images - self.n_kept

    def __str__(self) -> str:
        return (
            f"folder session {self.name}: kept {self.n_kept}/{self.n_images} frames, dropped {self.n_outside_poses} "
            f"outside the trajectory and {self.n_no_pose} without a pose within tolerance; {self.n_pose_rows} poses, "
            f"largest gap {self.max_pose_gap_s:.3f} s"
        )


def _decode_image(path: Path) -> np.ndarray:
    """RGB uint8 ``(H, W, 3)`` of an image file (grey images repeated, alpha dropped); errors name the file."""
    if not path.is_file():
        raise _err(path, None, "image file missing")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise _err(path, None, "unreadable or truncated image")
    if img.dtype != np.uint8:
        raise _err(path, None, f"expected an 8-bit image, got {img.dtype}")
    if img.ndim == 2:
        return np.ascontiguousarray(np.repeat(img[:, :, None], 3, axis=2))
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    if img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    raise _err(path, None, f"expected a grey, RGB or RGBA image, got {img.shape[2]} channels")


def _decode_depth(path: Path) -> np.ndarray:
    """float32 metres ``(H, W)`` of a depth file (uint16 PNG millimetres, or float .npy / .tiff metres)."""
    if not path.is_file():
        raise _err(path, None, "depth file missing")
    if path.suffix.lower() == ".npy":
        try:
            d = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise _err(path, None, f"unreadable depth array ({e})") from None
        if d.dtype.kind != "f" or d.ndim != 2:
            raise _err(path, None, f"expected a 2-D float array of metres, got {d.dtype} {d.shape}")
        return d.astype(np.float32)
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None:
        raise _err(path, None, "unreadable depth image")
    if d.ndim != 2:
        raise _err(path, None, f"expected a 1-channel depth image, got shape {d.shape}")
    if d.dtype == np.uint16:
        return d.astype(np.float32) / np.float32(1000.0)  # millimetres, as TUM RGB-D writes them; 0 = missing
    if d.dtype in (np.float32, np.float64):
        return d.astype(np.float32)
    raise _err(path, None, f"expected uint16 millimetres or float metres, got {d.dtype}")


class FolderSession:
    """One session folder (module docstring); satisfies :class:`placejax.data.Session`.

    Attributes:
        name: the session (by default the folder's name).
        folder: the session folder.
        utimes: int64 ``(N,)`` frame times, µs.
        poses: float64 ``(N, 3)`` x, y (m), yaw (rad) on the horizontal world axes.
        positions: float64 ``(N, 3)`` camera centres, m (world frame of the pose file).
        rotations: float64 ``(N, 3, 3)`` camera-to-world rotations.
        intrinsics: float64 ``(3, 3)`` of the images ``image(i)`` returns (undistorted, resized), 0-based.
        image_shape: ``(H, W)`` of those images.
        camera: the parsed ``camera.json``.
        camera_height_m: metres above the ground, or None when unknown.
        files: the image file of every frame.
        depth_files: the depth file of every frame, or None without a ``depth/`` folder.
        odometry: float64 ``(N, 3)`` wheel odometry x, y, yaw at the frame times (NaN outside the table), or None
            (no ``odometry.csv``, or an odometer-only one).
        travelled_m: float64 ``(N,)`` metres travelled since frame 0 by the odometry (``placejax.route`` reads
            it; clamped outside the table), or None without ``odometry.csv``.
        report: kept / dropped counts.
    """

    def __init__(
        self,
        *,
        name: str,
        folder: Path,
        camera: CameraSpec,
        files: tuple[Path, ...],
        utimes: np.ndarray,
        positions: np.ndarray,
        quaternions: np.ndarray,
        depth_files: tuple[Path, ...] | None,
        odometry: np.ndarray | None,
        travelled_m: np.ndarray | None,
        image_size: tuple[int, int] | None,
        report: FolderReport,
    ):
        self.name, self.folder, self.camera, self.files = name, folder, camera, files
        self.utimes = utimes
        self.positions = positions
        self.quaternions = quaternions
        self.rotations = quaternion_to_matrix(quaternions) if len(quaternions) else np.zeros((0, 3, 3))
        self.poses = planar_poses(positions, self.rotations, camera.vertical_axis)
        self.depth_files, self.odometry, self.report = depth_files, odometry, report
        self.travelled_m = travelled_m
        self.camera_height_m = camera.camera_height_m
        raw = (camera.height, camera.width)
        self.raw_shape = raw
        self.image_shape = tuple(int(v) for v in image_size) if image_size is not None else raw
        self.intrinsics = _camera.resize_intrinsics(camera.intrinsics, raw, self.image_shape)
        self._maps = None
        if camera.distortion and any(camera.distortion):
            k = camera.intrinsics
            self._maps = cv2.initUndistortRectifyMap(
                k, np.asarray(camera.distortion), None, k, (camera.width, camera.height), cv2.CV_32FC1
            )

    def __len__(self) -> int:
        return len(self.utimes)

    def __repr__(self) -> str:
        return f"FolderSession({self.name!r}, {len(self)} frames, image_shape={self.image_shape})"

    def _check(self, i: int) -> int:
        n = len(self)
        if not -n <= int(i) < n:
            raise IndexError(f"frame {i} out of range for session {self.name!r} with {n} frames")
        return int(i) % n

    def raw_image(self, i: int) -> np.ndarray:
        """Frame ``i`` as stored, RGB uint8 ``(height, width, 3)`` of ``camera.json``; errors name the file."""
        path = self.files[self._check(i)]
        img = _decode_image(path)
        if img.shape[:2] != self.raw_shape:
            raise _err(
                path,
                None,
                f"image is {img.shape[1]} x {img.shape[0]} (W x H), camera.json and the session's other images "
                f"are {self.raw_shape[1]} x {self.raw_shape[0]} (images of different sizes)",
            )
        return img

    def image(self, i: int) -> np.ndarray:
        """Upright RGB uint8 ``(H, W, 3)`` of frame ``i``: decoded, undistorted (with distortion given), resized."""
        img = self.raw_image(i)
        if self._maps is not None:
            img = cv2.remap(img, self._maps[0], self._maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return np.ascontiguousarray(_camera.resize_image(img, self.image_shape))

    def images(self, indices) -> np.ndarray:
        """RGB uint8 ``(n, H, W, 3)`` of frames ``indices``."""
        h, w = self.image_shape
        idx = np.atleast_1d(np.asarray(indices, np.int64))
        return np.stack([self.image(int(i)) for i in idx]) if len(idx) else np.zeros((0, h, w, 3), np.uint8)

    @property
    def has_depth(self) -> bool:
        """Whether the folder has a depth image for every frame."""
        return self.depth_files is not None

    def depth(self, i: int) -> np.ndarray:
        """Metric depth float32 ``(H, W)`` of frame ``i``, metres (0 or NaN where missing).

        Resized like the image (nearest neighbour, so no depth is invented across edges); not undistorted, so
        with distortion given it is only approximately aligned.
        """
        if self.depth_files is None:
            raise FileNotFoundError(f"{self.folder}: session {self.name!r} has no {DEPTH_DIR}/ folder")
        path = self.depth_files[self._check(i)]
        d = _decode_depth(path)
        if d.shape != self.raw_shape:
            raise _err(
                path,
                None,
                f"depth is {d.shape[1]} x {d.shape[0]} (W x H), the images are "
                f"{self.raw_shape[1]} x {self.raw_shape[0]}",
            )
        if d.shape != self.image_shape:
            d = cv2.resize(d, self.image_shape[::-1], interpolation=cv2.INTER_NEAREST)
        return d

    def depths(self, indices) -> np.ndarray:
        """Depth float32 ``(n, H, W)`` of frames ``indices``, metres."""
        idx = np.atleast_1d(np.asarray(indices, np.int64))
        return np.stack([self.depth(int(i)) for i in idx]) if len(idx) else np.zeros((0, *self.image_shape), np.float32)

    def fingerprint(self) -> dict:
        """What identifies the images this session returns (for cache keys).

        Frame times, poses, camera, the image file names and sizes and the bytes of the first, middle and last
        image are in; the folder's path is not, so a moved folder keeps its caches.
        """
        digest = hashlib.sha256()
        for a in (self.utimes, self.positions, self.quaternions, self.intrinsics):
            digest.update(np.ascontiguousarray(a).tobytes())
        digest.update(json.dumps(self.camera.to_dict(), sort_keys=True).encode())
        for p in self.files:
            digest.update(f"{p.name}:{p.stat().st_size};".encode())
        n = len(self)
        for i in sorted({0, n // 2, n - 1}):
            digest.update(self.files[i].read_bytes())
        return {
            "source": "folder",
            "name": self.name,
            "n": n,
            "image_shape": list(self.image_shape),
            "content_sha256": digest.hexdigest(),
        }


def _depth_files(folder: Path, files: Sequence[Path]) -> tuple[Path, ...] | None:
    d = folder / DEPTH_DIR
    if not d.is_dir():
        return None
    by_stem: dict[str, Path] = {}
    for p in d.iterdir():
        if p.suffix.lower() in _DEPTH_SUFFIXES:
            if p.stem in by_stem:
                raise _err(p, None, f"two depth files for image {p.stem!r}: {by_stem[p.stem].name} and {p.name}")
            by_stem[p.stem] = p
    out = []
    for f in files:
        if f.stem not in by_stem:
            raise _err(d, None, f"no depth file for image {f.name} (expected {f.stem}.png, .npy or .tiff)")
        out.append(by_stem[f.stem])
    return tuple(out)


def _pose_file(folder: Path) -> Path:
    present = [folder / f for f in (TUM_FILE, KITTI_FILE) if (folder / f).is_file()]
    if len(present) != 1:
        found = "both" if present else "neither"
        raise _err(folder, None, f"expected exactly one pose file, {TUM_FILE} or {KITTI_FILE}; found {found}")
    return present[0]


def _camera_file(folder: Path) -> Path:
    for name in (CAMERA_FILE, *_CAMERA_YAML):
        if (folder / name).is_file():
            return folder / name
    raise _err(folder, None, f"no {CAMERA_FILE} (image size, fx fy cx cy, camera_height_m; see docs/own-data.md)")


def load_session(
    folder: str | os.PathLike,
    *,
    name: str | None = None,
    image_size: tuple[int, int] | None = None,
    tolerance_s: float = 0.1,
    stride: int = 1,
    max_frames: int | None = None,
    verify_images: bool = False,
) -> FolderSession:
    """Loads one session folder: reads camera, image list and poses, matches them and checks the files.

    Args:
        folder: the session folder (layout: module docstring, ``docs/own-data.md``).
        name: session name (default: the folder's name).
        image_size: ``(H, W)`` to resize the images to (default: ``camera.json``'s size).
        tolerance_s: largest accepted gap between an image and its nearest pose, seconds (finite, ≥ 0).
        stride: keep every ``stride``-th image of the list (1: every image).
        max_frames: keep at most this many frames (the first ones, after ``stride`` and the pose matching;
            None: all).
        verify_images: decode every image now (size and readability); otherwise only the first kept image is
            decoded and every file's existence is checked.

    Returns:
        The session; ``session.report`` has the kept / dropped counts.

    Raises:
        FolderFormatError: naming the file (and line) of the first defect (module docstring); also when no
            frame is left.
        ValueError: a bad argument.
    """
    folder = Path(folder)
    if not (isinstance(tolerance_s, int | float) and not isinstance(tolerance_s, bool) and 0 <= tolerance_s < math.inf):
        raise ValueError(f"tolerance_s must be a finite number of seconds >= 0, got {tolerance_s!r}")
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise ValueError(f"stride must be a positive int, got {stride!r}")
    if max_frames is not None and (isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 1):
        raise ValueError(f"max_frames must be a positive int or None, got {max_frames!r}")
    if image_size is not None:
        size = tuple(image_size)
        if len(size) != 2 or not all(
            isinstance(v, int | np.integer) and not isinstance(v, bool) and v >= 1 for v in size
        ):
            raise ValueError(f"image_size must be (H, W), two positive ints, got {image_size!r}")
    if not folder.is_dir():
        raise _err(folder, None, "session folder not found")
    cam = read_camera(_camera_file(folder))
    table = folder / IMAGE_TABLE
    if table.is_file():
        names, utimes, lines = read_image_table(table)
    else:
        names, utimes, lines = _images_from_names(folder, cam.name_time_unit)
    pose_path = _pose_file(folder)
    if pose_path.name == KITTI_FILE:
        traj = read_kitti_poses(pose_path)
        if len(traj) != len(names):
            raise _err(
                pose_path, None, f"{len(traj)} poses for {len(names)} images: KITTI files have one pose per image"
            )
        positions, quats = traj.positions, traj.quaternions
        outside = too_far = np.zeros(len(names), bool)
        gap = 0.0
    else:
        traj = read_tum(pose_path)
        positions, quats, outside, too_far = interpolate_poses(utimes, traj, round(tolerance_s * 1e6))
        gap = float(np.diff(traj.utimes).max() / 1e6) if len(traj) > 1 else 0.0
    sel = np.arange(0, len(names), stride)
    names = [names[k] for k in sel]
    utimes, lines, positions, quats = utimes[sel], lines[sel], positions[sel], quats[sel]
    outside, too_far = outside[sel], too_far[sel]
    files = [folder / n for n in names]
    keep = ~outside & ~too_far
    n_matched = int(keep.sum())
    if max_frames is not None:
        keep &= np.cumsum(keep) <= max_frames
    for k in np.flatnonzero(keep):
        if not files[k].is_file():
            where = (table, int(lines[k])) if lines[k] >= 0 else (files[k], None)
            raise _err(*where, f"image file {names[k]} missing")
    report = FolderReport(
        name=name or folder.name,
        n_images=len(files),
        n_kept=int(keep.sum()),
        n_outside_poses=int(outside.sum()),
        n_no_pose=int(too_far.sum()),
        n_pose_rows=len(traj),
        max_pose_gap_s=gap,
        n_over_max_frames=n_matched - int(keep.sum()),
    )
    if report.n_kept == 0:
        raise _err(folder, None, f"no frame left after matching the images to {pose_path.name} ({report})")
    kept_files = [f for f, k in zip(files, keep, strict=True) if k]
    check = kept_files if verify_images else kept_files[:1]
    for f in check:
        shape = _decode_image(f).shape[:2]
        if shape != (cam.height, cam.width):
            raise _err(
                f,
                None,
                f"image is {shape[1]} x {shape[0]} (W x H), {CAMERA_FILE} says {cam.width} x {cam.height} "
                "(images of different sizes?)",
            )
    depth = _depth_files(folder, kept_files)
    odo = travelled = None
    if (folder / ODOMETRY_FILE).is_file():
        o_t, o_v, header = read_odometry(folder / ODOMETRY_FILE)
        ku = utimes[keep]
        out = (ku < o_t[0]) | (ku > o_t[-1])
        if len(header) == 4:
            yaw = np.unwrap(o_v[:, 2])
            odo = np.stack([_interp(ku, o_t, o_v[:, 0]), _interp(ku, o_t, o_v[:, 1]), _interp(ku, o_t, yaw)], -1)
            odo[:, 2] = np.angle(np.exp(1j * odo[:, 2]))
            odo[out] = np.nan
            # The odometer of a pose odometry: its planar path length (as placejax.data.nclt.travelled_at).
            reading = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(o_v[:, :2], axis=0), axis=1))])
        else:
            reading = o_v[:, 0]
        travelled = _interp(ku, o_t, reading)  # clamped outside the table: no motion invented there
        travelled -= travelled[0]
        report = dataclasses.replace(report, n_no_odometry=int(out.sum()))
    return FolderSession(
        name=report.name,
        folder=folder,
        camera=cam,
        files=tuple(kept_files),
        utimes=utimes[keep],
        positions=positions[keep],
        quaternions=quats[keep],
        depth_files=depth,
        odometry=odo,
        travelled_m=travelled,
        image_size=image_size,
        report=report,
    )


def load_sessions(root: str | os.PathLike, names: Sequence[str], **kwargs) -> list[FolderSession]:
    """Loads ``root/<name>`` for every name (keyword arguments as :func:`load_session`)."""
    root = Path(root)
    if not root.is_dir():
        raise _err(root, None, "folder of sessions not found")
    return [load_session(root / n, name=n, **kwargs) for n in names]


# --------------------------------------------------------------------------------------------------- writing


def write_session(
    folder: str | os.PathLike,
    camera: CameraSpec,
    utimes: np.ndarray,
    positions: np.ndarray,
    quaternions: np.ndarray,
    images: Iterable[np.ndarray],
    *,
    depths: Iterable[np.ndarray] | None = None,
    travelled_m: np.ndarray | None = None,
    pose_format: str = "tum",
) -> Path:
    """Writes one session folder in this format (what the exporters and ``docs/own-data.md`` use).

    Images go to ``images/<k:06d>.png`` (lossless) with ``images.csv``; depth (float metres) to
    ``depth/<k:06d>.npy``. Every file is written atomically; timestamps and poses round-trip exactly.

    Args:
        folder: the session folder (created).
        camera: the camera (:class:`CameraSpec`).
        utimes: int64 ``(N,)`` strictly increasing µs.
        positions: float ``(N, 3)`` camera centres, metres.
        quaternions: float ``(N, 4)`` camera-to-world ``(qx, qy, qz, qw)``.
        images: ``N`` RGB uint8 ``(height, width, 3)`` images.
        depths: optional ``N`` float ``(height, width)`` metric depths.
        travelled_m: optional float ``(N,)`` odometer reading at each image (metres), written as ``odometry.csv``.
        pose_format: ``"tum"`` (``poses_tum.txt``) or ``"kitti"`` (``poses_kitti.txt``).

    Returns:
        The folder.
    """
    folder = Path(folder)
    utimes = np.asarray(utimes, np.int64)
    positions, quaternions = np.asarray(positions, np.float64), np.asarray(quaternions, np.float64)
    n = len(utimes)
    if positions.shape != (n, 3) or quaternions.shape != (n, 4):
        raise ValueError(
            f"positions must be ({n}, 3) and quaternions ({n}, 4), got {positions.shape}, {quaternions.shape}"
        )
    if n == 0 or (np.diff(utimes) <= 0).any():
        raise ValueError("utimes must be non-empty and strictly increasing")
    if pose_format not in ("tum", "kitti"):
        raise ValueError(f"pose_format must be 'tum' or 'kitti', got {pose_format!r}")
    (folder / IMAGES_DIR).mkdir(parents=True, exist_ok=True)
    io.write_json(folder / CAMERA_FILE, camera.to_dict())
    rows = ["file,timestamp"]
    count = 0
    for k, img in enumerate(images):
        img = np.asarray(img)
        if img.dtype != np.uint8 or img.shape != (camera.height, camera.width, 3):
            raise ValueError(
                f"image {k} must be uint8 ({camera.height}, {camera.width}, 3), got {img.dtype} {img.shape}"
            )
        ok, buf = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        if not ok:
            raise OSError(f"could not encode image {k} as PNG")
        io.write_bytes(folder / IMAGES_DIR / f"{k:06d}.png", buf.tobytes())
        rows.append(f"{IMAGES_DIR}/{k:06d}.png,{format_timestamp(utimes[k])}")
        count += 1
    if count != n:
        raise ValueError(f"got {count} images for {n} poses")
    io.write_text(folder / IMAGE_TABLE, "\n".join(rows) + "\n")
    if depths is not None:
        (folder / DEPTH_DIR).mkdir(exist_ok=True)
        for k, d in enumerate(depths):
            with io.atomic_write(folder / DEPTH_DIR / f"{k:06d}.npy") as f:
                np.save(f, np.asarray(d, np.float32), allow_pickle=False)
    if travelled_m is not None:
        travelled_m = np.asarray(travelled_m, np.float64)
        if travelled_m.shape != (n,):
            raise ValueError(f"travelled_m must have shape ({n},), got {travelled_m.shape}")
        readings = (f"{format_timestamp(t)},{float(v)!r}" for t, v in zip(utimes, travelled_m, strict=True))
        rows = ["timestamp,travelled_m", *readings]
        io.write_text(folder / ODOMETRY_FILE, "\n".join(rows) + "\n")
    write_poses(folder, utimes, positions, quaternions, pose_format)
    return folder


def write_poses(
    folder: str | os.PathLike, utimes: np.ndarray, positions: np.ndarray, quaternions: np.ndarray, pose_format: str
) -> Path:
    """Writes ``poses_tum.txt`` or ``poses_kitti.txt`` (removing the other), floats in round-trip precision:
    ``utimes`` int ``(N,)`` microseconds, ``positions`` ``(N, 3)`` metres, ``quaternions`` ``(N, 4)``.

    Returns:
        The file written.
    """
    folder = Path(folder)
    if pose_format == "tum":
        lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world, metres)"]
        for t, p, q in zip(utimes, positions, quaternions, strict=True):
            lines.append(" ".join([format_timestamp(t), *(repr(float(v)) for v in (*p, *q))]))
        path, other = folder / TUM_FILE, folder / KITTI_FILE
    else:
        rot = quaternion_to_matrix(quaternions)
        lines = [
            " ".join(repr(float(v)) for v in np.concatenate([r, p[:, None]], 1).ravel())
            for r, p in zip(rot, positions, strict=True)
        ]
        path, other = folder / KITTI_FILE, folder / TUM_FILE
    io.write_text(path, "\n".join(lines) + "\n")
    other.unlink(missing_ok=True)
    return path
