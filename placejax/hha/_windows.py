"""Window moments and least-squares plane fits of the HHA encoder (7×7 and 21×21 windows, float32).

The normals are fitted with moments taken relative to each window's centre pixel, in pixel offsets (s = column
offset, t = row offset). The raw moments of a = X/Z and b = Y/Z are nearly singular (a and b change by ~0.01
across a window) and their adjugate cancels catastrophically in float32; the centred 3×3 systems are well
conditioned. The fit w = 1/Z ≈ y1·s + y2·t + y3 is mapped back to the reference plane x1·a + x2·b + x3 = 1/Z
exactly (x1 = fx·y1, x2 = fy·y2, x3 = y3 − x1·a_c − x2·b_c).

Window sums are separable correlations with the kernels 1, s, s² along columns and 1, t, t² along rows, written
as shifted slices so that XLA fuses them into a few loops. The 21×21 windows are assembled from three 7-wide
blocks of the 7×7 sums (Σ over a shifted block of (k + c)^p expands into the block's own moments).

Where every pixel of an image may be used (dense depth), a window is the rectangle where it overlaps the image,
the offsets' moments factor into a column part times a row part, and the 3×3 solve reduces to closed-form
per-column and per-row coefficients computed from the image size alone (:func:`_dense_axis`): no moments of the
mask and no adjugate per pixel.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from placejax.hha._constants import RADIUS_ANGLE, RADIUS_GRAVITY

# The 21×21 gravity windows are built from three 7×7 blocks: this relies on the two radii being 10 and 3.
assert RADIUS_GRAVITY == 3 * RADIUS_ANGLE + 1
assert 2 * RADIUS_ANGLE + 1 == 7


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


def window_sums(x: jax.Array, powers: tuple[int, ...], axis: int) -> dict[int, jax.Array]:
    """Σ_{k=-3..3} k^p · x[i + k] along ``axis`` for every p in ``powers``, "valid" part only: ``x`` of any shape,
    each result of its shape but 6 shorter along ``axis`` (the 7-wide windows of the angle channel's normals).

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
    cols = _materialise(window_sums(xp, col_powers, axis=1), token)  # columns −7 … W+7
    cols_wide = _materialise(_widen(cols, col_powers, axis=1), token)  # columns 0 … W
    narrow, wide = {}, {}
    for p, row_powers in spec.items():
        # 7×7: rows −3 … H+3 of the columns 0 … W of the 7-tap column sums.
        c7 = cols[p][_BORDER - r : _BORDER + h + r, e : e + w]
        narrow.update({(p, q): v for q, v in window_sums(c7, row_powers, axis=0).items()})
        rows = _materialise(window_sums(cols_wide[p], row_powers, axis=0), token)  # rows −7 … H+7
        wide.update({(p, q): v for q, v in _widen(rows, row_powers, axis=0).items()})
    return _materialise((narrow, wide), token)


# ----------------------------------------------------------------------------------------------------------------------
# Plane fits.

_SINGULAR_RTOL = 1e-5
MASK_SPEC = {0: (0, 1, 2), 1: (0, 1), 2: (0,)}  # moments of the valid mask: 1, t, t², s, st, s²
WEIGHT_SPEC = {0: (0, 1), 1: (0,)}  # moments of 1/Z: 1, t, s


def _cofactors(mm: dict[tuple[int, int], jax.Array]):
    """Adjugate of each window's symmetric system [[ss, st, s], [st, tt, t], [s, t, 1]] (mask moments only) and
    whether the system is regular.

    A window defines a plane only if its valid pixels are not collinear (≥ 3 of them, spanning 2-D): otherwise
    the moment matrix is singular and the reference's normal there is rounding noise. The pixel-offset moments
    are small integers, so the singular case is an exact (relative) zero; well-posed windows sit far above.
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


def mask_terms(fit_mask: jax.Array, token: jax.Array):
    """Cofactors and regularity of the 7×7 and 21×21 systems of one ``(H, W)`` fit mask (the half of the fits
    that does not depend on depth): ``((cof7, regular7), (cof21, regular21))``."""
    mm7, mm21 = _moments(fit_mask, MASK_SPEC, token)
    return _materialise(_cofactors(mm7), token), _materialise(_cofactors(mm21), token)


def _plane(y1, y2, y3, camera) -> jax.Array:
    """``(3, H, W)``: the plane x1·a + x2·b + x3 = 1/Z (unnormalised normal x) of the fit y1·s + y2·t + y3 = 1/Z
    in pixel offsets; ``camera`` = (a_c (1, W), b_c (H, 1), z (H, W) cm, fx, fy).

    One stacked array, so that XLA CPU (which does not fuse several outputs into one loop) computes the fit in a
    single loop whose three planes share nothing but the moments they read.
    """
    a_c, b_c, _, fx, fy = camera
    x1 = y1 * fx
    x2 = y2 * fy
    x3 = y3 - x1 * a_c - x2 * b_c
    return jnp.stack([x1, x2, x3])


def inverse_norm(x: jax.Array, regular) -> jax.Array:
    """1/|x| of the planes of :func:`_plane` where the window defines a plane (``regular`` and x ≠ 0), else 0."""
    norm2 = x[0] * x[0] + x[1] * x[1] + x[2] * x[2]
    ok = regular & (norm2 > 0)
    return jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, norm2, 1.0)), 0.0)


def unit_normals(x: jax.Array, inv_norm: jax.Array, camera) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Unit normals (nx, ny, nz) of the planes ``x``, oriented away from the camera; 0 where ``inv_norm`` is 0.

    Orientation as the reference: first n_z >= 0, then n·p >= 0 with the unmasked point p = z·(a_c, b_c, 1).
    Both signs combine into one factor; z > 0 drops out of the second test (z = 0 counts as +).
    """
    a_c, b_c, z, _, _ = camera
    x1, x2, x3 = x[0], x[1], x[2]
    s1 = jnp.where(x3 < 0, -1.0, 1.0)
    s2 = jnp.where(s1 * (x1 * a_c + x2 * b_c + x3) * z < 0, -1.0, 1.0)
    f = inv_norm * s1 * s2
    return x1 * f, x2 * f, x3 * f


def fit_planes(cof, regular, mw, camera, token):
    """Planes (:func:`_plane`) of the least-squares fits in each window and the mask of windows whose system is
    regular, from the cofactors of :func:`mask_terms` and ``mw``, the window moments of 1/Z."""
    c00, c01, c02, c11, c12, c22 = cof
    r_s, r_t, r_1 = mw[(1, 0)], mw[(0, 1)], mw[(0, 0)]
    y1 = c00 * r_s + c01 * r_t + c02 * r_1
    y2 = c01 * r_s + c11 * r_t + c12 * r_1
    y3 = c02 * r_s + c12 * r_t + c22 * r_1
    return _materialise(_plane(y1, y2, y3, camera), token), regular


@functools.cache
def _dense_axis(n: int, r: int) -> tuple[np.ndarray, ...]:
    """Per-position coefficients of a full-mask fit along one image axis of length ``n`` (window radius ``r``).

    With every pixel valid, the window at position i covers the offsets k in [−r, r] with 0 ≤ i + k < n; its
    moments are M0 = #k, M1 = Σk, M2 = Σk², and D = M0·M2 − M1² > 0 unless the window spans a single pixel.
    Returns float64 arrays ``(slope_x, slope_1, inv_m0, mean, regular_part)``: the slope along this axis of the
    window's least-squares plane is (slope_x · Σk·w − slope_1 · Σw) / M0' (M0' the other axis's count),
    the intercept subtracts mean = M1/M0 times the slope, and regular_part = D / (M0·M2) enters the
    singularity test of :func:`_cofactors` as a product of the two axes' parts.
    """
    k = np.arange(-r, r + 1)
    inside = (np.arange(n)[:, None] + k[None, :] >= 0) & (np.arange(n)[:, None] + k[None, :] < n)
    m0, m1, m2 = (np.sum(inside * k[None, :] ** p, axis=1).astype(np.float64) for p in (0, 1, 2))
    d = m0 * m2 - m1 * m1
    safe = np.where(d > 0, d, 1.0)
    slope_x = np.where(d > 0, m0 / safe, 0.0)
    slope_1 = np.where(d > 0, m1 / safe, 0.0)
    regular_part = np.where(d > 0, d / np.where(m2 > 0, m0 * m2, 1.0), 0.0)
    return slope_x, slope_1, 1.0 / m0, m1 / m0, regular_part


def fit_planes_dense(mw, r: int, camera, token):
    """:func:`fit_planes` for an image whose every pixel is valid, window radius ``r``.

    Over a rectangle the offsets' cross moment factors (Σst = Σs·Σt / #), so the system's solution is, up to a
    positive factor per window that the normalisation removes, y1 = (C0·Σsw − C1·Σw) / (R0·Dc),
    y2 = (R0·Σtw − R1·Σw) / (C0·Dr), y3 = Σw / (C0·R0) − (C1/C0)·y1 − (R1/R0)·y2 (C, R: the column and row
    moments of :func:`_dense_axis`). Everything but the three moment maps is a per-column or per-row constant.
    """
    h, w = mw[(0, 0)].shape
    dtype = mw[(0, 0)].dtype
    cx, c1, c_inv0, c_mean, c_reg = _dense_axis(w, r)
    rx, r1, r_inv0, r_mean, r_reg = _dense_axis(h, r)
    col = [jnp.asarray(v[None, :], dtype) for v in (cx, c1, c_inv0, c_mean)]
    row = [jnp.asarray(v[:, None], dtype) for v in (rx, r1, r_inv0, r_mean)]
    r_s, r_t, r_1 = mw[(1, 0)], mw[(0, 1)], mw[(0, 0)]
    y1 = (col[0] * r_s - col[1] * r_1) * row[2]
    y2 = (row[0] * r_t - row[1] * r_1) * col[2]
    y3 = r_1 * col[2] * row[2] - col[3] * y1 - row[3] * y2
    regular = np.outer(r_reg, c_reg) > _SINGULAR_RTOL
    regular = True if regular.all() else jnp.asarray(regular)  # static: depends on the image size alone
    return _materialise(_plane(y1, y2, y3, camera), token), regular
