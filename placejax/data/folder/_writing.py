"""Writing session folders (what the exporters use): every file atomic, timestamps and poses round-trip exactly."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from placejax import io
from placejax.data.folder._camera_file import CAMERA_FILE, CameraSpec
from placejax.data.folder._formats import IMAGE_TABLE, IMAGES_DIR, KITTI_FILE, ODOMETRY_FILE, TUM_FILE, format_timestamp
from placejax.data.folder._frames import DEPTH_DIR
from placejax.data.poses import quaternion_to_matrix

__all__ = ["write_poses", "write_session"]


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
