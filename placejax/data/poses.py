"""Camera poses: rotations as matrices, quaternions and Euler angles, slerp, planar poses, interpolation in time.

Conventions, everywhere in the data layer:

- rotations are camera-to-world (a camera's axes as the columns of its rotation matrix), camera axes as OpenCV's
  (x right, y down, z forward);
- quaternions are in TUM order ``(qx, qy, qz, qw)``, unit norm; :func:`matrix_to_quaternion` returns ``qw >= 0``;
- Euler angles are ``R = Rz(yaw) · Ry(pitch) · Rx(roll)`` (rotations about the fixed x, then y, then z axes);
  :data:`CAMERA_IN_FLU` and :data:`CAMERA_IN_FRD` turn a body rotation into the rotation of a camera that looks
  along the body's x axis.

Example:
    >>> r = rotation_zyx(np.zeros(1), np.zeros(1), np.full(1, np.pi / 2)) @ CAMERA_IN_FLU  # heading +y, z up
    >>> planar_poses(np.array([[1.0, 2.0, 0.5]]), r).round(12).tolist()
    [[1.0, 2.0, 1.570796326795]]
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

__all__ = [
    "CAMERA_IN_FLU",
    "CAMERA_IN_FRD",
    "VERTICAL_AXES",
    "Trajectory",
    "interp_exact",
    "interpolate_poses",
    "matrix_to_quaternion",
    "planar_poses",
    "quaternion_to_matrix",
    "rotation_zyx",
    "slerp",
]

CAMERA_IN_FLU = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""The OpenCV camera axes in a body frame x forward, y left, z up (ROS REP 103): camera x = −y, y = −z, z = x."""
CAMERA_IN_FRD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""The OpenCV camera axes in a body frame x forward, y right, z down (NED, as NCLT): camera x = y, y = z, z = x."""
VERTICAL_AXES = {"z": (0, 1), "x": (1, 2), "y": (2, 0)}
"""Vertical world axis → its two horizontal axes (first, second), in right-handed cyclic order."""


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

    Example:
        >>> matrix_to_quaternion(np.diag([1.0, -1.0, -1.0])).tolist()   # half a turn about x
        [1.0, 0.0, 0.0, 0.0]
    """
    r = np.asarray(r, np.float64)
    shape = r.shape[:-2]
    m = r.reshape(-1, 3, 3)
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    tr = m00 + m11 + m22
    pivot = np.argmax(np.stack([tr, m00, m11, m22], -1), -1)
    s = 2.0 * np.sqrt(np.maximum(np.stack([1.0 + tr, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22,
                                           1.0 - m00 - m11 + m22], -1), 0.0))  # fmt: skip
    a = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]  # antisymmetric parts
    b = m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1]  # symmetric parts
    with np.errstate(divide="ignore", invalid="ignore"):  # only the pivot's candidate is kept
        s0, s1, s2, s3 = s.T
        candidates = np.stack(
            [
                np.stack([a[0] / s0, a[1] / s0, a[2] / s0, 0.25 * s0], -1),
                np.stack([0.25 * s1, b[0] / s1, b[1] / s1, a[0] / s1], -1),
                np.stack([b[0] / s2, 0.25 * s2, b[2] / s2, a[1] / s2], -1),
                np.stack([b[1] / s3, b[2] / s3, 0.25 * s3, a[2] / s3], -1),
            ],
            1,
        )
    q = candidates[np.arange(len(m)), pivot]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[:, 3:] < 0, -q, q)
    return q.reshape(*shape, 4)


def rotation_zyx(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Rotations ``Rz(yaw) · Ry(pitch) · Rx(roll)``, float64 ``(N, 3, 3)``, of angles ``(N,)`` in radians.

    Example:
        >>> (rotation_zyx(np.zeros(1), np.zeros(1), np.full(1, np.pi / 2)).round(12) + 0.0)[0].tolist()  # no -0.0
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    """
    roll, pitch, yaw = (np.asarray(v, np.float64) for v in (roll, pitch, yaw))
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    r = np.empty((len(roll), 3, 3))
    r[:, 0] = np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1)
    r[:, 1] = np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1)
    r[:, 2] = np.stack([-sp, cp * sr, cp * cr], -1)
    return r


def slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical interpolation ``(N, 4)`` between unit quaternions ``(N, 4)`` at ``t (N,)`` in [0, 1], along the
    shorter arc (``q`` and ``−q`` are the same rotation)."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    sin = np.sin(theta)
    near = sin < 1e-9
    safe = np.where(near, 1.0, sin)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


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
    if vertical_axis not in VERTICAL_AXES:
        raise ValueError(f"vertical_axis must be one of {tuple(VERTICAL_AXES)}, got {vertical_axis!r}")
    a, b = VERTICAL_AXES[vertical_axis]
    positions, rotations = np.asarray(positions, np.float64), np.asarray(rotations, np.float64)
    fwd = rotations[:, :, 2]
    return np.stack([positions[:, a], positions[:, b], np.arctan2(fwd[:, b], fwd[:, a])], -1)


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """Camera-to-world poses at strictly increasing times, as read from a pose file.

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


def interp_exact(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """``np.interp`` whose value at a sample's exact time is that sample, bit for bit (clamped outside ``xp``).

    Args:
        x: int64 ``(N,)`` times, µs.
        xp: int64 ``(M,)`` sorted sample times, µs.
        fp: float ``(M,)`` sample values.

    Returns:
        float64 ``(N,)``.
    """
    out = np.interp(x.astype(np.float64), xp.astype(np.float64), fp)
    idx = np.clip(np.searchsorted(xp, x), 0, len(xp) - 1)
    hit = xp[idx] == x
    out[hit] = fp[idx[hit]]
    return out


def interpolate_poses(
    frame_utimes: np.ndarray, trajectory: Trajectory, tolerance_us: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Camera poses at frame times: position linear, orientation slerp between the two samples around each frame.

    Args:
        frame_utimes: int64 ``(N,)`` µs.
        trajectory: sorted poses (``placejax.data.folder.read_tum``).
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
    quat = slerp(trajectory.quaternions[left], trajectory.quaternions[right], w)
    # Exact sample times keep the sample, untouched by the arithmetic above.
    hit = t[right] == f
    pos[hit] = trajectory.positions[right[hit]]
    quat[hit] = trajectory.quaternions[right[hit]]
    nearest = np.minimum(np.abs(f - t[left]), np.abs(t[right] - f))
    outside = (f < t[0]) | (f > t[-1])
    too_far = ~outside & (nearest > tolerance_us)
    return pos, quat, outside, too_far
