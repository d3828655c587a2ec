"""A session folder as a :class:`placejax.data.Session`: :func:`load_session` matches images and poses, checks
the files and counts what it drops; :class:`FolderSession` decodes frames on demand."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from placejax.data import camera as _camera
from placejax.data.folder._camera_file import CAMERA_FILE, CAMERA_FILES, CameraSpec, read_camera
from placejax.data.folder._errors import MissingSessionError, _err, _quote
from placejax.data.folder._formats import (
    IMAGE_TABLE,
    KITTI_FILE,
    ODOMETRY_FILE,
    TUM_FILE,
    _check_speed,
    images_from_names,
    read_image_table,
    read_kitti_poses,
    read_odometry,
    read_tum,
)
from placejax.data.folder._frames import DEPTH_DIR, _decode_depth, _decode_image, _depth_files, _is_file, present
from placejax.data.folder._limits import FolderLimits
from placejax.data.poses import interp_exact, interpolate_poses, planar_poses, quaternion_to_matrix

__all__ = ["FolderReport", "FolderSession", "load_session", "load_sessions", "require_sessions", "session_folders"]

_DOCS = "docs/own-data.md"


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


class FolderSession:
    """One session folder (``placejax.data.folder``); satisfies :class:`placejax.data.Session`.

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
        limits: the budgets every image and depth file is read within.
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
        limits: FolderLimits | None = None,
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
        self.limits = limits or FolderLimits()
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
        return _decode_image(self.files[self._check(i)], self.raw_shape, self.limits)

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
        d = _decode_depth(self.depth_files[self._check(i)], self.raw_shape, self.limits)
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
            with self.files[i].open("rb") as f:
                while chunk := f.read(1 << 20):  # streamed: no image file is held whole for its hash
                    digest.update(chunk)
        return {
            "source": "folder",
            "name": self.name,
            "n": n,
            "image_shape": list(self.image_shape),
            "content_sha256": digest.hexdigest(),
        }


def _pose_file(folder: Path) -> Path:
    found = [folder / f for f in (TUM_FILE, KITTI_FILE) if present(folder / f)]
    if len(found) != 1:
        which = "both" if found else "neither"
        raise _err(folder, None, f"expected exactly one pose file, {TUM_FILE} or {KITTI_FILE}; found {which}")
    return found[0]


def _camera_file(folder: Path) -> Path:
    for name in CAMERA_FILES:
        if present(folder / name):
            return folder / name
    raise _err(folder, None, f"no {CAMERA_FILE} (image size, fx fy cx cy, camera_height_m; see {_DOCS})")


def _seconds(us: int) -> str:
    return f"{us / 1e6:.6f}".rstrip("0").rstrip(".")


def _nothing_kept(folder, report, pose_path, names, utimes, traj, from_names: bool, unit: str) -> Exception:
    """The error for a session whose images all miss the trajectory, saying why and what to do."""
    images = f"the images span {_seconds(utimes.min())}–{_seconds(utimes.max())} s"
    poses = f"the poses {_seconds(traj.utimes[0])}–{_seconds(traj.utimes[-1])} s"
    if report.n_outside_poses and from_names:
        why = (
            f"image names are read as timestamps in seconds or in name_time_unit {unit!r} "
            f"({names[0].rsplit('/', 1)[-1]} is {_seconds(int(utimes[0]))} s), {images}, {poses}: name each image by "
            f"its time or list 'file,timestamp' per image in {IMAGE_TABLE} ({_DOCS}, 'The format')"
        )
    elif report.n_outside_poses:
        why = f"{images}, {poses}: are the times of {IMAGE_TABLE} and {pose_path.name} on the same clock?"
    else:
        why = (
            "every image is farther than tolerance_s from its nearest pose "
            f"(largest pose gap {report.max_pose_gap_s:.3f} s)"
        )
    return _err(folder, None, f"no frame left after matching the images to {pose_path.name} ({report}): {why}")


def _check_args(tolerance_s, stride, max_frames, image_size) -> None:
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


def load_session(
    folder: str | os.PathLike,
    *,
    name: str | None = None,
    image_size: tuple[int, int] | None = None,
    tolerance_s: float = 0.1,
    stride: int = 1,
    max_frames: int | None = None,
    verify_images: bool = False,
    limits: FolderLimits | None = None,
    allow_outside: bool = False,
) -> FolderSession:
    """Loads one session folder: reads camera, image list and poses, matches them and checks the files.

    Args:
        folder: the session folder (layout: ``placejax.data.folder``, ``docs/own-data.md``).
        name: session name (default: the folder's name).
        image_size: ``(H, W)`` to resize the images to (default: ``camera.json``'s size).
        tolerance_s: largest accepted gap between an image and its nearest pose, seconds (finite, ≥ 0).
        stride: keep every ``stride``-th image of the list (1: every image).
        max_frames: keep at most this many frames (the first ones, after ``stride`` and the pose matching;
            None: all).
        verify_images: decode every kept image and depth file now (each header checked first); otherwise only
            the first kept image is decoded and every image file's existence is checked.
        limits: the budgets and physical bounds (default :class:`FolderLimits`: 50 m/s, 100 km, ...).
        allow_outside: let ``images.csv`` name files outside the folder (absolute paths, ``..``).

    Returns:
        The session; ``session.report`` has the kept / dropped counts.

    Raises:
        FolderFormatError: naming the file (and line) of the first defect; also when no frame is left, saying
            why (image names read as timestamps, another clock, pose gaps).
        ValueError: a bad argument.
    """
    folder, limits = Path(folder), limits or FolderLimits()
    _check_args(tolerance_s, stride, max_frames, image_size)
    try:
        found = folder.is_dir()
    except OSError as e:  # a name the file system refuses
        raise _err(_quote(str(folder)), None, f"cannot be read ({e.strerror or e})") from None
    if not found:
        raise _err(folder, None, "session folder not found", MissingSessionError)
    cam = read_camera(_camera_file(folder), limits)
    table = folder / IMAGE_TABLE
    from_names = not present(table)
    if from_names:
        names, utimes, lines = images_from_names(folder, cam.name_time_unit, limits)
    else:
        names, utimes, lines = read_image_table(table, limits, allow_outside=allow_outside)
    pose_path = _pose_file(folder)
    if pose_path.name == KITTI_FILE:
        traj = read_kitti_poses(pose_path, limits)
        if len(traj) != len(names):
            msg = f"{len(traj)} poses for {len(names)} images: KITTI files have one pose per image"
            raise _err(pose_path, None, msg)
        speed = limits.max_speed_mps
        _check_speed(pose_path, utimes, traj.positions, traj.lines, speed, "the camera (at the image times)")
        positions, quats = traj.positions, traj.quaternions
        outside = too_far = np.zeros(len(names), bool)
        gap = 0.0
    else:
        traj = read_tum(pose_path, limits)
        positions, quats, outside, too_far = interpolate_poses(utimes, traj, round(tolerance_s * 1e6))
        gap = float(np.diff(traj.utimes).max() / 1e6) if len(traj) > 1 else 0.0
    sel = np.arange(0, len(names), stride)
    all_names, all_utimes = names, utimes
    names = [names[k] for k in sel]
    utimes, lines, positions, quats = utimes[sel], lines[sel], positions[sel], quats[sel]
    outside, too_far = outside[sel], too_far[sel]
    files = [folder / n for n in names]
    keep = ~outside & ~too_far
    n_matched = int(keep.sum())
    if max_frames is not None:
        keep &= np.cumsum(keep) <= max_frames
    for k in np.flatnonzero(keep):
        if not _is_file(files[k]):
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
        raise _nothing_kept(folder, report, pose_path, all_names, all_utimes, traj, from_names, cam.name_time_unit)
    kept_files = [f for f, k in zip(files, keep, strict=True) if k]
    raw_shape = (cam.height, cam.width)
    for f in kept_files if verify_images else kept_files[:1]:
        _decode_image(f, raw_shape, limits)
    depth = _depth_files(folder, kept_files, limits)
    if verify_images and depth is not None:
        for f in depth:
            _decode_depth(f, raw_shape, limits)
    odo = travelled = None
    if present(folder / ODOMETRY_FILE):
        odo, travelled, n_out = _odometry(folder / ODOMETRY_FILE, utimes[keep], limits)
        report = dataclasses.replace(report, n_no_odometry=n_out)
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
        limits=limits,
    )


def _odometry(path: Path, ku: np.ndarray, limits: FolderLimits) -> tuple[np.ndarray | None, np.ndarray, int]:
    """``(odometry (N, 3) or None, travelled_m (N,), frames outside the table)`` at frame times ``ku``."""
    o_t, o_v, header = read_odometry(path, limits)
    out = (ku < o_t[0]) | (ku > o_t[-1])
    odo = None
    if len(header) == 4:
        yaw = np.unwrap(o_v[:, 2])
        odo = np.stack([interp_exact(ku, o_t, col) for col in (o_v[:, 0], o_v[:, 1], yaw)], -1)
        odo[:, 2] = np.angle(np.exp(1j * odo[:, 2]))
        odo[out] = np.nan
        # The odometer of a pose odometry: its planar path length (as placejax.data.nclt.travelled_at).
        reading = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(o_v[:, :2], axis=0), axis=1))])
    else:
        reading = o_v[:, 0]
    travelled = interp_exact(ku, o_t, reading)  # clamped outside the table: no motion invented there
    travelled -= travelled[0]
    return odo, travelled, int(out.sum())


def session_folders(root: str | os.PathLike) -> list[Path]:
    """The session folders directly inside ``root`` (sub-folders holding a camera file), sorted by name."""
    root = Path(root)
    try:
        found = root.is_dir()
        inside = sorted(p for p in root.iterdir() if p.is_dir()) if found else []
        sessions = [p for p in inside if any((p / c).is_file() for c in CAMERA_FILES)]
    except OSError as e:  # no permission, a name the file system refuses
        raise _err(_quote(str(root)), None, f"cannot be read ({e.strerror or e})") from None
    if not found:
        raise _err(root, None, "folder of sessions not found", MissingSessionError)
    return sessions


def require_sessions(root: str | os.PathLike, names: Sequence[str]) -> list[Path]:
    """``root/<name>`` for every name, or one error naming every missing folder and the session folders there are.

    What an experiment calls before loading ``data.sessions`` from ``data.root``.

    Raises:
        MissingSessionError: (a ``FolderFormatError`` and a ``FileNotFoundError``) ``root: no session folder 'WI',
            'SP' ...; the session folders in root are ...: set data.sessions=(...)``.
    """
    root = Path(root)
    found = session_folders(root)
    missing = [n for n in names if not (root / n).is_dir()]
    if missing:
        there = [p.name for p in found]
        more = f" and {len(there) - 20} more" if len(there) > 20 else ""
        listed = ", ".join(_quote(n, 40) for n in there[:20]) + more
        fix = (
            f"the session folders in {root} are {listed}: set data.sessions=({','.join(map(repr, there[:20]))}"
            f"{',' if len(there) == 1 else ''})"
            f" or put the missing folders there ({_DOCS})"
            if there
            else f"{root} holds no session folder (a folder with {CAMERA_FILE}, {_DOCS})"
        )
        names = ", ".join(_quote(n, 40) for n in missing)
        raise _err(root, None, f"no session folder {names} (data.sessions); {fix}", MissingSessionError)
    return [root / n for n in names]


def load_sessions(root: str | os.PathLike, names: Sequence[str], **kwargs) -> list[FolderSession]:
    """Loads ``root/<name>`` for every name (keyword arguments as :func:`load_session`), after checking that every
    folder is there (:func:`require_sessions`)."""
    return [load_session(p, name=n, **kwargs) for p, n in zip(require_sessions(root, names), names, strict=True)]
