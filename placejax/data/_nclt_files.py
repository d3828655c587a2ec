"""The readers of NCLT's own files: ground-truth and odometry CSVs, the camera intrinsics and the undistortion map
(``placejax.data.nclt`` re-exports them; formats in ``docs/nclt.md``). Every defect is an :class:`NcltFormatError`
naming the file."""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

log = logging.getLogger("placejax.data.nclt")


class NcltFormatError(ValueError):
    """A missing, truncated or malformed NCLT file; the message starts with the offending path."""


class GroundTruth(NamedTuple):
    """A parsed ground-truth CSV (see :func:`read_ground_truth`)."""

    utimes: np.ndarray  # int64 (M,), sorted, unique
    xyzrpy: np.ndarray  # float64 (M, 6)
    n_rows: int
    n_nan_rows: int
    n_conflicting_rows: int


def _read_pose_csv(path: Path, what: str) -> np.ndarray:
    """The float64 ``(rows, 7)`` table of an NCLT pose CSV (utime, x, y, z, roll, pitch, yaw), rows as written."""
    if not path.is_file():
        raise NcltFormatError(f"{path}: {what} CSV not found")
    if path.stat().st_size == 0:
        raise NcltFormatError(f"{path}: {what} CSV is empty")
    try:
        table = np.loadtxt(path, delimiter=",", dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise NcltFormatError(f"{path}: malformed {what} CSV ({e})") from None
    if table.shape[1] != 7:
        raise NcltFormatError(f"{path}: expected 7 columns (utime, x, y, z, roll, pitch, yaw), got {table.shape[1]}")
    return table


def read_ground_truth(path: str | os.PathLike) -> GroundTruth:
    """Reads ``groundtruth_<date>.csv``: headerless ``utime, x, y, z, roll, pitch, yaw`` (µs, m, rad, NED).

    Returns:
        :class:`GroundTruth`: rows with any NaN dropped, sorted by utime; exact duplicate rows collapsed to one;
        rows sharing a utime but not the pose (conflicting duplicates) all dropped and counted, with a warning.

    Raises:
        NcltFormatError: missing, empty or malformed file (wrong column count, non-numbers, truncated line,
            utimes that are not non-negative integers below 2**53).
    """
    path = Path(path)
    table = _read_pose_csv(path, "ground-truth")
    n_rows = len(table)
    finite = np.isfinite(table).all(axis=1)
    table = table[finite]
    if len(table) == 0:
        raise NcltFormatError(f"{path}: no ground-truth row without NaN")
    # utimes (~1.3e15 µs) are below 2**53, so float64 parsing is exact; beyond that it is not.
    t = table[:, 0]
    bad = (t < 0) | (t >= 2.0**53) | (t != np.rint(t))
    if bad.any():
        raise NcltFormatError(
            f"{path}: utime {t[bad][0]:.6g} is not a non-negative integer below 2**53 µs ({int(bad.sum())} such rows)"
        )
    utimes = t.astype(np.int64)
    order = np.lexsort(tuple(table[:, ::-1].T))  # by utime, then the pose: duplicates end up adjacent
    utimes, table = utimes[order], table[order]
    distinct = np.ones(len(table), bool)
    distinct[1:] = (table[1:] != table[:-1]).any(axis=1)
    utimes, table = utimes[distinct], table[distinct]  # exact duplicates collapsed
    values, counts = np.unique(utimes, return_counts=True)
    conflicting = np.isin(utimes, values[counts > 1])
    n_conflicting = int(conflicting.sum())
    if n_conflicting:
        log.warning(
            "%s: %d rows share a utime with a different pose (first at utime %d); all of them dropped",
            path,
            n_conflicting,
            utimes[conflicting][0],
        )
        utimes, table = utimes[~conflicting], table[~conflicting]
        if len(table) == 0:
            raise NcltFormatError(f"{path}: every ground-truth utime has conflicting poses")
    return GroundTruth(utimes, table[:, 1:], n_rows, n_rows - int(finite.sum()), n_conflicting)


class Odometry(NamedTuple):
    """A parsed wheel-odometry CSV (see :func:`read_odometry`)."""

    utimes: np.ndarray  # int64 (M,), sorted, unique
    xyzrpy: np.ndarray  # float64 (M, 6): x, y, z (m), roll, pitch, yaw (rad) of the odometry frame


def read_odometry(path: str | os.PathLike) -> Odometry:
    """Reads ``sensor_data/<date>/odometry_mu_100hz.csv`` (or ``odometry_mu.csv``): wheel odometry.

    Headerless ``utime, x, y, z, roll, pitch, yaw`` (µs, m, rad): the robot's dead-reckoned pose in the frame of
    its start, which drifts; only distances along it are meaningful (:func:`travelled_at`). The route filter
    reads nothing else of it (``placejax.route``).

    Returns:
        :class:`Odometry`: NaN rows dropped, sorted by utime, rows with a repeated utime reduced to the first.

    Raises:
        NcltFormatError: missing, empty or malformed file (wrong column count, non-numbers, utimes that are not
            non-negative integers below 2**53, no row without NaN).
    """
    path = Path(path)
    table = _read_pose_csv(path, "odometry")
    table = table[np.isfinite(table).all(axis=1)]
    if len(table) == 0:
        raise NcltFormatError(f"{path}: no odometry row without NaN")
    t = table[:, 0]
    bad = (t < 0) | (t >= 2.0**53) | (t != np.rint(t))
    if bad.any():
        raise NcltFormatError(f"{path}: utime {t[bad][0]:.6g} is not a non-negative integer below 2**53 µs")
    utimes, first = np.unique(t.astype(np.int64), return_index=True)  # sorted; first row of each utime
    return Odometry(utimes, table[first, 1:])


def travelled_at(odometry: Odometry, frame_utimes) -> np.ndarray:
    """Odometer reading at each frame time: metres travelled in the plane since the odometry's first row.

    The cumulative length of the odometry's ``(x, y)`` polyline, linearly interpolated at the frame times (frames
    before the first or after the last row read the first or last value: no motion is invented there, and a
    warning counts them). ``placejax.route.moved_from_travelled`` turns it into per-frame distances.

    Args:
        odometry: from :func:`read_odometry`.
        frame_utimes: int ``(N,)`` frame times (µs), e.g. ``NcltSession.utimes``.

    Returns:
        float64 ``(N,)`` metres.
    """
    f = np.asarray(frame_utimes, np.int64)
    if f.ndim != 1:
        raise ValueError(f"frame_utimes must have shape (N,), got {f.shape}")
    t = odometry.utimes
    step = np.linalg.norm(np.diff(odometry.xyzrpy[:, :2], axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(step)])
    outside = int(((f < t[0]) | (f > t[-1])).sum())
    if outside:
        log.warning("odometry covers utimes %d…%d; %d frames outside it get no motion", t[0], t[-1], outside)
    # Relative to the first row: float64 keeps µs exactly up to 2**53, and the offsets are small.
    return np.interp((f - t[0]).astype(np.float64), (t - t[0]).astype(np.float64), cum)


def _check_intrinsics(k: np.ndarray, source: str) -> np.ndarray:
    """A usable pinhole matrix: finite, fx = K[0, 0] > 0, fy = K[1, 1] > 0, last row (0, 0, 1)."""
    if k.shape != (3, 3):
        raise NcltFormatError(f"{source}: intrinsics must be a 3 × 3 matrix, got shape {k.shape}")
    if not np.isfinite(k).all():
        raise NcltFormatError(f"{source}: intrinsics must be finite, got {k.tolist()}")
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise NcltFormatError(
            f"{source}: focal lengths fx = K[0, 0] = {k[0, 0]} and fy = K[1, 1] = {k[1, 1]} must be positive"
        )
    if not np.allclose(k[2], [0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
        raise NcltFormatError(f"{source}: last row of the intrinsics must be (0, 0, 1), got {k[2].tolist()}")
    return k


def read_intrinsics(path: str | os.PathLike) -> np.ndarray:
    """Reads a 3 × 3 ``K_cam<c>.csv`` (comma- or space-separated) into float64 ``(3, 3)``.

    Raises:
        NcltFormatError: missing file, not 9 finite numbers, focal lengths ≤ 0, or a last row other than (0, 0, 1).
    """
    path = Path(path)
    if not path.is_file():
        raise NcltFormatError(f"{path}: intrinsics file not found (or pass intrinsics=...)")
    try:
        values = np.array(path.read_text().replace(",", " ").split(), dtype=np.float64)
    except ValueError as e:
        raise NcltFormatError(f"{path}: malformed intrinsics ({e})") from None
    if values.shape != (9,) or not np.isfinite(values).all():
        raise NcltFormatError(f"{path}: expected 9 finite numbers (a 3 × 3 matrix), got {values.size}")
    return _check_intrinsics(values.reshape(3, 3), str(path))


_U2D_HEADER = re.compile(r"width\D*(\d+)\D+height\D*(\d+)", re.IGNORECASE)
# Largest image side a U2D header may declare (the Ladybug3's is 1616 × 1232): bounds the allocation before any
# pixel line is read.
_U2D_MAX_SIDE = 16384
_U2D_MIN_LINE_BYTES = 8  # "0 0 0 0\n": the shortest possible pixel line


def read_u2d_map(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Reads an undistortion map ``U2D_Cam<c>_<W>X<H>.txt`` (any size up to 16384 per side).

    Format: a header ``width/cols = W , height/rows = H``, then one line ``i j v u`` per undistorted pixel:
    undistorted pixel (row i, col j) takes the distorted source pixel (row v, col u).

    Returns:
        ``(mapu, mapv)`` float32 ``(H, W)`` for ``cv2.remap(raw, mapu, mapv, cv2.INTER_LINEAR)`` on the
        unrotated image.

    Raises:
        NcltFormatError: naming the file and the offending pixel: a header outside 1…16384 per side or larger
            than the file could hold, a malformed line, pixel indices that are not integers inside the header
            size, a pixel listed twice or not at all (a cut file would otherwise leave black pixels: the official
            script samples pixel (0, 0) for them), or a source coordinate that is not finite or lies more than one
            image size outside the image.
    """
    path = Path(path)
    if not path.is_file():
        raise NcltFormatError(f"{path}: undistortion map not found")
    with path.open() as f:
        header = f.readline()
        m = _U2D_HEADER.search(header)
        if m is None:
            raise NcltFormatError(f"{path}: bad header {header.strip()!r}, expected 'width/cols = W , height/rows = H'")
        width, height = int(m.group(1)), int(m.group(2))
        if not (1 <= width <= _U2D_MAX_SIDE and 1 <= height <= _U2D_MAX_SIDE):
            raise NcltFormatError(f"{path}: header size {width} × {height} (W × H) outside 1…{_U2D_MAX_SIDE} per side")
        size = path.stat().st_size
        if width * height * _U2D_MIN_LINE_BYTES > size:
            raise NcltFormatError(
                f"{path}: header says {width} × {height} = {width * height} pixel lines, but the file has only "
                f"{size} bytes (truncated, or a wrong header)"
            )
        try:
            rows = np.loadtxt(f, dtype=np.float64, ndmin=2)
        except ValueError as e:
            raise NcltFormatError(f"{path}: malformed undistortion map ({e})") from None
    if rows.size == 0 or rows.shape[1] != 4:
        raise NcltFormatError(f"{path}: expected lines 'i j v u', got {rows.shape[1] if rows.size else 0} columns")
    ij = rows[:, :2]
    bad = ~np.isfinite(ij).all(axis=1) | (ij != np.rint(ij)).any(axis=1)
    bad |= (ij[:, 0] < 0) | (ij[:, 0] >= height) | (ij[:, 1] < 0) | (ij[:, 1] >= width)
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        raise NcltFormatError(
            f"{path}: pixel line {r + 1} ({rows[r, 0]:g} {rows[r, 1]:g}) is not an integer pixel inside the "
            f"{width} × {height} header size ({int(bad.sum())} such lines)"
        )
    i, j = ij[:, 0].astype(np.int64), ij[:, 1].astype(np.int64)
    vu = rows[:, 2:]
    far = ~np.isfinite(vu).all(axis=1)
    with np.errstate(invalid="ignore"):
        far |= (np.abs(vu[:, 0] - (height - 1) / 2) > 1.5 * height) | (np.abs(vu[:, 1] - (width - 1) / 2) > 1.5 * width)
    if far.any():
        r = int(np.flatnonzero(far)[0])
        raise NcltFormatError(
            f"{path}: pixel (row {i[r]}, col {j[r]}) has source (v, u) = ({vu[r, 0]:g}, {vu[r, 1]:g}), not finite "
            f"or more than one image size outside the {width} × {height} image ({int(far.sum())} such pixels)"
        )
    count = np.bincount(i * width + j, minlength=width * height)
    if (count > 1).any():
        flat = int(np.flatnonzero(count > 1)[0])
        raise NcltFormatError(
            f"{path}: pixel (row {flat // width}, col {flat % width}) listed {count[flat]} times "
            f"({int((count > 1).sum())} pixels listed more than once)"
        )
    if (count == 0).any():
        flat = int(np.flatnonzero(count == 0)[0])
        raise NcltFormatError(
            f"{path}: {int((count == 0).sum())} of {width * height} pixels not listed, first (row {flat // width}, "
            f"col {flat % width}) (a truncated file?)"
        )
    mapu = np.empty((height, width), dtype=np.float32)
    mapv = np.empty((height, width), dtype=np.float32)
    mapu[i, j] = vu[:, 1]
    mapv[i, j] = vu[:, 0]
    return mapu, mapv
