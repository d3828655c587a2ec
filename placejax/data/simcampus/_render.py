"""The jitted, vmapped ray caster of SimCampus.

One primary ray per pixel, first hit found exactly against analytic primitives (oriented boxes, vertical
cylinders, yaw-oriented ellipsoids), a sum-of-waves height field (bracketing march + false-position
refinement) and a far backdrop ring; then Lambert shading, procedural textures, haze, exposure/white balance
and sensor noise.

Speed comes from per-column culling: every image column's rays lie in one plane through the camera centre,
so for each column and primitive kind only the `K` primitives whose bounding sphere meets that plane (nearest
first, via `lax.top_k`) are intersected. All shapes are static; float32 throughout; deterministic.

Camera convention: OpenCV (x right, y down, z forward), 0-based pixel centres (pixel (row i, col j) is the ray
through u = j, v = i). Ray directions are scaled so that their camera-z component is 1, which makes the ray
parameter of a hit its z-depth directly.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

# Depth (m) reported for sky pixels (flagged separately in the sky mask).
SKY_DEPTH = 1000.0
"""Depth in metres reported for sky pixels (they are also flagged in the sky mask)."""
# Radius (m) of the backdrop ring (far tree line / hills) centred on the campus.
BACKDROP_RADIUS = 500.0
# Primitives intersected per image column and kind (culling budget): boxes, cylinders, ellipsoids.
K_BOX, K_CYL, K_ELL = 8, 8, 12
# Terrain march: z-depth samples (m), geometric so that near ground is resolved finely; then refinement.
_MARCH_T = np.concatenate([[0.0], np.geomspace(0.6, 650.0, 15)]).astype(np.float32)
_REFINE_STEPS = 4
_INF = 1e30
_EPS_T = 1e-3


class Geometry(NamedTuple):
    """Scene geometry (float32 device arrays; fixed capacities so one compiled renderer serves every scene).

    Attributes:
        box: ``(NB, 8)`` cx, cy, cz, hx, hy, hz, cos(yaw), sin(yaw).
        cyl: ``(NC, 5)`` cx, cy, z0, z1, r.
        ell: ``(NE, 8)`` cx, cy, cz, rx, ry, rz, cos(yaw), sin(yaw).
        box_sphere, cyl_sphere, ell_sphere: ``(N, 4)`` bounding spheres (cx, cy, cz, radius) for culling.
        ell_unit: ``(NE, 8)`` cx, cy, cz and the world-to-unit-sphere map (cos/rx, sin/rx, -sin/ry, cos/ry,
            1/rz), precomputed because XLA recomputes per-primitive factors for every pixel they broadcast to.
        terrain: ``(T, 4)`` amplitude, kx, ky, phase of the height field.
        matmap: ``int32 (M, M)`` ground material ids, ``matmap[iy, ix]`` for 0.5 m texels from ``-map_half``.
        map_half: ``()`` half extent (m) of the material map.
        backdrop: ``(P, 3)`` silhouette terms over azimuth (amplitude m, frequency, phase).
    """

    box: jax.Array
    cyl: jax.Array
    ell: jax.Array
    box_sphere: jax.Array
    cyl_sphere: jax.Array
    ell_sphere: jax.Array
    ell_unit: jax.Array
    terrain: jax.Array
    matmap: jax.Array
    map_half: jax.Array
    backdrop: jax.Array


class Look(NamedTuple):
    """Scene appearance (display-space RGB in [0, 1]); may carry a leading batch axis (one look per frame).

    Attributes:
        box: ``(NB, 13)`` wall rgb, window rgb, roof rgb, period_u, period_v, fill_u, fill_v (m, m, -, -).
        cyl: ``(NC, 7)`` rgb, alternate rgb, texture period (m).
        ell: ``(NE, 7)`` rgb, alternate rgb, texture period (m).
        ground: ``(n_materials, 7)`` base rgb, speckle rgb, speckle period (m), per ground material.
        sky_zenith, sky_horizon: ``(3,)`` sky gradient.
        sun_dir: ``(3,)`` unit vector towards the sun (world frame).
        sun_rgb, ambient_rgb: ``(3,)`` direct and ambient light.
        fog_rgb: ``(3,)`` haze colour; fog_dist: ``()`` e-folding distance (m).
        gain: ``(3,)`` exposure x white balance.
        noise: ``()`` sensor noise amplitude (std, in [0, 1] units).
        backdrop_rgb: ``(3,)`` far tree line / hills colour.
    """

    box: jax.Array
    cyl: jax.Array
    ell: jax.Array
    ground: jax.Array
    sky_zenith: jax.Array
    sky_horizon: jax.Array
    sun_dir: jax.Array
    sun_rgb: jax.Array
    ambient_rgb: jax.Array
    fog_rgb: jax.Array
    fog_dist: jax.Array
    gain: jax.Array
    noise: jax.Array
    backdrop_rgb: jax.Array


def bounding_spheres(box: np.ndarray, cyl: np.ndarray, ell: np.ndarray) -> tuple[np.ndarray, ...]:
    """Bounding spheres ``(N, 4)`` of the three primitive tables (numpy, built once per scene)."""
    bs = np.concatenate([box[:, :3], np.linalg.norm(box[:, 3:6], axis=1, keepdims=True)], 1)
    half = (cyl[:, 3] - cyl[:, 2]) / 2
    cs = np.stack([cyl[:, 0], cyl[:, 1], (cyl[:, 2] + cyl[:, 3]) / 2, np.hypot(half, cyl[:, 4])], 1)
    es = np.concatenate([ell[:, :3], ell[:, 3:6].max(1, keepdims=True)], 1)
    return bs, cs, es


def world_from_camera(yaw: jax.Array, pitch: jax.Array, roll: jax.Array) -> jax.Array:
    """Rotation ``(3, 3)`` taking OpenCV camera axes to world axes.

    Yaw turns the heading counter-clockwise from +x (east), pitch raises the optical axis, roll turns the
    image clockwise about the optical axis as seen by the camera.
    """
    cy_, sy_ = jnp.cos(yaw), jnp.sin(yaw)
    cp, sp = jnp.cos(pitch), jnp.sin(pitch)
    cr, sr = jnp.cos(roll), jnp.sin(roll)
    fwd = jnp.stack([cy_ * cp, sy_ * cp, sp])
    left0 = jnp.stack([-sy_, cy_, jnp.zeros_like(yaw)])
    up0 = jnp.stack([-sp * cy_, -sp * sy_, cp])
    left = cr * left0 + sr * up0
    up = -sr * left0 + cr * up0
    # OpenCV: x right = -left, y down = -up, z forward.
    return jnp.stack([-left, -up, fwd], axis=1)


def _hash01(a: jax.Array, b: jax.Array, c: jax.Array) -> jax.Array:
    """Deterministic hash of three int32 lattice coordinates to a float32 in [0, 1)."""
    h = (
        a.astype(jnp.uint32) * jnp.uint32(0x8DA6B343)
        ^ b.astype(jnp.uint32) * jnp.uint32(0xD8163841)
        ^ c.astype(jnp.uint32) * jnp.uint32(0xCB1AB31F)
    )
    h = h ^ (h >> 13)
    h = h * jnp.uint32(0x85EBCA6B)
    h = h ^ (h >> 16)
    h = h * jnp.uint32(0xC2B2AE35)
    h = h ^ (h >> 15)
    return (h >> 8).astype(jnp.float32) * jnp.float32(1.0 / (1 << 24))


def _cell_noise(px, py, pz, period):
    inv = 1.0 / period
    return _hash01(
        jnp.floor(px * inv).astype(jnp.int32),
        jnp.floor(py * inv).astype(jnp.int32),
        jnp.floor(pz * inv).astype(jnp.int32),
    )


def wave(x):
    """Cheap smooth periodic stand-in for sin: piecewise parabola, period 2*pi, range [-1, 1], C1.

    The height field is evaluated ~20 times per ray; XLA's CPU sin costs several times this, and the
    terrain only needs to be smooth, not sinusoidal. Works on numpy and jax arrays alike.
    """
    u = x * (0.5 / np.pi)
    u = u - (u + 0.5) // 1.0
    return 8.0 * u * (1.0 - 2.0 * abs(u))


def wave_grad(x):
    """Derivative of `wave`."""
    u = x * (0.5 / np.pi)
    u = u - (u + 0.5) // 1.0
    return (4.0 / np.pi) * (1.0 - 4.0 * abs(u))


def _terrain(terrain: jax.Array, x: jax.Array, y: jax.Array) -> jax.Array:
    h = jnp.zeros_like(x)
    for i in range(terrain.shape[0]):  # static, T = 4: unrolled so that XLA fuses the sum
        a, kx, ky, ph = terrain[i, 0], terrain[i, 1], terrain[i, 2], terrain[i, 3]
        h = h + a * wave(kx * x + ky * y + ph)
    return h


def _terrain_grad(terrain, x, y):
    gx = jnp.zeros_like(x)
    gy = jnp.zeros_like(x)
    for i in range(terrain.shape[0]):
        a, kx, ky, ph = terrain[i, 0], terrain[i, 1], terrain[i, 2], terrain[i, 3]
        c = a * wave_grad(kx * x + ky * y + ph)
        gx, gy = gx + c * kx, gy + c * ky
    return gx, gy


def _cull(sphere: jax.Array, o: jax.Array, nrm: jax.Array, fwd: jax.Array, k: int) -> jax.Array:
    """Indices ``(W, k)`` of the `k` nearest primitives whose bounding sphere meets each column's plane."""
    rel = sphere[:, :3] - o[None, :]  # (N, 3)
    r = sphere[:, 3]
    dist = jnp.sqrt((rel * rel).sum(1))
    front = rel @ fwd > -r
    plane = jnp.abs(nrm @ rel.T)  # (W, N)
    ok = (plane <= r[None, :]) & front[None, :]
    score = jnp.where(ok, -(dist - r)[None, :], -1e9 - dist[None, :])
    return jax.lax.top_k(score, k)[1]


def _first_hit(t: jax.Array, idx: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Nearest hit over the K candidates ``t (K, H, W)``: t ``(H, W)`` and global primitive index ``(H, W)``.

    The candidate slot is packed into the low mantissa bits of t (positive floats order like their int32
    bit patterns), so one fused min-reduction yields both; an argmin + gather costs several times more on
    CPU. The depth error is below 2**-19 relative for K <= 16.
    """
    k = t.shape[0]
    bits = max(1, int(np.ceil(np.log2(k))))
    mask = (1 << bits) - 1
    slot = jnp.arange(k, dtype=jnp.int32)[:, None, None]
    packed = (jax.lax.bitcast_convert_type(t, jnp.int32) & ~mask) | slot
    best = jnp.min(packed, axis=0)
    tmin = jax.lax.bitcast_convert_type(best & ~mask, jnp.float32)
    tmin = jnp.where(tmin > 0.5 * _INF, _INF, tmin)  # packing lowered the no-hit value a little
    arg = best & mask
    gidx = jnp.sum(jnp.where(arg[None] == slot, idx.T[:, None, :], 0), axis=0)
    return tmin, gidx


def _hit_boxes(g, o, dx, dy, dz):
    cx, cy, cz, hx, hy, hz, c, s = (g[:, None, :, i] for i in range(8))  # (K, 1, W)
    ox, oy, oz = o[0] - cx, o[1] - cy, o[2] - cz
    lox, loy = c * ox + s * oy, -s * ox + c * oy
    ldx, ldy = c * dx + s * dy, -s * dx + c * dy  # (K, H, W)
    tiny = 1e-12
    ldx = jnp.where(jnp.abs(ldx) < tiny, tiny, ldx)
    ldy = jnp.where(jnp.abs(ldy) < tiny, tiny, ldy)
    ldz = jnp.where(jnp.abs(dz) < tiny, tiny, dz)
    ix, iy, iz = 1.0 / ldx, 1.0 / ldy, 1.0 / ldz
    ax, bx = (-hx - lox) * ix, (hx - lox) * ix
    ay, by = (-hy - loy) * iy, (hy - loy) * iy
    az, bz = (-hz - oz) * iz, (hz - oz) * iz
    tn = jnp.maximum(jnp.maximum(jnp.minimum(ax, bx), jnp.minimum(ay, by)), jnp.minimum(az, bz))
    tf = jnp.minimum(jnp.minimum(jnp.maximum(ax, bx), jnp.maximum(ay, by)), jnp.maximum(az, bz))
    return jnp.where((tn <= tf) & (tn > _EPS_T), tn, _INF)


def _hit_cyls(g, o, dx, dy, dz):
    cx, cy, z0, z1, r = (g[:, None, :, i] for i in range(5))
    ox, oy = o[0] - cx, o[1] - cy
    a = dx * dx + dy * dy
    b = ox * dx + oy * dy
    cc = ox * ox + oy * oy - r * r
    disc = b * b - a * cc
    t = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.maximum(a, 1e-12)
    zh = o[2] + t * dz
    return jnp.where((disc > 0) & (t > _EPS_T) & (zh >= z0) & (zh <= z1), t, _INF)


def _hit_ells(g, o, dx, dy, dz):
    """Ray / ellipsoid first hits; `g` rows are `Geometry.ell_unit` (the map to the unit sphere)."""
    cx, cy, cz, axx, axy, ayx, ayy, irz = (g[:, None, :, i] for i in range(8))
    ox, oy, oz = o[0] - cx, o[1] - cy, o[2] - cz
    lox, loy, loz = axx * ox + axy * oy, ayx * ox + ayy * oy, oz * irz
    ldx, ldy, ldz = axx * dx + axy * dy, ayx * dx + ayy * dy, dz * irz
    a = ldx * ldx + ldy * ldy + ldz * ldz
    b = lox * ldx + loy * ldy + loz * ldz
    cc = lox * lox + loy * loy + loz * loz - 1.0
    disc = b * b - a * cc
    num = -b - jnp.sqrt(jnp.maximum(disc, 0.0))
    # Test on the numerator (a > 0) so that the division has a single consumer and fuses into the min.
    return jnp.where((disc > 0) & (num > _EPS_T * a), num / a, _INF)


def ellipsoid_unit_map(ell: np.ndarray) -> np.ndarray:
    """`Geometry.ell_unit` rows from ellipsoid rows ``(N, 8)`` (numpy, once per scene)."""
    c, s = ell[:, 6], ell[:, 7]
    irx, iry, irz = 1.0 / ell[:, 3], 1.0 / ell[:, 4], 1.0 / ell[:, 5]
    return np.stack([ell[:, 0], ell[:, 1], ell[:, 2], c * irx, s * irx, -s * iry, c * iry, irz], 1)


def _hit_terrain(terrain, o, dx, dy, dz):
    """First ground hit: march the z-depth samples `_MARCH_T` to bracket the first crossing, then refine.

    Both phases are `fori_loop`s over (W, H) arrays: a loop body is one fusion, so XLA materialises each
    step once instead of re-evaluating the height field inside every consumer (which it does when the march is
    written as one big elementwise expression).
    """
    ts = jnp.asarray(_MARCH_T)
    f = lambda t: o[2] + t * dz - _terrain(terrain, o[0] + t * dx, o[1] + t * dy)
    zero = jnp.zeros_like(dx)

    def march(i, st):
        t_prev, f_prev, ta, fa, tb, fb, found = st
        t = ts[i]
        ft = f(t)
        new = (ft < 0) & ~found
        ta, fa = jnp.where(new, t_prev, ta), jnp.where(new, f_prev, fa)
        tb, fb = jnp.where(new, t, tb), jnp.where(new, ft, fb)
        return t + zero, ft, ta, fa, tb, fb, found | new

    f0 = f(zero)
    st = (zero, f0, zero, f0, zero, f0, jnp.zeros(dx.shape, bool))
    _, _, ta, fa, tb, fb, found = jax.lax.fori_loop(1, len(_MARCH_T), march, st)

    # False position keeps the bracket [ta, tb] with f(ta) > 0 > f(tb); the terrain is smooth at the
    # sample spacing, so a few steps reach centimetre accuracy on near ground.
    def refine(_, st):
        ta, fa, tb, fb, _ = st
        tm = ta - fa * (tb - ta) / jnp.minimum(fb - fa, -1e-9)
        fm = f(tm)
        pos = fm > 0
        return (
            jnp.where(pos, tm, ta),
            jnp.where(pos, fm, fa),
            jnp.where(pos, tb, tm),
            jnp.where(pos, fb, fm),
            tm,
        )

    tm = jax.lax.fori_loop(0, _REFINE_STEPS, refine, (ta, fa, tb, fb, tb))[4]
    return jnp.where(found, tm, _INF)


def _hit_backdrop(profile, o, dx, dy, dz):
    a = dx * dx + dy * dy
    b = o[0] * dx + o[1] * dy
    cc = o[0] * o[0] + o[1] * o[1] - BACKDROP_RADIUS**2
    t = (-b + jnp.sqrt(jnp.maximum(b * b - a * cc, 0.0))) / jnp.maximum(a, 1e-12)
    az = jnp.arctan2(o[1] + t * dy, o[0] + t * dx)
    top = jnp.full_like(az, 6.0)
    for i in range(profile.shape[0]):
        top = top + profile[i, 0] * jnp.maximum(wave(profile[i, 1] * az + profile[i, 2]), -0.3)
    return jnp.where((o[2] + t * dz < top) & (a > 1e-12), t, _INF)


# Shading gathers one row per ray from a table stacking [geometry | look] of all three primitive kinds
# (21 columns: the widest, boxes, has 8 + 13); one gather instead of six is the cheaper layout on CPU.
_ROW = 21


def _shade_box(g, px, py, pz):
    cx, cy, cz, hx, hy, hz, c, s = (g[..., i] for i in range(8))
    lk = g[..., 8:]
    lx, ly, lz = c * (px - cx) + s * (py - cy), -s * (px - cx) + c * (py - cy), pz - cz
    ax, ay, az = jnp.abs(lx) / hx, jnp.abs(ly) / hy, jnp.abs(lz) / hz
    top = az >= jnp.maximum(ax, ay)
    xface = ax >= ay
    sx, sy = jnp.sign(lx), jnp.sign(ly)
    nx = jnp.where(top, 0.0, jnp.where(xface, c * sx, -s * sy))
    ny = jnp.where(top, 0.0, jnp.where(xface, s * sx, c * sy))
    nz = jnp.where(top, 1.0, 0.0)
    u = jnp.where(xface, ly + hy, lx + hx)
    v = lz + hz
    fu = u / lk[..., 9]
    fv = v / lk[..., 10]
    window = ((fu - jnp.floor(fu)) < lk[..., 11]) & ((fv - jnp.floor(fv)) < lk[..., 12]) & (v > 0.8)
    rgb = [jnp.where(top, lk[..., 6 + i], jnp.where(window, lk[..., 3 + i], lk[..., i])) for i in range(3)]
    return rgb, (nx, ny, nz)


def _mix(look, w):
    return [look[..., i] * (1.0 - w) + look[..., 3 + i] * w for i in range(3)]


def _shade_cyl(g, px, py, pz):
    lk = g[..., 5:12]
    nx, ny = (px - g[..., 0]) / g[..., 4], (py - g[..., 1]) / g[..., 4]
    w = _cell_noise(px, py, pz, lk[..., 6])
    return _mix(lk, w), (nx, ny, jnp.zeros_like(nx))


def _shade_ell(g, px, py, pz):
    cx, cy, cz, rx, ry, rz, c, s = (g[..., i] for i in range(8))
    lk = g[..., 8:15]
    lx, ly, lz = c * (px - cx) + s * (py - cy), -s * (px - cx) + c * (py - cy), pz - cz
    gx, gy, gz = lx / (rx * rx), ly / (ry * ry), lz / (rz * rz)
    inv = jax.lax.rsqrt(gx * gx + gy * gy + gz * gz + 1e-20)
    nx, ny, nz = (c * gx - s * gy) * inv, (s * gx + c * gy) * inv, gz * inv
    w = _cell_noise(px, py, pz, lk[..., 6])
    return _mix(lk, w), (nx, ny, nz)


def _shade_ground(geo: Geometry, look_ground, px, py, pz):
    gx, gy = _terrain_grad(geo.terrain, px, py)
    inv = jax.lax.rsqrt(gx * gx + gy * gy + 1.0)
    m = geo.matmap.shape[0]
    res = 2.0 * geo.map_half / m
    ix = jnp.clip(jnp.floor((px + geo.map_half) / res).astype(jnp.int32), 0, m - 1)
    iy = jnp.clip(jnp.floor((py + geo.map_half) / res).astype(jnp.int32), 0, m - 1)
    inside = (jnp.abs(px) < geo.map_half) & (jnp.abs(py) < geo.map_half)
    mat = jnp.where(inside, geo.matmap[iy, ix], 0)
    # A handful of materials: selects beat a gather.
    lk = [
        functools.reduce(
            lambda acc, j: jnp.where(mat == j, look_ground[j, c], acc),
            range(1, look_ground.shape[0]),
            jnp.full(px.shape, look_ground[0, c]),
        )
        for c in range(7)
    ]
    lk = jnp.stack(lk, -1)
    # Two octaves of cell noise: one octave reads as a checkerboard on near ground.
    zero = jnp.zeros_like(pz)
    w = 0.6 * _cell_noise(px, py, zero, lk[..., 6]) + 0.4 * _cell_noise(px + 0.37, py, zero, lk[..., 6] * 0.31)
    return _mix(lk, w), (-gx * inv, -gy * inv, inv)


def _row_table(geo: Geometry, look: Look) -> jax.Array:
    pad = lambda a: jnp.pad(a, ((0, 0), (0, _ROW - a.shape[1])))
    return jnp.concatenate(
        [
            jnp.concatenate([geo.box, look.box], 1),
            pad(jnp.concatenate([geo.cyl, look.cyl], 1)),
            pad(jnp.concatenate([geo.ell, look.ell], 1)),
        ]
    )


def _rays(pose6: jax.Array, kmat: jax.Array, hw):
    """Camera centre ``(3,)``, rotation, column ray-plane normals ``(W, 3)``, ray directions ``(H, W)`` x3."""
    h, w = hw
    rot = world_from_camera(pose6[3], pose6[4], pose6[5])
    fx, fy, cx, cy = kmat[0, 0], kmat[1, 1], kmat[0, 2], kmat[1, 2]
    xn = (jnp.arange(w, dtype=jnp.float32) - cx) / fx  # (W,)
    yn = (jnp.arange(h, dtype=jnp.float32) - cy) / fy  # (H,)
    # Ray directions (H, W); per-column primitive sets (K, 1, W) broadcast over the rows.
    dx, dy, dz = (rot[i, 0] * xn[None, :] + rot[i, 1] * yn[:, None] + rot[i, 2] for i in range(3))
    # Normal of each column's ray plane: cross((xn, 0, 1), (0, 1, 0)) = (-1, 0, xn) in camera axes.
    ncam = jnp.stack([-jnp.ones_like(xn), jnp.zeros_like(xn), xn], 1) * jax.lax.rsqrt(1.0 + xn * xn)[:, None]
    return pose6[:3], rot, ncam @ rot.T, (dx, dy, dz)


def _geometry_stage(geo: Geometry, pose6, kmat, hw, budget):
    """First hits: z-depth ``t (H, W)`` (0 on sky), hit kind, sky mask and the shading-table row."""
    o, rot, nrm, (dx, dy, dz) = _rays(pose6, kmat, hw)
    fwd = rot[:, 2]
    ib = _cull(geo.box_sphere, o, nrm, fwd, min(budget[0], geo.box.shape[0]))
    ic = _cull(geo.cyl_sphere, o, nrm, fwd, min(budget[1], geo.cyl.shape[0]))
    ie = _cull(geo.ell_sphere, o, nrm, fwd, min(budget[2], geo.ell.shape[0]))
    # Candidates on the leading axis, (K, H, W): the min over K then vectorises along the image rows.
    rx, ry, rz = dx[None], dy[None], dz[None]
    tb, gb = _first_hit(_hit_boxes(geo.box[ib.T], o, rx, ry, rz), ib)
    tc, gc = _first_hit(_hit_cyls(geo.cyl[ic.T], o, rx, ry, rz), ic)
    te, ge = _first_hit(_hit_ells(geo.ell_unit[ie.T], o, rx, ry, rz), ie)
    tg = _hit_terrain(geo.terrain, o, dx, dy, dz)
    tk = _hit_backdrop(geo.backdrop, o, dx, dy, dz)
    ts = jnp.stack([tb, tc, te, tg, tk], 0)
    kind = jnp.argmin(ts, 0).astype(jnp.int32)  # 0 box, 1 cyl, 2 ell, 3 ground, 4 backdrop
    t = jnp.min(ts, 0)
    sky = t >= _INF
    nb, nc = geo.box.shape[0], geo.cyl.shape[0]
    row_idx = jnp.where(kind == 0, gb, jnp.where(kind == 1, nb + gc, jnp.where(kind == 2, nb + nc + ge, 0)))
    return jnp.where(sky, 0.0, t), kind, sky, row_idx


def _surface_stage(geo: Geometry, look: Look, pose6, kmat, t, kind, row_idx, hw):
    """Albedo (three ``(H, W)`` planes) and Lambert factor ``(H, W)`` at the hits."""
    o, _, _, (dx, dy, dz) = _rays(pose6, kmat, hw)
    px, py, pz = o[0] + t * dx, o[1] + t * dy, o[2] + t * dz
    row = _row_table(geo, look)[row_idx]  # (H, W, 21)
    shaded = [
        _shade_box(row, px, py, pz),
        _shade_cyl(row, px, py, pz),
        _shade_ell(row, px, py, pz),
        _shade_ground(geo, look.ground, px, py, pz),
    ]
    sel = lambda vals: functools.reduce(
        lambda acc, kv: jnp.where(kind == kv[0], kv[1], acc), enumerate(vals[1:], 1), vals[0]
    )
    # Three separate planes: stacking them here makes XLA evaluate all of the shading per stacked element.
    albedo = tuple(sel([s[0][i] for s in shaded]) for i in range(3))
    normal = [sel([s[1][i] for s in shaded]) for i in range(3)]
    lam = jnp.maximum(normal[0] * look.sun_dir[0] + normal[1] * look.sun_dir[1] + normal[2] * look.sun_dir[2], 0)
    return albedo, lam


def _compose_stage(look: Look, pose6, kmat, frame_id, t, kind, sky, albedo, lam, hw):
    """Light, haze, sky, exposure and sensor noise: rgb ``uint8 (3, H, W)`` and depth ``(H, W)``."""
    h, w = hw
    _, _, _, (dx, dy, dz) = _rays(pose6, kmat, hw)
    dnorm = jnp.sqrt(dx * dx + dy * dy + dz * dz)
    haze = jnp.exp(-t * dnorm / look.fog_dist)
    el = jnp.clip(dz / dnorm, 0.0, 1.0)
    wz = jnp.sqrt(el)
    sun = (dx * look.sun_dir[0] + dy * look.sun_dir[1] + dz * look.sun_dir[2]) / dnorm
    glow = jnp.maximum(sun, 0.0) ** 32
    col = jnp.arange(w, dtype=jnp.int32)[None, :] * jnp.ones((h, 1), jnp.int32)
    row = jnp.arange(h, dtype=jnp.int32)[:, None] * jnp.ones((1, w), jnp.int32)
    out = []
    for i in range(3):
        lit = jnp.where(kind == 4, look.backdrop_rgb[i], albedo[i] * (look.ambient_rgb[i] + look.sun_rgb[i] * lam))
        lit = lit * haze + look.fog_rgb[i] * (1.0 - haze)
        sky_rgb = look.sky_horizon[i] * (1 - wz) + look.sky_zenith[i] * wz + look.sun_rgb[i] * glow
        c = jnp.where(sky, sky_rgb, lit)
        # Sensor noise: a hash of (frame id, pixel, channel), so a frame's pixels never depend on its batch.
        n = _hash01(frame_id * 4 + i, col, row) - 0.5
        v = c * look.gain[i] + n * (look.noise * np.sqrt(12.0))  # uniform noise with std `noise`
        out.append(jnp.clip(jnp.floor(v * 255.0 + 0.5), 0, 255).astype(jnp.uint8))
    # Channel-major: stacking along a major axis keeps each channel's loop vectorised.
    return jnp.stack(out, 0), jnp.where(sky, SKY_DEPTH, t).astype(jnp.float32)


# Three executables: XLA's CPU pipeline drops optimization barriers before fusion, and left as one program
# it fuses the hit maths and the shading into every consumer (each colour channel, depth, ...), several times
# slower. Executable boundaries make every stage's outputs materialise exactly once.
@functools.partial(jax.jit, static_argnames=("hw", "budget"))
def _geometry_batch(geo, poses6, kmats, *, hw, budget):
    return jax.vmap(lambda p, k: _geometry_stage(geo, p, k, hw, budget))(poses6, kmats)


@functools.partial(jax.jit, static_argnames=("hw", "look_per_frame"))
def _surface_batch(geo, look, poses6, kmats, t, kind, row_idx, *, hw, look_per_frame):
    fn = lambda lk, p, k, t_, kd, r: _surface_stage(geo, lk, p, k, t_, kd, r, hw)
    return jax.vmap(fn, in_axes=(0 if look_per_frame else None, 0, 0, 0, 0, 0))(look, poses6, kmats, t, kind, row_idx)


@functools.partial(jax.jit, static_argnames=("hw", "look_per_frame"))
def _compose_batch(look, poses6, kmats, frame_ids, t, kind, sky, albedo, lam, *, hw, look_per_frame):
    rgb, depth = jax.vmap(
        lambda lk, p, k, f, t_, kd, s, a, lm: _compose_stage(lk, p, k, f, t_, kd, s, a, lm, hw),
        in_axes=(0 if look_per_frame else None, 0, 0, 0, 0, 0, 0, 0, 0),
    )(look, poses6, kmats, frame_ids, t, kind, sky, albedo, lam)
    return jnp.moveaxis(rgb, 1, -1), depth


class Rendered(NamedTuple):
    """A rendered batch: ``rgb`` uint8 ``(B, H, W, 3)``, ``depth`` float32 ``(B, H, W)`` z-depth (m, sky at
    ``SKY_DEPTH``), ``sky`` bool ``(B, H, W)``, ``objects`` bool ``(B, H, W)``: the pixel shows a box,
    cylinder or ellipsoid (building, trunk, crown, sign, snow bank, …), neither ground nor sky."""

    rgb: jax.Array
    depth: jax.Array
    sky: jax.Array
    objects: jax.Array


def render_batch(
    geo: Geometry,
    look: Look,
    poses6: jax.Array,
    kmats: jax.Array,
    frame_ids: jax.Array,
    *,
    hw: tuple[int, int],
    look_per_frame: bool = False,
    budget: tuple[int, int, int] = (K_BOX, K_CYL, K_ELL),
) -> Rendered:
    """Renders a batch of frames: three jitted, vmapped stages (first hits, surfaces, light and sensor).

    Args:
        geo: scene geometry.
        look: scene appearance, shared by all frames, or with a leading ``B`` axis if `look_per_frame`.
        poses6: ``float32 (B, 6)`` camera x, y, z (m), yaw, pitch, roll (rad).
        kmats: ``float32 (B, 3, 3)`` 0-based pinhole intrinsics.
        frame_ids: ``int32 (B,)`` ids seeding the sensor noise.
        hw: static ``(H, W)``.
        look_per_frame: static; whether `look` is batched.
        budget: static; primitives intersected per image column for boxes, cylinders, ellipsoids. A budget
            at or above the table sizes disables culling (every ray tests every primitive: slow reference).

    Returns:
        :class:`Rendered` ``(rgb, depth, sky, objects)``.
    """
    t, kind, sky, row_idx = _geometry_batch(geo, poses6, kmats, hw=hw, budget=budget)
    albedo, lam = _surface_batch(geo, look, poses6, kmats, t, kind, row_idx, hw=hw, look_per_frame=look_per_frame)
    rgb, depth = _compose_batch(
        look, poses6, kmats, frame_ids, t, kind, sky, albedo, lam, hw=hw, look_per_frame=look_per_frame
    )
    return Rendered(rgb, depth, sky, (kind < 3) & ~sky)
