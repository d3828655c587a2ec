"""Analytic depth scenes with known geometry: a camera above a ground plane, facing a wall."""

from __future__ import annotations

import numpy as np


def rotation(pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Camera-to-world rotation: pitch about the camera x axis, then roll about its z axis (y down, z forward)."""
    p, r = np.deg2rad(pitch_deg), np.deg2rad(roll_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    return rx @ rz


def ground_and_wall(
    h: int,
    w: int,
    *,
    f: float,
    pitch_deg: float,
    roll_deg: float,
    camera_height_m: float = 1.3,
    wall_distance_m: float = 6.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast z-depth of a horizontal ground plane and a vertical wall seen by a pitched and rolled camera.

    World frame: y down (gravity), z forward; the ground is y = camera_height_m, the wall z = wall_distance_m.

    Returns:
        ``(depth_m (h, w), intrinsics (3, 3) 0-based, gravity_cam (3,), is_ground (h, w) bool)``; the gravity
        vector is the world's down direction expressed in camera coordinates.
    """
    k = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    rot = rotation(pitch_deg, roll_deg)  # camera → world
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays_cam = np.stack([(u - k[0, 2]) / f, (v - k[1, 2]) / f, np.ones_like(u)], -1)  # z_cam = 1
    rays_world = rays_cam @ rot.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(rays_world[..., 1] > 1e-6, camera_height_m / rays_world[..., 1], np.inf)
        t_wall = np.where(rays_world[..., 2] > 1e-6, wall_distance_m / rays_world[..., 2], np.inf)
    t = np.minimum(t_ground, t_wall)
    if not np.all(np.isfinite(t)):
        raise ValueError("every ray must hit the ground or the wall; lower the pitch or the field of view")
    gravity_cam = rot.T @ np.array([0.0, 1.0, 0.0])
    return t, k, gravity_cam, t_ground < t_wall  # t is z-depth since z_cam of every ray is 1
