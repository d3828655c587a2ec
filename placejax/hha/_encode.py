"""Jitted, batched HHA encoder (float32, centred least squares, fixed-trip-count gravity loop).

The algorithm is the reference one (``docs/hha.md``, Gupta et al. ECCV 2014); what differs is how it is
computed so that float32 is enough and XLA can compile it once for a whole batch:

* Normals are fitted with moments taken relative to each window's centre pixel, in pixel offsets (s = column
  offset, t = row offset). The raw moments of a = X/Z and b = Y/Z are nearly singular (a and b change by ~0.01
  across a window) and their adjugate cancels catastrophically in float32; the centred 3×3 systems are well
  conditioned. The fit w = 1/Z ≈ y1·s + y2·t + y3 is mapped back to the reference plane x1·a + x2·b + x3 = 1/Z
  exactly (x1 = fx·y1, x2 = fy·y2, x3 = y3 − x1·a_c − x2·b_c).
* Window sums are separable correlations with the kernels 1, s, s² along columns and 1, t, t² along rows,
  written as shifted slices so that XLA fuses them into a few loops. The 21×21 windows are assembled from three
  7-wide blocks of the 7×7 sums (Σ over a shifted block of (k + c)^p expands into the block's own moments), which
  costs a fraction of a direct 21-tap pass.
* The gravity estimate is a ``lax.fori_loop`` over 5 + 5 iterations with fixed-shape floor/wall masks, so one
  compiled function serves every image of a batch.

Performance (XLA CPU; measured on a loaded 2-core x86 machine, see ``benchmarks/hha_speed.py``):

* Every stage is materialised with :func:`_materialise` (an identity ``lax.cond``): otherwise XLA fuses each
  stage into all its consumers and recomputes it there (4× the work of the stages; ``optimization_barrier``
  does not prevent this on CPU).
* Maps are zero-padded once and every pass after that is a "valid" correlation: an explicit pad per stage is
  materialised as a separate copy. The 7×7 and 21×21 moments share their column pass; the depth-independent
  cofactors of the mask moments are computed once per call for dense input.
* Gravity runs image by image (``lax.map``), so each image's normals stay in cache through the ten passes, and
  each pass is one matrix-vector product against the precomputed entries of n nᵀ.
* ``jnp.arccos`` (an ``atan2`` that does not vectorise) is replaced by a float32 polynomial of the same accuracy.
"""

from __future__ import annotations

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

# The 21×21 gravity windows are built from three 7×7 blocks: this relies on the two radii being 10 and 3.
assert RADIUS_GRAVITY == 3 * RADIUS_ANGLE + 1 and 2 * RADIUS_ANGLE + 1 == 7


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


# ----------------------------------------------------------------------------------------------------------------------
# Materialisation points.


def _materialise(tree, token: jax.Array):
    """``tree`` unchanged, computed once into memory: a fusion barrier XLA CPU respects.

    Left to itself XLA fuses each window-sum stage into every consumer and recomputes it there: the 7-tap
    row-pass slices of the moments went into each of nx, ny, nz and the validity mask separately (4× the work,
    plus the fit itself 4×), which made the whole encoder ~4× slower than its stages. ``optimization_barrier``
    does not stop this on CPU (it is expanded before fusion); a conditional does, since fusion never crosses its
    boundary. Both branches are the identity, so the predicate only has to be an *unbatched* runtime scalar
    (``token``, taken outside ``vmap``): a batched predicate would turn the cond into a select of both branches.
    """
    return jax.lax.cond(token != 0.5, lambda t: t, lambda t: jax.tree.map(jnp.copy, t), tree)


# ----------------------------------------------------------------------------------------------------------------------
# Window moments.


def _correlate(x: jax.Array, powers: tuple[int, ...], axis: int) -> dict[int, jax.Array]:
    """Σ_{k=-3..3} k^p · x[i + k] along ``axis`` for every p in ``powers``, "valid" part only (6 shorter).

    Plain shifted slices of an array that already carries its zero border: no padding op in between, which XLA
    CPU would otherwise materialise as a separate copy at every stage.
    """
    r = RADIUS_ANGLE
    n = x.shape[axis] - 2 * r
    taps = [jax.lax.slice_in_dim(x, r + k, r + k + n, axis=axis) for k in range(-r, r + 1)]
    outs = {}
    for p in powers:
        acc = taps[r] if p == 0 else None  # k = 0 contributes only to p = 0
        for k in range(1, r + 1):
            if p == 0:
                term = taps[r + k] + taps[r - k]
            elif p % 2:
                term = float(k**p) * (taps[r + k] - taps[r - k])
            else:
                term = float(k**p) * (taps[r + k] + taps[r - k])
            acc = term if acc is None else acc + term
        outs[p] = acc
    return outs


def _widen(m: dict[int, jax.Array], powers: tuple[int, ...], axis: int) -> dict[int, jax.Array]:
    """Moments over 21 taps from moments over 7 taps: blocks centred at offsets −7, 0, +7 ("valid", 14 shorter).

    Σ_{k in block c} k^p x = Σ_{k'=-3..3} (k' + c)^p x[i + c + k'], expanded binomially in the block's own
    moments M_q (q ≤ p) evaluated at i + c.
    """
    w = 2 * RADIUS_ANGLE + 1
    n = next(iter(m.values())).shape[axis] - 2 * w

    def at(x, c):  # x[i + c] on the output domain
        return jax.lax.slice_in_dim(x, w + c, w + c + n, axis=axis)

    binom = {0: (1,), 1: (1, 1), 2: (1, 2, 1)}
    out = {}
    for p in powers:
        total = at(m[p], 0)
        for c in (-w, w):
            block = sum(binom[p][q] * float(c ** (p - q)) * m[q] for q in range(p + 1))
            total = total + at(block, c)
        out[p] = total
    return out


# Border the maps carry into the moment computation: 3 for the 7-tap pass, then 7 more for the 21-wide blocks.
_BORDER = RADIUS_ANGLE + 2 * RADIUS_ANGLE + 1  # = RADIUS_GRAVITY


def _moments(
    x: jax.Array, spec: dict[int, tuple[int, ...]], token: jax.Array
) -> tuple[dict[tuple[int, int], jax.Array], dict[tuple[int, int], jax.Array]]:
    """Window sums Σ s^p t^q x over 7×7 and over 21×21 windows of an ``(H, W)`` map, zero outside the image.

    ``spec`` maps a column power p to the row powers q needed with it (s = column offset, t = row offset).
    The map is zero-padded once by ``_BORDER``; every pass after that is a "valid" correlation that shrinks the
    domain, so the 7-tap column pass is shared by both sizes and no stage pads again. The 7-wide blocks of a
    border window are centred up to 7 pixels outside the image, where their own sums still see image pixels:
    that is what the border is for. Each stage is materialised (see :func:`_materialise`).
    """
    r, e = RADIUS_ANGLE, 2 * RADIUS_ANGLE + 1
    h, w = x.shape
    xp = jnp.pad(x, _BORDER)
    col_powers = tuple(sorted(spec))
    cols = _materialise(_correlate(xp, col_powers, axis=1), token)  # columns −7 … W+7
    cols_wide = _materialise(_widen(cols, col_powers, axis=1), token)  # columns 0 … W
    narrow, wide = {}, {}
    for p, row_powers in spec.items():
        # 7×7: rows −3 … H+3 of the columns 0 … W of the 7-tap column sums.
        c7 = cols[p][_BORDER - r : _BORDER + h + r, e : e + w]
        narrow.update({(p, q): v for q, v in _correlate(c7, row_powers, axis=0).items()})
        rows = _materialise(_correlate(cols_wide[p], row_powers, axis=0), token)  # rows −7 … H+7
        wide.update({(p, q): v for q, v in _widen(rows, row_powers, axis=0).items()})
    return _materialise((narrow, wide), token)


_SINGULAR_RTOL = 1e-5
_MASK_SPEC = {0: (0, 1, 2), 1: (0, 1), 2: (0,)}  # moments of the valid mask: 1, t, t², s, st, s²
_WEIGHT_SPEC = {0: (0, 1), 1: (0,)}  # moments of 1/Z: 1, t, s


def _cofactors(mm: dict[tuple[int, int], jax.Array]):
    """Adjugate of each window's symmetric system [[ss, st, s], [st, tt, t], [s, t, 1]] (mask moments only) and
    whether the system is regular.

    A window defines a plane only if its valid pixels are not collinear (≥ 3 of them, spanning 2-D): otherwise
    the moment matrix is singular and the reference's normal there is rounding noise. The pixel-offset moments
    are small integers, so the singular case is an exact (relative) zero; well-posed windows sit far above.
    Depends on the fit mask alone: for dense input it is computed once per batch.
    """
    s_ss, s_st, s_s = mm[(2, 0)], mm[(1, 1)], mm[(1, 0)]
    s_tt, s_t, s_1 = mm[(0, 2)], mm[(0, 1)], mm[(0, 0)]
    c00 = s_tt * s_1 - s_t * s_t
    c01 = s_s * s_t - s_st * s_1
    c02 = s_st * s_t - s_s * s_tt
    c11 = s_ss * s_1 - s_s * s_s
    c12 = s_st * s_s - s_ss * s_t
    c22 = s_ss * s_tt - s_st * s_st
    det = s_ss * c00 + s_st * c01 + s_s * c02
    regular = det > _SINGULAR_RTOL * s_ss * s_tt * s_1
    return (c00, c01, c02, c11, c12, c22), regular


def _fit_normals(cof, regular, mw, a_c, b_c, z, fx, fy, token):
    """Unit normals (nx, ny, nz maps) of the least-squares plane in each window, oriented away from the camera.

    ``cof``/``regular`` from :func:`_cofactors`, ``mw`` the window moments of 1/Z. Returns the three component
    maps and the mask of windows that define a plane. Components are kept as separate ``(H, W)`` maps rather
    than a stacked ``(H, W, 3)`` array: every step is then a plain elementwise loop that XLA fuses, with no
    strided channel access.
    """
    c00, c01, c02, c11, c12, c22 = cof
    r_s, r_t, r_1 = mw[(1, 0)], mw[(0, 1)], mw[(0, 0)]
    y1 = c00 * r_s + c01 * r_t + c02 * r_1
    y2 = c01 * r_s + c11 * r_t + c12 * r_1
    y3 = c02 * r_s + c12 * r_t + c22 * r_1
    x1 = y1 * fx
    x2 = y2 * fy
    x3 = y3 - x1 * a_c - x2 * b_c
    norm2 = x1 * x1 + x2 * x2 + x3 * x3
    ok = regular & (norm2 > 0)
    inv_norm = jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, norm2, 1.0)), 0.0)
    # Orientation as the reference: first n_z >= 0, then n·p >= 0 with the unmasked point p = z·(a_c, b_c, 1).
    # Both signs combine into one factor; z > 0 drops out of the second test (z = 0 counts as +).
    s1 = jnp.where(x3 < 0, -1.0, 1.0)
    s2 = jnp.where(s1 * (x1 * a_c + x2 * b_c + x3) * z < 0, -1.0, 1.0)
    f = inv_norm * s1 * s2
    return _materialise(((x1 * f, x2 * f, x3 * f), ok), token)


# ----------------------------------------------------------------------------------------------------------------------
# Gravity.


def _gravity(normals: tuple[jax.Array, jax.Array, jax.Array], ok: jax.Array) -> jax.Array:
    """Iterative floor/wall estimate of the down direction (reference ``getYDir``) as a fixed-trip-count loop.

    One image at a time (the caller maps it over the batch, so that an image's normals stay in cache through the
    ten passes). The six distinct entries of n nᵀ are formed once; each iteration then only builds the ±1/0
    floor/wall weights and takes one matrix-vector product: A = Σ_W n nᵀ − Σ_F n nᵀ = (n nᵀ entries) · weights.
    The normals are materialised before the loop, so the product's operands are plain arrays.
    """
    nx, ny, nz = (c.reshape(-1) for c in normals)
    ok = ok.reshape(-1)
    dtype = nx.dtype
    thresholds = np.repeat(np.deg2rad(GRAVITY_THRESHOLDS_DEG), GRAVITY_ITERATIONS)
    cos_t = jnp.asarray(np.cos(thresholds), dtype)
    sin_t = jnp.asarray(np.sin(thresholds), dtype)
    outer = jnp.stack([nx * nx, nx * ny, nx * nz, ny * ny, ny * nz, nz * nz])  # (6, P)
    hi = jax.lax.Precision.HIGHEST

    def step(i, y):
        c = jnp.abs(nx * y[0] + ny * y[1] + nz * y[2])
        floor = ok & (c > cos_t[i])
        wall = ok & (c < sin_t[i])
        weight = wall.astype(dtype) - floor.astype(dtype)
        axx, axy, axz, ayy, ayz, azz = jnp.dot(outer, weight, precision=hi)
        a = jnp.stack([jnp.stack([axx, axy, axz]), jnp.stack([axy, ayy, ayz]), jnp.stack([axz, ayz, azz])])
        _, vecs = jnp.linalg.eigh(a)
        new = vecs[:, 0]  # eigenvalues ascend: the smallest one's eigenvector
        new = new * jnp.where(new @ y < 0, -1.0, 1.0)
        # Nothing selected: A = 0 has no preferred direction, so keep the current estimate. A = 0 means exactly
        # that, without a separate count: tr A = |W| − |F| (unit normals) would force |W| = |F| = k, and then
        # yᵀAy = Σ_W c² − Σ_F c² < k sin²θ − k cos²θ ≤ 0 (θ ≤ 45°) unless k = 0.
        return jnp.where(jnp.any(a != 0), new, y)

    return jax.lax.fori_loop(0, len(thresholds), step, jnp.array([0.0, 1.0, 0.0], dtype))


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


def _camera(depth_m: jax.Array, intrinsics: jax.Array):
    """Valid mask, depth in cm, and X/Z of each column ``(1, W)`` and Y/Z of each row ``(H, 1)``."""
    h, w = depth_m.shape
    dtype = depth_m.dtype
    valid = jnp.isfinite(depth_m) & (depth_m > 0)
    z = jnp.where(valid, depth_m, 0.0) * 100.0  # cm, as the reference
    fx, fy = intrinsics[0, 0], intrinsics[1, 1]
    cx, cy = intrinsics[0, 2], intrinsics[1, 2]
    a_c = (jnp.arange(w, dtype=dtype)[None, :] - cx) / fx  # (1, W): X/Z of each column
    b_c = (jnp.arange(h, dtype=dtype)[:, None] - cy) / fy  # (H, 1): Y/Z of each row
    return valid, z, a_c, b_c


def _normals_one(depth_m: jax.Array, intrinsics: jax.Array, mask_terms, token: jax.Array):
    """One ``(H, W)`` image's 7×7 and 21×21 normals. ``mask_terms``: :func:`_mask_terms` of its fit mask (the
    pixels the normal fits may use); ``token`` is the unbatched scalar of :func:`_materialise`."""
    fit_mask, (cof7, regular7), (cof21, regular21) = mask_terms
    _, z, a_c, b_c = _camera(depth_m, intrinsics)
    inv_z = fit_mask / jnp.where(fit_mask > 0, z, 1.0)
    fx, fy = intrinsics[0, 0], intrinsics[1, 1]
    mw7, mw21 = _moments(inv_z, _WEIGHT_SPEC, token)
    return (
        _fit_normals(cof7, regular7, mw7, a_c, b_c, z, fx, fy, token),
        _fit_normals(cof21, regular21, mw21, a_c, b_c, z, fx, fy, token),
    )


def _mask_terms(fit_mask: jax.Array, token: jax.Array):
    """The fit mask and the cofactors of its 7×7 and 21×21 systems (the depth-independent half of the fits)."""
    mm7, mm21 = _moments(fit_mask, _MASK_SPEC, token)
    return fit_mask, _materialise(_cofactors(mm7), token), _materialise(_cofactors(mm21), token)


def _finish_one(depth_m: jax.Array, intrinsics: jax.Array, normals, ok_angle: jax.Array, g: jax.Array) -> HHAResult:
    """One image's height, angle and quantised channels from its 7×7 normals and its gravity vector."""
    dtype = depth_m.dtype
    valid, z, a_c, b_c = _camera(depth_m, intrinsics)
    nx, ny, nz = normals

    rotate = jnp.arccos(jnp.clip(g[1], -1.0, 1.0)) > np.deg2rad(ROTATION_SKIP_DEG)
    up = jnp.where(rotate, g, jnp.array([0.0, 1.0, 0.0], dtype))  # (Rᵀp)_y = (R y0)·p = g·p, R y0 = g (Rodrigues)
    height = -z * (a_c * up[0] + b_c * up[1] + up[2])
    y_min = jnp.min(jnp.where(valid, height, jnp.inf))
    y_min = jnp.where(y_min > FLOOR_RULE_CM, FLOOR_FALLBACK_CM, y_min)
    height = height - y_min

    cos_angle = jnp.clip(nx * g[0] + ny * g[1] + nz * g[2], -1.0, 1.0)
    angle = jnp.where(ok_angle, jnp.degrees(_arccos(cos_angle)), ANGLE_NAN_DEG)
    disparity = DISPARITY_NUMERATOR / jnp.maximum(z, DISPARITY_MIN_CM)

    def quantise(x):  # round half to even (as np.rint), cap at 255; invalid depth → 0
        return jnp.where(valid, jnp.clip(jnp.round(x), 0, 255), 0).astype(jnp.uint8)

    hha = jnp.stack([quantise(disparity), quantise(height), quantise(angle + ANGLE_OFFSET)], axis=-1)
    normals = jnp.stack([nx, ny, nz], axis=-1)
    return HHAResult(hha, normals, ok_angle, g, jnp.where(valid, height, 0.0), angle, valid)


def _encode_dense(depth_m: jax.Array, intrinsics: jax.Array, token: jax.Array) -> HHAResult:
    """Every pixel valid and present: the fit mask is shared by the whole batch, and vmap leaves an unbatched
    input unbatched, so its window moments (half of the normal-fitting work) are computed once per call instead
    of once per image."""
    fit_mask = jnp.ones(depth_m.shape[1:], depth_m.dtype)
    mask_terms = _mask_terms(fit_mask, token)
    return _encode_masked(depth_m, intrinsics, mask_terms, None, token)


def _encode_missing(depth_m: jax.Array, intrinsics: jax.Array, fit_mask: jax.Array, token: jax.Array) -> HHAResult:
    """Some pixel missing: one fit mask per image."""
    mask_terms = jax.vmap(_mask_terms, in_axes=(0, None))(fit_mask.astype(depth_m.dtype), token)
    return _encode_masked(depth_m, intrinsics, mask_terms, 0, token)


def _encode_masked(depth_m, intrinsics, mask_terms, mask_axis, token) -> HHAResult:
    (n_angle, ok_angle), n_gravity = jax.vmap(_normals_one, in_axes=(0, 0, mask_axis, None))(
        depth_m, intrinsics, mask_terms, token
    )
    # Gravity image by image (a loop over the batch, not vmap): each image's normals then stay in cache through
    # the ten passes, instead of every pass streaming the whole batch's normals through memory.
    g = jax.lax.map(lambda a: _gravity(*a), n_gravity)
    return jax.vmap(_finish_one)(depth_m, intrinsics, n_angle, ok_angle, g)


@jax.jit
def _encode_batch(
    depth_m: jax.Array, intrinsics: jax.Array, raw_depth_m: jax.Array | None, depth_range: jax.Array
) -> HHAResult:
    """``depth_m (B, H, W)`` metres, ``intrinsics (B, 3, 3)``, ``raw_depth_m (B, H, W)`` metres or ``None``,
    ``depth_range (2,)``: the inclusive valid depth range [min, max] in metres.

    Every decision about the data is taken here, on traced values, so the result is the same eagerly and under a
    caller's ``jit``/``vmap``:

    * depth outside the range (NaN and ±inf included) becomes NaN, i.e. missing for everything downstream;
    * an image whose intrinsics are non-finite or have fx ≤ 0 or fy ≤ 0 is entirely missing (its matrix is
      replaced by the identity so that no NaN leaks into the outputs);
    * the shared-mask fast path runs only when every pixel of the batch is valid and present (``lax.cond``,
      which executes one branch; under a caller's ``vmap`` it becomes a select of both, each image still getting
      its own branch's result).
    """
    dtype = depth_m.dtype
    lo, hi = depth_range[0], depth_range[1]
    fx, fy = intrinsics[:, 0, 0], intrinsics[:, 1, 1]
    k_ok = jnp.all(jnp.isfinite(intrinsics), axis=(1, 2)) & (fx > 0) & (fy > 0)
    intrinsics = jnp.where(k_ok[:, None, None], intrinsics, jnp.eye(3, dtype=dtype))
    valid = (depth_m >= lo) & (depth_m <= hi) & k_ok[:, None, None]  # NaN compares False
    depth_m = jnp.where(valid, depth_m, jnp.nan)
    fit_mask = valid if raw_depth_m is None else valid & (raw_depth_m >= lo) & (raw_depth_m <= hi)
    token = jnp.sum(depth_m.reshape(-1)[:1])  # any unbatched runtime scalar (see _materialise); 0 if empty
    return jax.lax.cond(
        jnp.all(fit_mask),
        lambda d, k, m, t: _encode_dense(d, k, t),
        _encode_missing,
        depth_m,
        intrinsics,
        fit_mask,
        token,
    )
