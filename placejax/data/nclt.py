"""NCLT sessions: Ladybug3 images matched to SLAM ground-truth poses (format in ``docs/nclt.md``).

Typical use::

    from placejax.data import nclt
    session = nclt.load_session("/data/nclt", "2012-01-22", camera=5, image_size=(224, 224))
    print(session.report)                  # kept / dropped frame counts
    img = session.image(0)                 # upright RGB uint8 (224, 224, 3)

Every component root is configurable because users rename and move the extracted archives:

* images: ``<images_root>/<date>/lb3/Cam<c>/<utime>.tiff`` (default ``images_root = root/images``),
* ground truth: ``<ground_truth_root>/groundtruth_<date>.csv`` (default ``root/ground_truth``),
* calibration: ``K_cam<c>.csv`` and ``U2D_Cam<c>_<W>X<H>.txt`` in ``calib_root`` or one folder below it
  (default ``root/ladybug3_calib``).

Bad input never fails silently nor deep inside training: a missing folder or CSV, a malformed CSV line or an
unreadable image raises :class:`NcltFormatError` naming the file; with ``skip_bad_frames=True`` bad images are
dropped and counted in :attr:`NcltSession.report` instead.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import logging
import math
import os
import re
from pathlib import Path

import cv2
import numpy as np

from placejax import progress as _progress
from placejax.data import camera as _camera
from placejax.data._nclt_files import (
    GroundTruth,
    NcltFormatError,
    Odometry,
    _check_intrinsics,
    read_ground_truth,
    read_intrinsics,
    read_odometry,
    read_u2d_map,
    travelled_at,
)

log = logging.getLogger(__name__)

__all__ = [
    "CAM5_INTRINSICS",
    "GroundTruth",
    "NcltFormatError",
    "NcltPaths",
    "NcltReport",
    "NcltSession",
    "Odometry",
    "find_paths",
    "load_session",
    "match_nearest",
    "read_ground_truth",
    "read_intrinsics",
    "read_odometry",
    "read_u2d_map",
    "travelled_at",
]

# K_cam5.csv of ladybug3_calib/cam_params.zip (docs/nclt.md): intrinsics of the undistorted, *unrotated*
# 1616 × 1232 Cam5 image. Pass as ``intrinsics=`` when the calibration archive is not at hand.
CAM5_INTRINSICS = np.array(
    [[399.433184, 0.0, 826.361952], [0.0, 399.433184, 621.668624], [0.0, 0.0, 1.0]], dtype=np.float64
)
"""float64 ``(3, 3)`` pinhole matrix of the undistorted, unrotated 1616 × 1232 NCLT Cam5 image (pixels)."""

_UTIME_RE = re.compile(r"^\d+$")
_IMAGE_SUFFIXES = (".tiff", ".tif")


@dataclasses.dataclass(frozen=True)
class NcltPaths:
    """Where one session's files are."""

    images_dir: Path
    ground_truth_csv: Path
    calib_dir: Path


@dataclasses.dataclass(frozen=True)
class NcltReport:
    """Per-session frame accounting: every image file is either kept or counted under one reason.

    Attributes:
        n_images: image files found.
        n_kept: frames in the session.
        n_outside_ground_truth: dropped, timestamp before the first or after the last ground-truth row.
        n_no_pose: dropped, nearest ground-truth row farther than the tolerance (a gap in the ground truth).
        n_bad_images: dropped (only with ``skip_bad_frames``) because the file was empty or unreadable.
        n_ground_truth_rows: rows in the ground-truth CSV.
        n_ground_truth_nan_rows: of those, rows dropped for NaN values.
        n_ground_truth_conflicting_rows: of those, rows dropped because another row has the same utime but a
            different pose (no pose at that time can be trusted; frames match the neighbouring rows instead).
            Exact duplicate rows are collapsed to one and not counted.
        bad_images: the skipped files.
    """

    date: str
    camera: int
    n_images: int
    n_kept: int
    n_outside_ground_truth: int
    n_no_pose: int
    n_bad_images: int
    n_ground_truth_rows: int
    n_ground_truth_nan_rows: int
    n_ground_truth_conflicting_rows: int = 0
    bad_images: tuple[str, ...] = ()

    @property
    def n_dropped(self) -> int:
        return self.n_images - self.n_kept

    def __str__(self) -> str:
        return (
            f"NCLT {self.date} Cam{self.camera}: kept {self.n_kept}/{self.n_images} frames, dropped "
            f"{self.n_outside_ground_truth} outside ground truth, {self.n_no_pose} without a pose within "
            f"tolerance, {self.n_bad_images} bad images; ground truth {self.n_ground_truth_rows} rows "
            f"({self.n_ground_truth_nan_rows} NaN rows, {self.n_ground_truth_conflicting_rows} rows with conflicting "
            "duplicate utimes dropped)"
        )


def find_paths(
    root: str | os.PathLike | None,
    date: str,
    camera: int = 5,
    *,
    images_root: str | os.PathLike | None = None,
    ground_truth_root: str | os.PathLike | None = None,
    calib_root: str | os.PathLike | None = None,
) -> NcltPaths:
    """Resolves a session's folders from the dataset root and per-component overrides (no file access)."""
    if root is None and None in (images_root, ground_truth_root, calib_root):
        raise ValueError("NCLT: give `root`, or all of images_root, ground_truth_root and calib_root")
    base = Path(root) if root is not None else None
    images = Path(images_root) if images_root is not None else base / "images"
    gt = Path(ground_truth_root) if ground_truth_root is not None else base / "ground_truth"
    calib = Path(calib_root) if calib_root is not None else base / "ladybug3_calib"
    return NcltPaths(
        images_dir=images / date / "lb3" / f"Cam{camera}",
        ground_truth_csv=gt / f"groundtruth_{date}.csv",
        calib_dir=calib,
    )


def match_nearest(
    frame_utimes: np.ndarray, gt_utimes: np.ndarray, tolerance_us: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest ground-truth row of every frame.

    Args:
        frame_utimes: int64 ``(N,)`` frame times, µs.
        gt_utimes: int64 ``(M,)`` sorted ground-truth times, µs.
        tolerance_us: largest accepted ``|frame − gt|``, µs.

    Returns:
        ``(index int64 (N,), outside bool (N,), too_far bool (N,))``: the nearest row; frames before the first
        or after the last row (``outside``); frames inside the span but farther than the tolerance
        (``too_far``). A frame is usable iff neither flag is set.
    """
    frame_utimes = np.asarray(frame_utimes, dtype=np.int64)
    gt_utimes = np.asarray(gt_utimes, dtype=np.int64)
    right = np.clip(np.searchsorted(gt_utimes, frame_utimes), 1, len(gt_utimes) - 1)
    left = right - 1
    if len(gt_utimes) == 1:
        left = right = np.zeros_like(frame_utimes)
    dl = np.abs(frame_utimes - gt_utimes[left])
    dr = np.abs(gt_utimes[right] - frame_utimes)
    index = np.where(dr < dl, right, left)
    outside = (frame_utimes < gt_utimes[0]) | (frame_utimes > gt_utimes[-1])
    too_far = ~outside & (np.minimum(dl, dr) > tolerance_us)
    return index, outside, too_far


def _find_one(folder: Path, pattern: str, what: str) -> Path:
    hits = sorted(folder.glob(pattern)) + sorted(folder.glob(f"*/{pattern}"))
    if not hits:
        raise NcltFormatError(f"{folder}: no {what} ({pattern}) here or one folder below")
    if len(hits) > 1:
        raise NcltFormatError(f"{folder}: several {what} files match {pattern}: {[str(h) for h in hits]}")
    return hits[0]


def _decode(path: Path) -> np.ndarray:
    """Raw BGR uint8 ``(H, W, 3)`` as stored (sideways); errors name the file."""
    if not path.is_file():
        raise NcltFormatError(f"{path}: image file missing")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise NcltFormatError(f"{path}: unreadable or truncated image")
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] not in (3, 4):
        raise NcltFormatError(f"{path}: expected an 8-bit 3-channel image, got {img.dtype} {img.shape}")
    return img[:, :, :3]


class NcltSession:
    """One NCLT camera's session; satisfies :class:`placejax.data.Session`.

    Attributes:
        name: the date, e.g. ``"2012-01-22"``.
        utimes: int64 ``(N,)`` frame times, µs.
        poses: float64 ``(N, 3)``: x (north), y (east) in metres, yaw in radians, from the nearest
            ground-truth row (NED frame shared by all sessions).
        intrinsics: float64 ``(3, 3)`` of the images ``image(i)`` returns (rotated, resized), 0-based.
        image_shape: ``(H, W)`` of those images; ``(1616, 1232)`` for full-size upright NCLT.
        raw_shape: ``(H, W)`` of the stored sideways images.
        files: the image file of every frame.
        report: kept / dropped counts.
    """

    def __init__(
        self,
        *,
        date: str,
        camera: int,
        files: tuple[Path, ...],
        utimes: np.ndarray,
        poses: np.ndarray,
        raw_shape: tuple[int, int],
        raw_intrinsics: np.ndarray,
        image_size: tuple[int, int] | None,
        u2d: tuple[np.ndarray, np.ndarray] | None,
        report: NcltReport,
        paths: NcltPaths,
    ):
        self.name = date
        self.date = date
        self.camera = camera
        self.files = files
        self.utimes = utimes
        self.poses = poses
        self.raw_shape = raw_shape
        self.report = report
        self.paths = paths
        self.undistort = u2d is not None
        self._u2d = u2d
        upright = (raw_shape[1], raw_shape[0])
        k = _camera.rotate_intrinsics_cw(raw_intrinsics, raw_shape[0])
        self.image_shape = tuple(int(s) for s in image_size) if image_size is not None else upright
        self.intrinsics = _camera.resize_intrinsics(k, upright, self.image_shape)
        self._raw_intrinsics = np.asarray(raw_intrinsics, dtype=np.float64)

    def __len__(self) -> int:
        return len(self.utimes)

    def __repr__(self) -> str:
        return f"NcltSession({self.name!r}, Cam{self.camera}, {len(self)} frames, image_shape={self.image_shape})"

    def raw_image(self, i: int) -> np.ndarray:
        """Frame ``i`` as stored: sideways BGR uint8 ``raw_shape + (3,)``."""
        path = self.files[i]
        img = _decode(path)
        if img.shape[:2] != self.raw_shape:
            raise NcltFormatError(f"{path}: image is {img.shape[:2]}, the session's images are {self.raw_shape}")
        return img

    def image(self, i: int) -> np.ndarray:
        """Upright RGB uint8 ``(H, W, 3)`` of frame ``i``: decoded, undistorted (optional), rotated, resized."""
        img = self.raw_image(i)
        if self._u2d is not None:
            # The U2D maps are defined on the stored (unrotated) image, so remap before rotating.
            img = cv2.remap(img, self._u2d[0], self._u2d[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        img = cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        return np.ascontiguousarray(_camera.resize_image(img, self.image_shape))

    def fingerprint(self) -> dict:
        """What identifies the images this session returns (for cache keys).

        Paths are left out on purpose so a moved dataset keeps its caches; frame times, poses, intrinsics and
        every processing setting are in.
        """
        digest = hashlib.sha256()
        for a in (self.utimes, self.poses, self._raw_intrinsics):
            digest.update(np.ascontiguousarray(a).tobytes())
        if self._u2d is not None:
            digest.update(self._u2d[0].tobytes())
            digest.update(self._u2d[1].tobytes())
        return {
            "source": "nclt",
            "date": self.date,
            "camera": self.camera,
            "n": len(self),
            "raw_shape": list(self.raw_shape),
            "image_shape": list(self.image_shape),
            "undistort": self.undistort,
            "content_sha256": digest.hexdigest(),
        }


def load_session(
    root: str | os.PathLike | None,
    date: str,
    camera: int = 5,
    *,
    images_root: str | os.PathLike | None = None,
    ground_truth_root: str | os.PathLike | None = None,
    calib_root: str | os.PathLike | None = None,
    intrinsics: np.ndarray | None = None,
    undistort: bool = False,
    image_size: tuple[int, int] | None = None,
    tolerance_s: float = 0.1,
    skip_bad_frames: bool = False,
    verify_images: bool = False,
    progress: bool = True,
) -> NcltSession:
    """Loads one NCLT session: lists the images, reads and matches the ground truth, checks the files.

    Args:
        root: dataset root holding ``images/``, ``ground_truth/`` and ``ladybug3_calib/`` (may be ``None`` if
            all three roots below are given).
        date: session date, e.g. ``"2012-01-22"``.
        camera: Ladybug3 camera 0–5; Cam5 faces forward.
        images_root, ground_truth_root, calib_root: override each component's folder.
        intrinsics: float ``(3, 3)`` K of the stored (unrotated) image; default: ``K_cam<c>.csv`` under
            ``calib_root``. :data:`CAM5_INTRINSICS` holds the published Cam5 values.
        undistort: remap with ``U2D_Cam<c>_<W>X<H>.txt`` (the paper does not say whether it undistorted).
            Without it the images keep the lens distortion and K is only approximate.
        image_size: ``(H, W)`` to resize the upright images to; default: the upright size (W_raw, H_raw).
        tolerance_s: largest accepted gap between a frame and its nearest ground-truth row, seconds (finite,
            ≥ 0).
        skip_bad_frames: drop (and count in ``report``) empty or unreadable images instead of raising.
        verify_images: decode every image once now (slow on full NCLT: ~26k TIFFs) so that a corrupt file
            cannot surface later; otherwise only emptiness is checked here and a corrupt image raises
            :class:`NcltFormatError` naming the file when it is read (e.g. while building the cache).
        progress: show a progress bar while verifying.

    Returns:
        The session; ``session.report`` has the kept / dropped counts (also logged at INFO).

    Raises:
        NcltFormatError: a missing folder, CSV or calibration file, a malformed CSV or undistortion map, a bad
            image (unless ``skip_bad_frames``), two images with the same utime (``.tiff`` next to ``.TIF``), a
            utime out of range, or no frame left.
        ValueError: a bad argument (camera outside 0–5, ``tolerance_s`` negative or not finite, ``image_size``
            not two positive ints, ``intrinsics`` not finite with positive focal lengths).
    """
    if isinstance(camera, bool) or not isinstance(camera, int | np.integer) or not 0 <= camera <= 5:
        raise ValueError(f"camera must be a Ladybug3 camera number 0-5, got {camera!r}")
    if (
        isinstance(tolerance_s, bool | np.bool_)
        or not isinstance(tolerance_s, int | float | np.integer | np.floating)
        or not 0 <= tolerance_s < math.inf
    ):
        raise ValueError(f"tolerance_s must be a finite number of seconds ≥ 0, got {tolerance_s!r}")
    if image_size is not None:
        size = tuple(image_size)
        if len(size) != 2 or not all(
            isinstance(v, int | np.integer) and not isinstance(v, bool) and v >= 1 for v in size
        ):
            raise ValueError(f"image_size must be (H, W), two positive ints, got {image_size!r}")
    paths = find_paths(
        root,
        date,
        camera,
        images_root=images_root,
        ground_truth_root=ground_truth_root,
        calib_root=calib_root,
    )
    if not paths.images_dir.is_dir():
        raise NcltFormatError(
            f"{paths.images_dir}: image folder not found (expected <images_root>/{date}/lb3/Cam{camera})"
        )

    entries = []
    for entry in os.scandir(paths.images_dir):
        stem, suffix = os.path.splitext(entry.name)
        if suffix.lower() not in _IMAGE_SUFFIXES:
            continue
        if not _UTIME_RE.match(stem):
            raise NcltFormatError(f"{entry.path}: image name is not <utime>.tiff")
        if int(stem) >= 2**53:  # int64 and the float64 ground-truth utimes
            raise NcltFormatError(f"{entry.path}: utime {stem} in the image name is out of range (≥ 2**53 µs)")
        entries.append((int(stem), entry))
    if not entries:
        raise NcltFormatError(f"{paths.images_dir}: no <utime>.tiff images")
    entries.sort(key=lambda e: (e[0], e[1].name))
    for (u0, e0), (u1, e1) in itertools.pairwise(entries):
        if u0 == u1:  # e.g. 123.tiff next to 123.TIF, or 0123.tiff: one frame per timestamp
            raise NcltFormatError(
                f"{paths.images_dir}: two images for utime {u0}: {e0.name} and {e1.name} (remove one)"
            )
    utimes = np.array([u for u, _ in entries], dtype=np.int64)
    files = [Path(e.path) for _, e in entries]

    truth = read_ground_truth(paths.ground_truth_csv)
    gt_utimes, gt = truth.utimes, truth.xyzrpy
    index, outside, too_far = match_nearest(utimes, gt_utimes, round(tolerance_s * 1e6))
    keep = ~outside & ~too_far

    bad: list[str] = []

    def reject(k: int, why: str) -> None:
        if not skip_bad_frames:
            raise NcltFormatError(f"{files[k]}: {why} (pass skip_bad_frames=True to drop bad frames)")
        bad.append(str(files[k]))
        keep[k] = False

    for k in np.flatnonzero(keep):
        if entries[k][1].stat().st_size == 0:
            reject(k, "empty image file")

    if intrinsics is None:
        raw_k = read_intrinsics(_find_one(paths.calib_dir, f"K_cam{camera}.csv", "intrinsics"))
    else:
        try:
            raw_k = np.asarray(intrinsics, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise ValueError(f"intrinsics must be a (3, 3) float matrix ({e})") from None
        try:
            _check_intrinsics(raw_k, "intrinsics argument")
        except NcltFormatError as e:
            raise ValueError(str(e)) from None

    # The stored size comes from the first decodable kept image; every other image must match it.
    raw_shape = None
    if verify_images:
        candidates = _progress.bar(np.flatnonzero(keep), desc=f"verify NCLT {date}", unit="img", disable=not progress)
    else:
        candidates = np.flatnonzero(keep)
    for k in candidates:
        try:
            shape = _decode(files[k]).shape[:2]
        except NcltFormatError as e:
            reject(k, str(e).removeprefix(f"{files[k]}: "))
            continue
        if raw_shape is None:
            raw_shape = shape
        elif shape != raw_shape:
            reject(k, f"image is {shape}, expected {raw_shape} like the session's other images")
        if not verify_images:
            break

    u2d = None
    if undistort:
        u2d_path = _find_one(paths.calib_dir, f"U2D_Cam{camera}_*X*.txt", "undistortion map")
        u2d = read_u2d_map(u2d_path)
        if raw_shape is not None and u2d[0].shape != raw_shape:
            raise NcltFormatError(
                f"{u2d_path}: map is {u2d[0].shape[1]} × {u2d[0].shape[0]} (W × H) but the images in "
                f"{paths.images_dir} are {raw_shape[1]} × {raw_shape[0]}"
            )

    n_kept = int(keep.sum())
    report = NcltReport(
        date=date,
        camera=camera,
        n_images=len(files),
        n_kept=n_kept,
        n_outside_ground_truth=int(outside.sum()),
        n_no_pose=int(too_far.sum()),
        n_bad_images=len(bad),
        n_ground_truth_rows=truth.n_rows,
        n_ground_truth_nan_rows=truth.n_nan_rows,
        n_ground_truth_conflicting_rows=truth.n_conflicting_rows,
        bad_images=tuple(bad),
    )
    log.info("%s", report)
    if n_kept == 0:
        raise NcltFormatError(
            f"{paths.images_dir}: no frame left after matching to {paths.ground_truth_csv} ({report})"
        )

    rows = gt[index[keep]]
    poses = np.column_stack([rows[:, 0], rows[:, 1], rows[:, 5]])  # x, y, yaw
    return NcltSession(
        date=date,
        camera=camera,
        files=tuple(f for f, k in zip(files, keep, strict=True) if k),
        utimes=utimes[keep],
        poses=poses,
        raw_shape=tuple(int(s) for s in raw_shape),
        raw_intrinsics=raw_k,
        image_size=image_size,
        u2d=u2d,
        report=report,
        paths=paths,
    )


if __name__ == "__main__":  # a program: it may use the modules built on this one
    from placejax import cli
    from placejax.data.export import nclt_command

    raise SystemExit(cli.command(nclt_command)())
