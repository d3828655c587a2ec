"""Jitted, batched HHA encoder (float32, centred least squares, gravity loop that stops at its fixed point).

The algorithm is the reference one (``docs/hha.md``, Gupta et al. ECCV 2014); what differs is how it is
computed so that float32 is enough and XLA can compile it once for a whole batch. The window sums and plane
fits live in :mod:`placejax.hha._windows` (centred moments; closed-form fits for dense images); this module holds
the gravity estimate, the channels and the batch loop.

* The batch runs one image at a time (``lax.map``): every stage of one image, gravity's iterations included,
  works on a few MiB that stay in cache (a 256² map is 256 KiB), where one ``vmap`` over the batch makes every
  kernel stream that stage's maps for all images (~54 MB per kernel at 256² × 32) through memory. XLA still
  splits each large kernel between the cores.
* Whether an image is dense (every pixel usable by the fits) is decided per image by a ``lax.cond`` on the
  data; dense images skip the moments of the mask and the per-pixel adjugate.
* The gravity estimate runs its 5 + 5 iterations as two ``lax.while_loop`` s that stop once an iteration
  returns its input bit for bit: from there on every further iteration of that pass would return it again (the
  floor/wall sets, hence A, are functions of the estimate alone), so the result is the fixed-trip-count one.
* ``encode`` (the HHA image only) compiles without the intermediates ``encode_full`` returns: the stacked
  normals, heights and angles are never written.
* ``jnp.arccos`` (an ``atan2`` that does not vectorise) is replaced by a float32 polynomial of the same accuracy.

Where the time goes, stage by stage, against the machine's memory bandwidth and arithmetic rate:
``python -m benchmarks.hha_roofline`` (``docs/hha.md``, "Speed").
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
from typing import NamedTuple

import jax
import jax.numpy as jnp
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
from placejax.hha._windows import (
    WEIGHT_SPEC,
    _materialise,
    _moments,
    fit_planes,
    fit_planes_dense,
    inverse_norm,
    mask_terms,
    unit_normals,
)

ENCODER_VERSION = 3
"""The encoder's version, part of every HHA cache key: bumped whenever its outputs may change, so that a cache of
an older encoder is rebuilt, not reused (2: the per-image loop, one level apart from version 1 on about 7e-5 of the
values; 3: a repeated smallest eigenvalue in the gravity loop keeps the estimate nearest the current one, which
changes head-on walls and nothing in the default run's images)."""


class HHAResult(NamedTuple):
    """HHA image and the intermediates it was computed from (leading batch axes as in the input).

    Attributes:
        hha: ``uint8 (..., H, W, 3)`` channels (disparity, height, angle). Missing pixels (depth outside the
            valid range, NaN/±inf included, or unusable intrinsics) are 0 in all three channels.
        normals: ``float32 (..., H, W, 3)`` unit surface normals from 7×7 windows, camera frame (x right, y down,
            z forward), pointing away from the camera; 0 where undefined (see ``normal_valid``).
        normal_valid: ``bool (..., H, W)``: the 7×7 window held at least one valid pixel.
        gravity: ``float32 (..., 3)`` unit gravity direction in the camera frame (pointing down).
        height_cm: ``float32 (..., H, W)`` height above the estimated floor in centimetres (before rounding).
        angle_deg: ``float32 (..., H, W)`` angle between normal and gravity in degrees; 180 where undefined.
        valid: ``bool (..., H, W)`` pixels whose depth lies in the valid range [min_depth_m, max_depth_m] (and
            whose image has usable intrinsics).
    """

    hha: jax.Array
    normals: jax.Array
    normal_valid: jax.Array
    gravity: jax.Array
    height_cm: jax.Array
    angle_deg: jax.Array
    valid: jax.Array


@dataclasses.dataclass(frozen=True)
class HeightRule:
    """Where the height channel's floor is and how many centimetres one level is.

    The reference (the default) takes the lowest valid point as the floor (1.3 m below the camera when that point is
    less than 0.9 m below it) and one level per centimetre, capped at 255. Outdoors that floor is often no floor:
    sky or far points a degree or two off the estimated gravity lie tens of metres below the camera, and most
    heights then sit at the cap.

    Attributes:
        floor: ``"lowest"`` (the reference), ``"near"`` (the lowest valid point nearer than ``near_m``, with the
            reference's fallback) or ``"camera"`` (``camera_height_m`` below the camera: the height prior of a robot
            whose camera height is known).
        near_m: the farthest depth (metres) a floor point may have, for ``floor="near"``.
        camera_height_m: the camera's height above the floor (metres), for ``floor="camera"``.
        cm_per_level: centimetres per level of the height channel (1 in the reference; 4 spans 10.2 m).
    """

    floor: str = "lowest"
    near_m: float | None = None
    camera_height_m: float | None = None
    cm_per_level: float = 1.0

    def __post_init__(self):
        if self.floor not in ("lowest", "near", "camera"):
            raise ValueError(f"HeightRule.floor must be 'lowest', 'near' or 'camera', got {self.floor!r}")
        for name, needed in (("near_m", self.floor == "near"), ("camera_height_m", self.floor == "camera")):
            value = getattr(self, name)
            if needed and (value is None or isinstance(value, bool) or not 0 < float(value) < math.inf):
                raise ValueError(f"HeightRule.{name} must be a positive number for floor={self.floor!r}, got {value!r}")
            if not needed and value is not None:
                raise ValueError(f"HeightRule.{name} applies only to floor={name.split('_')[0]!r}, got {value!r}")
        cm = self.cm_per_level
        if isinstance(cm, bool) or not isinstance(cm, int | float) or not 0 < float(cm) < math.inf:
            raise ValueError(f"HeightRule.cm_per_level must be a positive number, got {cm!r}")


REFERENCE_HEIGHT = HeightRule()
"""The reference's height channel: the lowest point as the floor, 1 cm per level."""


# ----------------------------------------------------------------------------------------------------------------------
# Gravity.


def _gravity(x: jax.Array, inv_norm: jax.Array, token: jax.Array) -> jax.Array:
    """Iterative floor/wall estimate of the down direction (reference ``getYDir``) of one image, from its 21×21
    planes ``x (3, H, W)`` and their inverse norms (0 where a window defines no plane): unit ``(3,)``."""
    with jax.named_scope("gravity_rows"):
        outer = _gravity_rows(x, inv_norm, token)
    with jax.named_scope("gravity_iterations"):
        return _gravity_iterate(outer)[0]


def _gravity_rows(x: jax.Array, inv_norm: jax.Array, token: jax.Array) -> jax.Array:
    """``(6, P)``: the distinct entries (xx, xy, xz, yy, yz, zz) of n nᵀ for every pixel's unit normal n (0 where
    no plane); the orientation of n drops out of them."""
    n = (x * inv_norm[None]).reshape(3, -1)
    # One gather of rows (a stack of six products is a concatenate, which XLA CPU writes element by element, ~3×
    # slower). Materialised, so that the weights read the very array the product reads (left alone, XLA feeds
    # them six separate copies of the rows: twice the memory each iteration reads).
    return _materialise(n[np.array([0, 0, 0, 1, 1, 2])] * n[np.array([0, 1, 2, 1, 2, 2])], token)


def _gravity_step(outer: jax.Array, y: jax.Array, theta_deg: float) -> jax.Array:
    """One iteration: the smallest eigenvector of A = Σ_W n nᵀ − Σ_F n nᵀ, sign-aligned with the estimate ``y``.

    The ±1/0 floor/wall weights come from c² = (n·y)² = Σ (n nᵀ)·(y yᵀ), so that the iteration reads the six
    rows of ``outer`` and nothing else; A is then one matrix-vector product, (n nᵀ entries) · weights. Windows
    without a plane have n nᵀ = 0: whatever weight they get, they add nothing.
    """
    dtype = outer.dtype
    cos2_t = np.asarray(np.cos(np.deg2rad(theta_deg)) ** 2, dtype)
    sin2_t = np.asarray(np.sin(np.deg2rad(theta_deg)) ** 2, dtype)
    q = (y[0] * y[0], 2 * y[0] * y[1], 2 * y[0] * y[2], y[1] * y[1], 2 * y[1] * y[2], y[2] * y[2])
    c2 = sum(outer[k] * q[k] for k in range(6))
    weight = jnp.where(c2 < sin2_t, 1.0, 0.0).astype(dtype) - jnp.where(c2 > cos2_t, 1.0, 0.0).astype(dtype)
    axx, axy, axz, ayy, ayz, azz = jnp.dot(outer, weight, precision=jax.lax.Precision.HIGHEST)
    a = jnp.stack([jnp.stack([axx, axy, axz]), jnp.stack([axy, ayy, ayz]), jnp.stack([axz, ayz, azz])])
    new = _smallest_eigenvector(a, y)
    new = new * jnp.where(new @ y < 0, -1.0, 1.0)
    # Nothing selected: A = 0 has no preferred direction, so keep the current estimate. A = 0 means exactly
    # that, without a separate count: tr A = |W| − |F| (unit normals) would force |W| = |F| = k, and then
    # yᵀAy = Σ_W c² − Σ_F c² < k sin²θ − k cos²θ ≤ 0 (θ ≤ 45°) unless k = 0.
    return jnp.where(jnp.any(a != 0), new, y)


_TIE_RTOL = 1e-5
"""Eigenvalues within this fraction of the largest magnitude of the smallest count as one repeated eigenvalue: the
float32 sums of the floor/wall matrix do not tell them apart."""


def _smallest_eigenvector(a: jax.Array, y: jax.Array) -> jax.Array:
    """Unit eigenvector of the smallest eigenvalue of the symmetric 3×3 ``a``; where that eigenvalue is repeated,
    the vector of its eigenspace nearest the current estimate ``y``.

    A scene of head-on walls gives A ≈ diag(0, 0, k): every direction of the image plane is an answer, and which
    one an eigensolver returns is decided by rounding and by the machine's LAPACK kernels (for a flat wall the
    float64 reference gives the image's down axis on a Xeon and its x axis on an EPYC; float32 LAPACK gave the x
    axis). The nearest to ``y`` keeps what the data do not contradict, on every machine, and ``y`` itself is then a
    fixed point.
    """
    w, vecs = jnp.linalg.eigh(a, symmetrize_input=False)  # a is symmetric by construction; w ascends
    tied = w <= w[0] + _TIE_RTOL * jnp.max(jnp.abs(w))
    nearest = vecs @ jnp.where(tied, vecs.T @ y, 0.0)
    length2 = nearest @ nearest
    nearest = nearest * jax.lax.rsqrt(jnp.where(length2 > 0, length2, 1.0))
    return jnp.where((jnp.sum(tied) > 1) & (length2 > 0), nearest, vecs[:, 0])


def _gravity_iterate(outer: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The 5 + 5 iterations from y = (0, 1, 0): ``(gravity (3,), iterations run (2,) int32)``.

    Each pass stops early at a fixed point (an iteration that returns its input bit for bit), which changes
    nothing: every further iteration of the pass would compute the same A from the same estimate.
    """

    def bits(v):
        return jax.lax.bitcast_convert_type(v, jnp.int32)

    y = jnp.array([0.0, 1.0, 0.0], outer.dtype)
    runs = []
    for theta_deg, iterations in zip(GRAVITY_THRESHOLDS_DEG, GRAVITY_ITERATIONS, strict=True):

        def body(state, theta_deg=theta_deg):
            i, y, _ = state
            new = _gravity_step(outer, y, theta_deg)
            return i + 1, new, jnp.all(bits(new) == bits(y))

        def more(state, iterations=iterations):
            i, _, fixed = state
            return (i < iterations) & ~fixed

        i, y, _ = jax.lax.while_loop(more, body, (jnp.int32(0), y, jnp.bool_(False)))
        runs.append(i)
    return y, jnp.stack(runs)


# ----------------------------------------------------------------------------------------------------------------------
# One image.


def _arccos(x: jax.Array) -> jax.Array:
    """arccos on [−1, 1] as a polynomial (Cephes ``acosf``: max error ~3e-7 rad, as ``jnp.arccos`` in float32).

    XLA CPU lowers ``jnp.arccos`` to an ``atan2`` that does not vectorise: ~1.5 ms per 256×256 image, more than
    the whole angle channel otherwise costs; this is elementwise arithmetic and one ``sqrt``. Other dtypes (float64)
    keep ``jnp.arccos``, whose accuracy the polynomial would not match.
    """
    if x.dtype != jnp.float32:
        return jnp.arccos(x)
    a = jnp.abs(x)
    big = a > 0.5
    z = jnp.where(big, 0.5 * (1.0 - a), a * a)
    s = jnp.where(big, jnp.sqrt(z), a)
    p = (((4.2163199048e-2 * z + 2.4181311049e-2) * z + 4.5470025998e-2) * z + 7.4953002686e-2) * z + 1.6666752422e-1
    asin_s = s + s * z * p  # arcsin(s)
    acos_a = jnp.where(big, 2.0 * asin_s, np.float32(np.pi / 2) - asin_s)  # arccos(|x|)
    return jnp.where(x < 0, np.float32(np.pi) - acos_a, acos_a)


def _prepare_one(depth_m, raw_depth_m, intrinsics, depth_range):
    """One image's masks and camera: ``(valid, fit_mask, camera)`` with camera = (a_c (1, W), b_c (H, 1),
    z (H, W) cm, fx, fy).

    Every decision about the data is taken here, on traced values, so the result is the same eagerly and under
    a caller's ``jit``/``vmap``: depth outside the range (NaN and ±inf included) is missing; an image whose
    intrinsics are non-finite or have fx ≤ 0 or fy ≤ 0 is entirely missing (its matrix is replaced by the
    identity so that no NaN leaks into the outputs).
    """
    h, w = depth_m.shape
    dtype = depth_m.dtype
    lo, hi = depth_range[0], depth_range[1]
    fx, fy = intrinsics[0, 0], intrinsics[1, 1]
    k_ok = jnp.all(jnp.isfinite(intrinsics)) & (fx > 0) & (fy > 0)
    intrinsics = jnp.where(k_ok, intrinsics, jnp.eye(3, dtype=dtype))
    valid = (depth_m >= lo) & (depth_m <= hi) & k_ok  # NaN compares False
    fit_mask = valid if raw_depth_m is None else valid & (raw_depth_m >= lo) & (raw_depth_m <= hi)
    z = jnp.where(valid, depth_m, 0.0) * 100.0  # cm, as the reference
    fx, fy = intrinsics[0, 0], intrinsics[1, 1]
    cx, cy = intrinsics[0, 2], intrinsics[1, 2]
    a_c = (jnp.arange(w, dtype=dtype)[None, :] - cx) / fx  # (1, W): X/Z of each column
    b_c = (jnp.arange(h, dtype=dtype)[:, None] - cy) / fy  # (H, 1): Y/Z of each row
    return valid, fit_mask, (a_c, b_c, z, fx, fy)


def _planes_dense(fit_mask, camera, token):
    """7×7 and 21×21 planes ``(x, inverse norm)`` of an image whose every pixel is usable (``fit_mask`` all True)."""
    with jax.named_scope("window_sums"):
        mw7, mw21 = _moments(1.0 / camera[2], WEIGHT_SPEC, token)
    with jax.named_scope("plane_fits"):
        x7, regular7 = fit_planes_dense(mw7, RADIUS_ANGLE, camera, token)
        x21, regular21 = fit_planes_dense(mw21, RADIUS_GRAVITY, camera, token)
        return _materialise(((x7, inverse_norm(x7, regular7)), (x21, inverse_norm(x21, regular21))), token)


def _planes_masked(fit_mask, camera, token):
    """7×7 and 21×21 planes of an image with missing pixels: fits from the moments of its own mask."""
    z = camera[2]
    m = fit_mask.astype(z.dtype)
    with jax.named_scope("mask_window_sums"):
        (cof7, regular7), (cof21, regular21) = mask_terms(m, token)
    with jax.named_scope("window_sums"):
        mw7, mw21 = _moments(m / jnp.where(fit_mask, z, 1.0), WEIGHT_SPEC, token)
    with jax.named_scope("plane_fits"):
        x7, regular7 = fit_planes(cof7, regular7, mw7, camera, token)
        x21, regular21 = fit_planes(cof21, regular21, mw21, camera, token)
        return _materialise(((x7, inverse_norm(x7, regular7)), (x21, inverse_norm(x21, regular21))), token)


def _finish_one(valid, camera, x7, inv7, g, full: bool, height_rule: HeightRule = REFERENCE_HEIGHT):
    """One image's height, angle and quantised channels from its 7×7 planes and its gravity vector: the HHA
    channels packed as ``uint32 (H, W)`` (and, if ``full``, the normals and the float channels)."""
    a_c, b_c, z, _, _ = camera
    dtype = z.dtype
    nx, ny, nz = unit_normals(x7, inv7, camera)
    ok_angle = inv7 > 0

    rotate = jnp.arccos(jnp.clip(g[1], -1.0, 1.0)) > np.deg2rad(ROTATION_SKIP_DEG)
    up = jnp.where(rotate, g, jnp.array([0.0, 1.0, 0.0], dtype))  # (Rᵀp)_y = (R y0)·p = g·p, R y0 = g (Rodrigues)
    height = -z * (a_c * up[0] + b_c * up[1] + up[2])
    if height_rule.floor == "camera":
        y_min = jnp.asarray(-100.0 * height_rule.camera_height_m, dtype)
    else:
        candidates = valid if height_rule.floor == "lowest" else valid & (z <= 100.0 * height_rule.near_m)
        y_min = jnp.min(jnp.where(candidates, height, jnp.inf))
        y_min = jnp.where(y_min > FLOOR_RULE_CM, FLOOR_FALLBACK_CM, y_min)
    height = height - y_min
    levels = height if height_rule.cm_per_level == 1 else height / np.asarray(height_rule.cm_per_level, dtype)

    cos_angle = jnp.clip(nx * g[0] + ny * g[1] + nz * g[2], -1.0, 1.0)
    angle = jnp.where(ok_angle, jnp.degrees(_arccos(cos_angle)), ANGLE_NAN_DEG)
    disparity = DISPARITY_NUMERATOR / jnp.maximum(z, DISPARITY_MIN_CM)

    def quantise(x):  # round half to even (as np.rint), cap at 255; invalid depth → 0
        return jnp.where(valid, jnp.clip(jnp.round(x), 0, 255), 0).astype(jnp.uint32)

    # The three channels packed into one uint32 per pixel (bytes 0, 1, 2): one kernel writes them, and the
    # batch's (B, H, W, 3) array is then a byte view of it (_channels_last).
    packed = quantise(disparity) | (quantise(levels) << 8) | (quantise(angle + ANGLE_OFFSET) << 16)
    if not full:
        return packed
    return packed, (nx, ny, nz), ok_angle, g, jnp.where(valid, height, 0.0), angle, valid


def _encode_one(depth_m, raw_depth_m, intrinsics, depth_range, token, full: bool, height_rule: HeightRule):
    """One ``(H, W)`` image, unbatched: a ``lax.cond`` picks the dense fits when every pixel is usable (``cond``
    runs one branch; under a caller's ``vmap`` it becomes a select of both, each image still getting its own
    branch's result)."""
    with jax.named_scope("prepare"):
        valid, fit_mask, camera = _prepare_one(depth_m, raw_depth_m, intrinsics, depth_range)
    (x7, inv7), (x21, inv21) = jax.lax.cond(jnp.all(fit_mask), _planes_dense, _planes_masked, fit_mask, camera, token)
    g = _gravity(x21, inv21, token)
    with jax.named_scope("finish"):
        return _finish_one(valid, camera, x7, inv7, g, full, height_rule)


@functools.partial(jax.jit, static_argnames=("full", "height_rule"))
def _encode_batch(
    depth_m, intrinsics, raw_depth_m, depth_range, full: bool = True, height_rule: HeightRule = REFERENCE_HEIGHT
):
    """``depth_m (B, H, W)`` metres, ``intrinsics (B, 3, 3)``, ``raw_depth_m (B, H, W)`` metres or ``None``,
    ``depth_range (2,)``: the inclusive valid depth range [min, max] in metres; ``height_rule``: the height channel's
    floor and scale (:class:`HeightRule`).

    Returns the :class:`HHAResult`, or with ``full=False`` only its ``uint8 (B, H, W, 3)`` HHA images (then
    nothing else is computed into memory).
    """
    token = jnp.sum(depth_m.reshape(-1)[:1])  # any unbatched runtime scalar (see _materialise); 0 if empty
    fn = functools.partial(_encode_one, depth_range=depth_range, token=token, full=full, height_rule=height_rule)
    out = jax.lax.map(lambda a: fn(*a), (depth_m, raw_depth_m, intrinsics))
    with jax.named_scope("channels_last"):
        if not full:
            return _channels_last(out)
        packed, normals, ok_angle, g, height, angle, valid = out
        normals = jnp.moveaxis(jnp.stack(normals, axis=1), 1, -1)  # a stack along the last axis is ~3× slower
        return HHAResult(_channels_last(packed), normals, ok_angle, g, height, angle, valid)


def _channels_last(packed: jax.Array) -> jax.Array:
    """``uint8 (..., 3)`` channels from pixels packed by :func:`_finish_one` (byte k = channel k): a byte view
    and one strided copy, where stacking three maps along the last axis is written element by element."""
    as_bytes = jax.lax.bitcast_convert_type(packed, jnp.uint8)  # (..., 4) in the platform's byte order
    return as_bytes[..., :3] if sys.byteorder == "little" else as_bytes[..., :0:-1]
