"""Pinhole intrinsics under the image operations the data layer applies (rotation, resizing).

All matrices use the 0-based (OpenCV) pixel convention: the centre of pixel (row i, col j) is at u = j, v = i.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["project", "resize_image", "resize_intrinsics", "rotate_intrinsics_cw"]


def _as_k(k: np.ndarray) -> np.ndarray:
    k = np.asarray(k, dtype=np.float64)
    if k.shape != (3, 3):
        raise ValueError(f"intrinsics must be a (3, 3) matrix, got shape {k.shape}")
    return k


def rotate_intrinsics_cw(k: np.ndarray, raw_height: int) -> np.ndarray:
    """Intrinsics of an image rotated 90° clockwise (``cv2.ROTATE_90_CLOCKWISE`` / ``np.rot90(img, k=-1)``).

    A raw pixel (u, v) of an image ``raw_height`` rows tall moves to (u', v') = (H_raw − 1 − v, u), and the
    camera axes rotate with it (x' = −y, y' = x), so K' = P K Rᵀ with P the pixel map and R the axis rotation.
    For a skew-free K this is fx' = fy, fy' = fx, cx' = H_raw − 1 − cy, cy' = cx.

    Args:
        k: float ``(3, 3)`` intrinsics of the unrotated image, pixels.
        raw_height: rows of the unrotated image.

    Returns:
        float64 ``(3, 3)`` intrinsics of the rotated image.

    Example:
        >>> rotate_intrinsics_cw(np.array([[400.0, 0, 826], [0, 390, 621], [0, 0, 1]]), 1232).tolist()
        [[390.0, 0.0, 610.0], [0.0, 400.0, 826.0], [0.0, 0.0, 1.0]]
    """
    k = _as_k(k)
    pixel_map = np.array([[0.0, -1.0, raw_height - 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    axis_rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return pixel_map @ k @ axis_rotation.T


def resize_intrinsics(k: np.ndarray, from_hw: tuple[int, int], to_hw: tuple[int, int]) -> np.ndarray:
    """Intrinsics ``k`` ``(3, 3)`` after resizing an ``from_hw`` image to ``to_hw`` (``cv2.resize``, pixel-centre
    aligned); a new ``(3, 3)`` float64 matrix.

    With pixel centres at integer coordinates, ``cv2.resize`` maps u to (u + 0.5)·s − 0.5 with s = W'/W (same
    for v with H'/H), so fx' = s·fx and cx' = (cx + 0.5)·s − 0.5.
    """
    k = _as_k(k)
    sy, sx = to_hw[0] / from_hw[0], to_hw[1] / from_hw[1]
    scale = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return scale @ k


def resize_image(image: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """Resizes ``image (H, W, C)`` to ``hw = (H', W')``; area averaging when shrinking (no aliasing), else bilinear.

    Returns the input unchanged when it already has that size.
    """
    h, w = int(hw[0]), int(hw[1])
    if image.shape[:2] == (h, w):
        return image
    if h < 1 or w < 1:
        raise ValueError(f"target size must be positive, got {hw}")
    shrink = h <= image.shape[0] and w <= image.shape[1]
    return cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def project(k: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates ``(N, 2)`` (u, v) of camera-frame points ``(N, 3)`` (x right, y down, z forward)."""
    p = np.asarray(points, dtype=np.float64) @ _as_k(k).T
    return p[:, :2] / p[:, 2:3]
