"""Warnings about trajectories that read fine but are unlikely to be what a robot drove (two axes swapped, another
unit, the wrong vertical axis): ``python -m placejax.data check`` prints them with their numbers; nothing fails."""

from __future__ import annotations

import numpy as np

from placejax.data.poses import VERTICAL_AXES

__all__ = [
    "MAX_ELEVATION_DEG",
    "MAX_VERTICAL_SHARE",
    "MIN_EXTENT_M",
    "MIN_EXTENT_RATIO",
    "MIN_MOTION_M",
    "PLAUSIBLE_SPEED_MPS",
    "trajectory_warnings",
]

MIN_MOTION_M = 0.01
"""A session whose frames all lie within this (metres, both horizontal axes) has not moved: one place for all."""
PLAUSIBLE_SPEED_MPS = 10.0
"""A ground robot's top speed, m/s: a 95th-percentile speed between frames above it is worth a warning."""
MIN_EXTENT_M = 10.0
"""Trajectories whose larger horizontal extent is below this (metres) are not judged by their shape."""
MIN_EXTENT_RATIO = 0.05
"""Smaller over larger horizontal extent below this: a nearly one-dimensional trajectory."""
MAX_VERTICAL_SHARE = 0.2
"""The vertical coordinate's range over the larger horizontal extent above this (and above 2 m): the camera
height varies like a horizontal coordinate."""
MAX_ELEVATION_DEG = 45.0
"""The median angle of the optical axis above or below the horizontal plane above this: the camera looks up or
down, where a ground robot's camera looks about level."""


def trajectory_warnings(
    name: str, utimes: np.ndarray, positions: np.ndarray, rotations: np.ndarray, vertical_axis: str
) -> list[str]:
    """One line per implausible trait of a session's trajectory, with the numbers that make it so.

    Args:
        name: the session (starts every line).
        utimes: int64 ``(N,)`` frame times, µs, strictly increasing.
        positions: float ``(N, 3)`` camera centres, metres.
        rotations: float ``(N, 3, 3)`` camera-to-world rotations (OpenCV camera axes).
        vertical_axis: ``"z"``, ``"y"`` or ``"x"`` (``camera.json``).

    Returns:
        The warnings (empty for a plausible trajectory).

    Example:
        >>> t = np.arange(50) * 1_000_000
        >>> line = np.stack([np.arange(50.0), np.zeros(50), np.full(50, 1.2)], -1)   # 1 m/s along x
        >>> level = np.broadcast_to(np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]), (50, 3, 3))
        >>> [w[:40] for w in trajectory_warnings("a", t, line, level, "z")]
        ['a: spans 49 m along x but 0 m along y (r']
    """
    out = []
    a, b = VERTICAL_AXES[vertical_axis]
    v = 3 - a - b
    positions = np.asarray(positions, np.float64)
    if len(positions) >= 2 and np.ptp(positions[:, [a, b]], axis=0).max() < MIN_MOTION_M:
        out.append(
            f"{name}: all {len(positions)} frames are at one place (moved less than {100 * MIN_MOTION_M:g} cm over "
            f"{(utimes[-1] - utimes[0]) / 1e6:.3g} s), so every frame gets one place class: do the image times fall "
            "within one pose interval (images named by frame number, times on another clock), or did the robot "
            "stand still?"
        )
    if len(positions) >= 2:
        speed = np.linalg.norm(np.diff(positions, axis=0), axis=1) / (np.diff(utimes) / 1e6)
        p50, p95, top = np.percentile(speed, [50, 95, 100])
        if p95 > PLAUSIBLE_SPEED_MPS:
            out.append(
                f"{name}: the camera moves {p50:.3g} m/s (median), {p95:.3g} m/s (95th percentile), {top:.3g} m/s "
                f"at most between frames, faster than a ground robot ({PLAUSIBLE_SPEED_MPS:g} m/s): positions in "
                "another unit, or timestamps?"
            )
    extent = np.ptp(positions, axis=0)
    axes = "xyz"
    wide, narrow = (a, b) if extent[a] >= extent[b] else (b, a)
    big = float(extent[wide])
    if big >= MIN_EXTENT_M and extent[narrow] < MIN_EXTENT_RATIO * big:
        out.append(
            f"{name}: spans {big:.3g} m along {axes[wide]} but {extent[narrow]:.3g} m along {axes[narrow]} (ratio "
            f"{extent[narrow] / big:.3f} < {MIN_EXTENT_RATIO:g}): a straight drive, or two axes swapped in the pose "
            "file?"
        )
    if big > 0 and extent[v] > max(2.0, MAX_VERTICAL_SHARE * big):
        out.append(
            f"{name}: the camera height ({axes[v]}, vertical_axis {vertical_axis!r}) varies over {extent[v]:.3g} m "
            f"(std {np.std(positions[:, v]):.3g} m) against a horizontal extent of {big:.3g} m: another vertical "
            "axis, or two axes swapped in the pose file?"
        )
    rotations = np.asarray(rotations, np.float64)
    if len(rotations):
        elevation = np.degrees(np.arcsin(np.clip(np.abs(rotations[:, v, 2]), 0.0, 1.0)))
        median = float(np.median(elevation))
        if median > MAX_ELEVATION_DEG:
            out.append(
                f"{name}: the optical axis is {median:.0f}° from the horizontal plane (median over the frames), "
                f"where a ground robot's camera looks about level: is vertical_axis {vertical_axis!r} right "
                "(visual odometry in the first camera's frame: 'y')?"
            )
    return out
