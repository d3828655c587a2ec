"""The text files of a session folder: timestamps, TUM and KITTI pose files, ``images.csv``, ``odometry.csv``.

Every reader streams its file within the budgets of :class:`FolderLimits` (bytes, lines, line length) and checks
each value against the physical bounds of ``_limits`` as it reads it; a defect is a :class:`FolderFormatError`
``path:line: message``.
"""

from __future__ import annotations

import array
import decimal
import itertools
import math
import os
import re
from collections.abc import Iterator, Sequence
from pathlib import Path, PurePosixPath

import numpy as np

from placejax.data.folder._errors import _err, _quote
from placejax.data.folder._limits import (
    MAX_LINE_BYTES,
    MAX_NAME_BYTES,
    MAX_ODOMETER_M,
    MAX_TABLE_PATH_CHARS,
    MAX_TIMESTAMP_US,
    MAX_YAW_RAD,
    FolderLimits,
)
from placejax.data.poses import Trajectory, matrix_to_quaternion

__all__ = [
    "IMAGES_DIR",
    "IMAGE_SUFFIXES",
    "IMAGE_TABLE",
    "KITTI_FILE",
    "ODOMETRY_FILE",
    "QUATERNION_NORM_TOLERANCE",
    "TIME_UNITS",
    "TUM_FILE",
    "format_timestamp",
    "images_from_names",
    "parse_timestamp",
    "read_image_table",
    "read_kitti_poses",
    "read_odometry",
    "read_tum",
]

IMAGES_DIR = "images"
"""The folder of a session's images."""
IMAGE_TABLE = "images.csv"
"""The optional table ``file,timestamp`` of a session's images."""
TUM_FILE = "poses_tum.txt"
"""The TUM RGB-D trajectory of a session (one of the two pose files)."""
KITTI_FILE = "poses_kitti.txt"
"""The KITTI pose file of a session, one pose per image (one of the two pose files)."""
ODOMETRY_FILE = "odometry.csv"
"""The optional wheel odometry of a session."""
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")
"""Suffixes taken as images in ``images/`` when there is no ``images.csv`` (formats whose header is checked)."""
TIME_UNITS = {"s": 0, "ms": 3, "us": 6, "ns": 9}  # decimal places below the second
QUATERNION_NORM_TOLERANCE = 1e-3
"""A quaternion whose norm is farther than this from 1 is an error, not rounding (TUM files carry 4–7 digits)."""
MIN_NAME_STEP_US = 1000
"""Image names read as times less than this far apart (median, µs: a camera above 1,000 frames/s) are frame numbers
(``000000.png``, ``000001.png``), refused rather than all matched to the trajectory's first pose."""
# Plain ASCII decimals (Decimal() alone would also take "1_000", "NaN" and non-ASCII digits).
_DECIMAL = re.compile(r"\+?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
# Exact for any decimal a line can hold; the exponent is bounded before the context is used.
_EXACT = decimal.Context(prec=MAX_LINE_BYTES + 64, Emax=10**6, Emin=-(10**6))
_DOCS = "docs/own-data.md"


# --------------------------------------------------------------------------------------------------- timestamps


def parse_timestamp(text: str, unit: str = "s") -> int:
    """An exact timestamp in integer microseconds from its decimal text (no float rounding on the way).

    Args:
        text: a decimal number, e.g. ``"1327251905.811462"``.
        unit: unit of ``text``: ``"s"``, ``"ms"``, ``"us"`` or ``"ns"``.

    Returns:
        int µs, rounded half to even below the microsecond.

    Raises:
        ValueError: not a non-negative decimal number, or later than ``MAX_TIMESTAMP_US`` (2**53 µs, the year
            2255).

    Example:
        >>> parse_timestamp("1327251905.811462"), parse_timestamp("1500", "ns")
        (1327251905811462, 2)
    """
    if unit not in TIME_UNITS:
        raise ValueError(f"time unit must be one of {tuple(TIME_UNITS)}, got {unit!r}")
    s = text.strip()
    if not _DECIMAL.fullmatch(s):
        raise ValueError(f"timestamp {_quote(s)} is not a non-negative decimal number")
    d = decimal.Decimal(s)
    if d.is_zero() or d.adjusted() < -30:  # below 1e-30 s: 0 µs after rounding, whatever the unit
        return 0
    us = None
    if d.adjusted() <= 30:
        us = int(d.scaleb(6 - TIME_UNITS[unit], _EXACT).to_integral_value(decimal.ROUND_HALF_EVEN, _EXACT))
    if us is None or us > MAX_TIMESTAMP_US:
        raise ValueError(
            f"timestamp {_quote(s, 40)} {unit} is later than 2**53 µs (the year 2255, MAX_TIMESTAMP_US): "
            "nanoseconds or milliseconds read as a larger unit?"
        )
    return us


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


# --------------------------------------------------------------------------------------------------- text


def _data_lines(path: Path, limits: FolderLimits) -> Iterator[tuple[int, str]]:
    """``(line number, text)`` of every non-blank, non-comment (``#``) line, within the text budgets."""
    try:
        size = path.stat().st_size
    except OSError as e:
        raise _err(path, None, f"cannot be read ({e.strerror or e})") from None
    if size > limits.max_text_bytes:
        raise _err(path, None, f"{size} bytes, more than {limits.max_text_bytes} (FolderLimits.max_text_bytes)")
    try:
        f = path.open("rb")
    except OSError as e:
        raise _err(path, None, f"cannot be read ({e.strerror or e})") from None
    with f:
        n, read = 0, 0
        while raw := f.readline(MAX_LINE_BYTES + 1):
            n += 1
            read += len(raw)
            if n > limits.max_text_lines:
                raise _err(path, n, f"more than {limits.max_text_lines} lines (FolderLimits.max_text_lines)")
            if read > limits.max_text_bytes:  # the file grew while being read
                raise _err(path, n, f"more than {limits.max_text_bytes} bytes (FolderLimits.max_text_bytes)")
            if len(raw) > MAX_LINE_BYTES:
                raise _err(path, n, f"a line longer than {MAX_LINE_BYTES} bytes (MAX_LINE_BYTES)")
            try:
                s = raw.decode("utf-8-sig" if n == 1 else "utf-8").strip()
            except UnicodeDecodeError:
                raise _err(path, n, "not UTF-8 text") from None
            if s and not s.startswith("#"):
                yield n, s


def _floats(path: Path, n: int, fields: list[str], what: str) -> list[float]:
    try:
        return [float(f) for f in fields]
    except ValueError:
        raise _err(path, n, f"{what}: non-number in {_quote(' '.join(fields))}") from None


def _timestamp(path: Path, n: int, text: str) -> int:
    try:
        return parse_timestamp(text)
    except ValueError as e:
        raise _err(path, n, str(e)) from None


def _check_position(path: Path, n: int, v: Sequence[float], limits: FolderLimits, what: str) -> None:
    if not all(math.isfinite(x) for x in v):
        raise _err(path, n, f"{what} = {_quote(list(v))} is not finite")
    bound = limits.max_coordinate_m
    if any(abs(x) > bound for x in v):
        raise _err(
            path,
            n,
            f"{what} = {_quote(list(v))} m is farther than {bound:g} m from the origin on an axis "
            "(FolderLimits.max_coordinate_m): not a position a robot drives to (positions are in metres: "
            "millimetres or centimetres need dividing by 1000 or 100)",
        )


def _check_speed(
    path: Path, utimes: np.ndarray, xyz: np.ndarray, lines: np.ndarray, max_speed_mps: float | None, what: str
) -> None:
    """Raises at the first of consecutive samples that move faster than ``max_speed_mps`` (None: no check).

    Args:
        path: the file the samples come from (named in the error).
        utimes: int64 ``(M,)`` strictly increasing µs.
        xyz: float ``(M, D)`` positions (or odometer readings, ``D = 1``), metres.
        lines: int ``(M,)`` the line of each sample.
        max_speed_mps: the bound, m/s.
        what: what moves ("pose", "odometry").
    """
    if max_speed_mps is None or len(utimes) < 2:
        return
    dt = np.diff(np.asarray(utimes, np.int64)) / 1e6
    dist = np.linalg.norm(np.diff(np.asarray(xyz, np.float64), axis=0), axis=1)
    fast = np.flatnonzero(dist > max_speed_mps * dt)
    if fast.size:
        k = int(fast[0])
        raise _err(
            path,
            int(lines[k + 1]),
            f"{what} moves {dist[k]:.4g} m in {dt[k]:.6g} s since line {int(lines[k])} ({dist[k] / dt[k]:.4g} m/s, "
            f"faster than {max_speed_mps:g} m/s, FolderLimits.max_speed_mps): a wrong timestamp, or positions in "
            "another unit than metres (millimetres: divide by 1000), or times in another unit than seconds? "
            "(for a faster vehicle: FolderLimits(max_speed_mps=None), check --max-speed-mps 0)",
        )


# --------------------------------------------------------------------------------------------------- poses


def _unit_quaternion(path: Path, n: int, q: list[float]) -> list[float]:
    if not all(math.isfinite(v) for v in q):
        raise _err(path, n, f"quaternion (qx qy qz qw) = {_quote(q)} is not finite")
    norm = math.sqrt(sum(v * v for v in q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise _err(
            path, n, f"quaternion (qx qy qz qw) = {_quote(q)} has norm {norm:.6g}, not 1 (±{QUATERNION_NORM_TOLERANCE})"
        )
    return [v / norm for v in q]


def _missing(path: Path, what: str) -> None:
    if not path.is_file():
        raise _err(path, None, f"{what} not found")


def read_tum(path: str | os.PathLike, limits: FolderLimits | None = None) -> Trajectory:
    """Reads a TUM RGB-D trajectory: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments allowed.

    Args:
        path: the file. Timestamps in seconds (any number of decimals, read exactly to the µs); position in
            metres; orientation a unit quaternion, camera-to-world.
        limits: the budgets and bounds (default :class:`FolderLimits`).

    Returns:
        :class:`Trajectory` (quaternions normalised).

    Raises:
        FolderFormatError: ``path:line:`` for a line without 8 numbers, a NaN or infinite value, a coordinate
            beyond ``max_coordinate_m``, a quaternion whose norm is not 1 (±1e-3), an unsorted or duplicate
            timestamp, motion faster than ``max_speed_mps``, a file over a budget; ``path:`` for a missing or empty
            file.
    """
    path, limits = Path(path), limits or FolderLimits()
    _missing(path, "trajectory file")
    ts, pos, quat, lines = array.array("q"), array.array("d"), array.array("d"), array.array("q")
    for n, line in _data_lines(path, limits):
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise _err(path, n, f"expected 8 values 'timestamp tx ty tz qx qy qz qw', got {len(fields)}")
        t = _timestamp(path, n, fields[0])
        v = _floats(path, n, fields[1:], "pose")
        _check_position(path, n, v[:3], limits, "position (tx ty tz)")
        ts.append(t)
        pos.extend(v[:3])
        quat.extend(_unit_quaternion(path, n, v[3:]))
        lines.append(n)
    if not ts:
        raise _err(path, None, "no pose in the trajectory file (empty session)")
    _check_increasing(ts, lines, path, "pose")
    traj = Trajectory(
        np.frombuffer(ts, np.int64).copy(),
        np.frombuffer(pos, np.float64).reshape(-1, 3).copy(),
        np.frombuffer(quat, np.float64).reshape(-1, 4).copy(),
        np.frombuffer(lines, np.int64).copy(),
        path,
    )
    _check_speed(path, traj.utimes, traj.positions, traj.lines, limits.max_speed_mps, "the camera")
    return traj


def read_kitti_poses(path: str | os.PathLike, limits: FolderLimits | None = None) -> Trajectory:
    """Reads KITTI odometry poses: 12 numbers per line, the row-major 3 × 4 camera-to-world ``[R | t]``.

    The file has no times: the speed between poses is checked where they are matched to the images
    (``load_session``).

    Returns:
        :class:`Trajectory` with ``utimes`` all ``-1`` (line ``k`` is the pose of the ``k``-th image).

    Raises:
        FolderFormatError: ``path:line:`` for a line without 12 finite numbers, a coordinate beyond
            ``max_coordinate_m``, a rotation that is not orthonormal with determinant 1 (±1e-3), a file over a
            budget; ``path:`` for a missing or empty file.
    """
    path, limits = Path(path), limits or FolderLimits()
    _missing(path, "pose file")
    pos, rot, lines = array.array("d"), array.array("d"), array.array("q")
    for n, line in _data_lines(path, limits):
        fields = line.split()
        if len(fields) != 12:
            raise _err(path, n, f"expected 12 numbers (a row-major 3 x 4 [R | t]), got {len(fields)}")
        m = np.array(_floats(path, n, fields, "pose")).reshape(3, 4)
        if not np.isfinite(m).all():
            raise _err(path, n, "pose is not finite")
        _check_position(path, n, m[:, 3].tolist(), limits, "position (t)")
        r = m[:, :3]
        # Entries beyond ±1 are no rotation's, and would overflow the products below.
        error = np.abs(r @ r.T - np.eye(3)).max() if np.abs(r).max() <= 2.0 else np.inf
        if error > QUATERNION_NORM_TOLERANCE or abs(np.linalg.det(r) - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise _err(path, n, f"rotation is not orthonormal with determinant 1 (|R Rᵀ − I| = {error:.3g})")
        pos.extend(m[:, 3])
        rot.extend(r.ravel())
        lines.append(n)
    if not pos:
        raise _err(path, None, "no pose in the pose file (empty session)")
    quat = matrix_to_quaternion(np.frombuffer(rot, np.float64).reshape(-1, 3, 3))
    positions = np.frombuffer(pos, np.float64).reshape(-1, 3).copy()
    return Trajectory(
        np.full(len(positions), -1, np.int64), positions, quat, np.frombuffer(lines, np.int64).copy(), path
    )


# --------------------------------------------------------------------------------------------------- images


def _table_path(path: Path, n: int, name: str, allow_outside: bool) -> None:
    """Refuses a file name of ``images.csv`` that the file system cannot hold or that leaves the session folder."""
    if len(name) > MAX_TABLE_PATH_CHARS:
        raise _err(path, n, f"file name {_quote(name)} is longer than {MAX_TABLE_PATH_CHARS} characters")
    if "\0" in name:
        raise _err(path, n, f"file name {_quote(name)} holds a NUL character")
    p = PurePosixPath(name)
    long = [c for c in p.parts if len(c.encode()) > MAX_NAME_BYTES]
    if long:
        raise _err(
            path, n, f"file name {_quote(name)}: a part of {len(long[0].encode())} bytes, more than {MAX_NAME_BYTES}"
        )
    if not allow_outside and (p.is_absolute() or ".." in p.parts):
        raise _err(
            path,
            n,
            f"file name {_quote(name)} points outside the session folder: images are named relative to it, without "
            "'..' (allow_outside=True, check --allow-outside: read images elsewhere)",
        )


def read_image_table(
    path: str | os.PathLike, limits: FolderLimits | None = None, *, allow_outside: bool = False
) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Reads ``images.csv``: a header ``file,timestamp``, then one image per line (timestamp in seconds).

    Args:
        path: the table.
        limits: the budgets (default :class:`FolderLimits`).
        allow_outside: accept absolute file names and names with ``..`` (files outside the session folder).

    Returns:
        ``(files, utimes int64 (N,) µs, lines int64 (N,))``; files as written (relative to the table's folder).

    Raises:
        FolderFormatError: ``path:line:`` for a wrong header, a line without 2 fields, a bad, unsorted or
            duplicate timestamp, a file named twice, a file name that leaves the folder or that no file system
            holds, more than ``max_images`` rows or a file over a budget; ``path:`` for a file without rows.
    """
    path, limits = Path(path), limits or FolderLimits()
    rows = _data_lines(path, limits)
    first = next(rows, None)
    if first is None:
        raise _err(path, None, "empty image table (expected a header 'file,timestamp' and one line per image)")
    n0, header = first
    if [h.strip().lower() for h in header.split(",")] != ["file", "timestamp"]:
        raise _err(path, n0, f"header must be 'file,timestamp', got {_quote(header)}")
    files, ts, lines, seen = [], [], [], {}
    for n, line in rows:
        fields = [f.strip() for f in line.rsplit(",", 1)]
        if len(fields) != 2 or not fields[0]:
            raise _err(path, n, f"expected 'file,timestamp', got {_quote(line)}")
        if len(files) == limits.max_images:
            raise _err(path, n, f"more than {limits.max_images} images (FolderLimits.max_images)")
        _table_path(path, n, fields[0], allow_outside)
        if fields[0] in seen:
            raise _err(path, n, f"image {_quote(fields[0])} already listed at line {seen[fields[0]]}")
        seen[fields[0]] = n
        ts.append(_timestamp(path, n, fields[1]))
        files.append(fields[0])
        lines.append(n)
    if not files:
        raise _err(path, None, "no image listed (empty session)")
    _check_increasing(ts, lines, path, "image")
    return files, np.array(ts, np.int64), np.array(lines, np.int64)


def images_from_names(
    folder: Path, unit: str, limits: FolderLimits | None = None
) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The images of ``folder/images/`` with the timestamps their names give (no ``images.csv``).

    Returns:
        ``(files relative to folder, utimes int64 (N,) µs sorted, lines (N,) all -1)``.

    Raises:
        FolderFormatError: no ``images/``, no image, a name that is not a timestamp, two images of one time,
            more than ``max_images`` images.
    """
    limits = limits or FolderLimits()
    images = folder / IMAGES_DIR
    if not images.is_dir():
        raise _err(folder, None, f"no {IMAGE_TABLE} and no {IMAGES_DIR}/ folder (see {_DOCS})")
    names = []
    try:
        with os.scandir(images) as it:
            for e in it:
                if os.path.splitext(e.name)[1].lower() in IMAGE_SUFFIXES:
                    if len(names) == limits.max_images:
                        raise _err(images, None, f"more than {limits.max_images} images (FolderLimits.max_images)")
                    names.append(e.name)
    except OSError as e:
        raise _err(images, None, f"cannot be listed ({e.strerror or e})") from None
    entries = []
    for name in sorted(names):
        stem = os.path.splitext(name)[0]
        decimal_point = re.fullmatch(r"[0-9]+\.[0-9]+", stem) is not None
        if not (decimal_point or re.fullmatch(r"[0-9]+", stem)):
            raise _err(
                images / name,
                None,
                f"image name is not a timestamp: without {IMAGE_TABLE} each image's name is its time (seconds, "
                f"'1327251905.811462.png', or an integer in camera.json's name_time_unit); list 'file,timestamp' "
                f"per image in {IMAGE_TABLE} ({_DOCS})",
            )
        try:
            t = parse_timestamp(stem, "s" if decimal_point else unit)
        except ValueError as ex:
            raise _err(images / name, None, str(ex)) from None
        entries.append((t, f"{IMAGES_DIR}/{name}"))
    if not entries:
        raise _err(images, None, "no image (empty session)")
    entries.sort()
    for (t0, f0), (t1, f1) in itertools.pairwise(entries):
        if t0 == t1:
            raise _err(folder / f1, None, f"same timestamp as {f0} (duplicate timestamp)")
    step_us = float(np.median(np.diff([t for t, _ in entries]))) if len(entries) > 1 else math.inf
    if step_us < MIN_NAME_STEP_US:
        first, second = (f.rsplit("/", 1)[-1] for _, f in entries[:2])
        raise _err(
            images,
            None,
            f"image names look like frame numbers, not times: read as timestamps ({first}, {second}, ... in "
            f"name_time_unit {unit!r}) they are {step_us:g} µs apart, a camera at {1e6 / step_us:,.0f} frames/s; "
            f"list 'file,timestamp' per image in {IMAGE_TABLE}, with the times of the pose file's clock ({_DOCS})",
        )
    return [f for _, f in entries], np.array([t for t, _ in entries], np.int64), np.full(len(entries), -1)


# --------------------------------------------------------------------------------------------------- odometry

_ODOMETRY_HEADERS = (("timestamp", "x", "y", "yaw"), ("timestamp", "travelled_m"))


def read_odometry(
    path: str | os.PathLike, limits: FolderLimits | None = None
) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """Reads ``odometry.csv``: wheel odometry as poses or as an odometer.

    Two forms, told apart by the header: ``timestamp,x,y,yaw`` (seconds, metres, metres, radians: the odometry
    frame's pose) or ``timestamp,travelled_m`` (seconds, metres travelled since any origin: an odometer, which
    must not decrease).

    Returns:
        ``(utimes int64 (M,) µs, values float64 (M, 3) or (M, 1), header)``.

    Raises:
        FolderFormatError: ``path:line:`` for another header, a bad line, a non-finite value or one beyond its
            bound (``max_coordinate_m``, ``MAX_YAW_RAD``, ``MAX_ODOMETER_M``), an unsorted or duplicate timestamp,
            a decreasing odometer, motion faster than ``max_speed_mps``, a file over a budget; ``path:`` for no
            rows.
    """
    path, limits = Path(path), limits or FolderLimits()
    rows = _data_lines(path, limits)
    first = next(rows, None)
    header = tuple(h.strip().lower() for h in first[1].split(",")) if first else ()
    if header not in _ODOMETRY_HEADERS:
        raise _err(path, first[0] if first else None, "header must be 'timestamp,x,y,yaw' or 'timestamp,travelled_m'")
    ts, vals, lines = [], [], []
    for n, line in rows:
        fields = line.split(",")
        if len(fields) != len(header):
            raise _err(path, n, f"expected {len(header)} values {','.join(header)!r}, got {len(fields)}")
        ts.append(_timestamp(path, n, fields[0]))
        v = _floats(path, n, fields[1:], "odometry")
        if len(v) == 3:
            _check_position(path, n, v[:2], limits, "odometry (x y)")
            if not (math.isfinite(v[2]) and abs(v[2]) <= MAX_YAW_RAD):
                raise _err(
                    path, n, f"odometry yaw {_quote(v[2])} rad is not finite within ±{MAX_YAW_RAD:g} (MAX_YAW_RAD)"
                )
        else:
            if not (math.isfinite(v[0]) and abs(v[0]) <= MAX_ODOMETER_M):
                raise _err(
                    path, n, f"travelled_m {_quote(v[0])} is not finite within ±{MAX_ODOMETER_M:g} m (MAX_ODOMETER_M)"
                )
            if vals and v[0] < vals[-1][0]:
                raise _err(path, n, f"travelled_m {v[0]!r} is below the previous line's {vals[-1][0]!r} (an odometer)")
        vals.append(v)
        lines.append(n)
    if not ts:
        raise _err(path, None, "no odometry row")
    _check_increasing(ts, lines, path, "odometry")
    utimes, values = np.array(ts, np.int64), np.array(vals, np.float64)
    _check_speed(path, utimes, values[:, :2], np.array(lines), limits.max_speed_mps, "the odometry")
    return utimes, values, header
