"""Plain NumPy float64 HHA encoder: one image at a time, the reference algorithm step by step.

This is the test oracle for :func:`placejax.hha.encode` and the baseline of ``benchmarks.hha_speed``. It follows
the original formulation of Gupta et al. (``rcnn-depth``/``rgbdutils``, as described in ``docs/hha.md``):
raw (uncentred) least-squares moments summed in square windows, an adjugate solve, and the iterative gravity
estimate. In float64 it reproduces the reference HHA images exactly; it is deliberately simple, not fast.
"""

from __future__ import annotations

import numpy as np

from placejax.hha._constants import (
    ANGLE_NAN_DEG,
    ANGLE_OFFSET,
    DISPARITY_MIN_CM,
    DISPARITY_NUMERATOR,
    FLOOR_FALLBACK_CM,
    FLOOR_RULE_CM,
    GRAVITY_ITERATIONS,
    GRAVITY_THRESHOLDS_DEG,
    RADIUS_ANGLE,
    RADIUS_GRAVITY,
    ROTATION_SKIP_DEG,
)


def box_sum(x: np.ndarray, r: int) -> np.ndarray:
    """Sum of ``x`` over the (2r+1)×(2r+1) window centred on each pixel, zero-padded, same size.

    Direct separable sums, not a summed-area table: a window with nothing in it must sum to exactly 0 (the
    reference marks such normals NaN through 0/0), which running-sum differences do not guarantee.

    Args:
        x: ``(H, W, ...)`` array.
        r: window radius in pixels.
    """
    h, w = x.shape[:2]
    pad = [(r, r), (r, r)] + [(0, 0)] * (x.ndim - 2)
    xp = np.pad(x, pad)
    rows = sum(xp[i : i + h] for i in range(2 * r + 1))
    return sum(rows[:, j : j + w] for j in range(2 * r + 1))


def point_cloud_cm(depth_cm: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` camera-frame points in cm (x right, y down, z forward); intrinsics 0-based."""
    h, w = depth_cm.shape
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([(u - cx) * depth_cm / fx, (v - cy) * depth_cm / fy, depth_cm], axis=-1)


def normals(points: np.ndarray, missing: np.ndarray, r: int) -> np.ndarray:
    """Unit normals ``(H, W, 3)`` from a least-squares plane fit in (2r+1)² windows; NaN where nothing is valid.

    Fits x1·a + x2·b + x3 = 1/Z (a = X/Z, b = Y/Z) over the window: the plane x·p = 1, normal ∝ x.
    """
    p = np.where(missing[..., None], np.nan, points)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    a, b, wz = x / z, y / z, 1.0 / z
    one = np.where(np.isnan(z), np.nan, 1.0)
    ata = np.stack([a * a, a * b, a, b * b, b, one], axis=-1)
    atb = np.stack([a * wz, b * wz, wz], axis=-1)
    ata = box_sum(np.nan_to_num(ata, nan=0.0), r)
    atb = box_sum(np.nan_to_num(atb, nan=0.0), r)
    s_aa, s_ab, s_a, s_bb, s_b, s_1 = np.moveaxis(ata, -1, 0)
    # Adjugate of the symmetric matrix [[aa, ab, a], [ab, bb, b], [a, b, 1]]; no division by the determinant.
    adj = np.stack(
        [
            np.stack([s_bb * s_1 - s_b * s_b, s_a * s_b - s_ab * s_1, s_ab * s_b - s_a * s_bb], -1),
            np.stack([s_a * s_b - s_ab * s_1, s_aa * s_1 - s_a * s_a, s_ab * s_a - s_aa * s_b], -1),
            np.stack([s_ab * s_b - s_a * s_bb, s_ab * s_a - s_aa * s_b, s_aa * s_bb - s_ab * s_ab], -1),
        ],
        -2,
    )
    n = np.einsum("...ij,...j->...i", adj, atb)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    # Orientation: first N_z >= 0, then N·P >= 0 with the unmasked points (NaN and 0 count as +).
    sz = np.sign(n[..., 2])
    sz[sz == 0] = 1
    n = n * sz[..., None]
    sp = np.sign(np.sum(n * points, axis=-1))
    sp[np.isnan(sp) | (sp == 0)] = 1
    return n * sp[..., None]


def gravity(normals_r10: np.ndarray) -> np.ndarray:
    """Gravity direction (unit, camera frame, pointing down) from the iterative floor/wall eigen-update."""
    nn = normals_r10.reshape(-1, 3)
    nn = nn[~np.isnan(nn[:, 0])]
    y = np.array([0.0, 1.0, 0.0])
    for thresh_deg, iters in zip(GRAVITY_THRESHOLDS_DEG, GRAVITY_ITERATIONS, strict=True):
        t = np.deg2rad(thresh_deg)
        for _ in range(iters):
            c = np.abs(nn @ y)
            nf, nw = nn[c > np.cos(t)], nn[c < np.sin(t)]
            a = nw.T @ nw - nf.T @ nf
            evals, evecs = np.linalg.eigh(a)
            new = evecs[:, np.argmin(evals)]
            s = np.sign(y @ new)
            y = new * (1.0 if s == 0 else s)
    return y


def height_cm(points: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Height above the assumed floor in cm, after rotating the cloud so that ``g`` becomes +y."""
    y0 = np.array([0.0, 1.0, 0.0])
    phi = np.arccos(np.clip(y0 @ g, -1.0, 1.0))
    if abs(np.rad2deg(phi)) > ROTATION_SKIP_DEG:
        ax = np.cross(y0, g)
        ax /= np.linalg.norm(ax)
        k = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
        rot = np.eye(3) + np.sin(phi) * k + (1 - np.cos(phi)) * (k @ k)  # Rodrigues: rot @ y0 == g
    else:
        rot = np.eye(3)
    h = -(points @ rot)[..., 1]  # (rotᵀ p)_y for every point
    y_min = h.min()
    if y_min > FLOOR_RULE_CM:
        y_min = FLOOR_FALLBACK_CM
    return h - y_min


def encode_reference(depth_m: np.ndarray, intrinsics: np.ndarray, raw_depth_m: np.ndarray | None = None):
    """HHA of one dense depth image, float64 throughout.

    Args:
        depth_m: ``(H, W)`` dense depth in metres (every pixel > 0 and finite).
        intrinsics: ``(3, 3)`` pinhole matrix, 0-based pixel convention.
        raw_depth_m: ``(H, W)`` raw depth; pixels where it is 0 are missing for the normal fits. ``None``: none.

    Returns:
        ``(hha, gravity)``: ``uint8 (H, W, 3)`` in the order (disparity, height, angle), and the unit gravity
        vector ``(3,)`` in camera coordinates (pointing down).
    """
    depth_cm = np.asarray(depth_m, np.float64) * 100.0
    k = np.asarray(intrinsics, np.float64)
    missing = np.zeros(depth_cm.shape, bool) if raw_depth_m is None else np.asarray(raw_depth_m) == 0
    pts = point_cloud_cm(depth_cm, k)
    n_angle = normals(pts, missing, RADIUS_ANGLE)
    g = gravity(normals(pts, missing, RADIUS_GRAVITY))
    h = height_cm(pts, g)
    angle = np.rad2deg(np.arccos(np.clip(np.sum(n_angle * g, axis=-1), -1.0, 1.0)))
    angle[np.isnan(angle)] = ANGLE_NAN_DEG
    disparity = DISPARITY_NUMERATOR / np.maximum(depth_cm, DISPARITY_MIN_CM)
    hha = np.rint(np.stack([disparity, h, angle + ANGLE_OFFSET], axis=-1))
    return np.minimum(hha, 255).astype(np.uint8), g
