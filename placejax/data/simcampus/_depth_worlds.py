"""Domain-randomised depth-training worlds: RGB + metric depth from campuses other than the evaluation one.

The analogue of MiDaS being trained on other data and then used unchanged (paper §III): the depth network is
trained on other world seeds with random colours, textures, sky and light per object *and per frame*, so it
never sees the evaluation campus or its seasonal looks.
"""

from __future__ import annotations

from collections.abc import Iterator

import jax
import jax.numpy as jnp
import numpy as np

from placejax import progress as _progress
from placejax.data.simcampus import _render, _seasons, _session, _trajectory
from placejax.data.simcampus import _world as W

# Depth-training world seeds live far from the small seeds used for evaluation campuses.
DEPTH_WORLD_SEED_BASE = 7_000_000


def _uniform(key, shape, lo=0.0, hi=1.0):
    return jax.random.uniform(key, shape, jnp.float32, lo, hi)


@jax.jit
def random_look(key: jax.Array) -> _render.Look:
    """One fully random appearance (colours, window grids, texture scales, sky, sun, haze, exposure)."""
    k = jax.random.split(key, 20)
    nb, nc, ne, nm = _seasons.N_BOX, _seasons.N_CYL, _seasons.N_ELL, W.N_MATERIALS
    box = jnp.concatenate(
        [_uniform(k[0], (nb, 9)), _uniform(k[1], (nb, 2), 0.5, 6.0), _uniform(k[2], (nb, 2), 0.05, 1.0)], 1
    )
    cyl = jnp.concatenate([_uniform(k[3], (nc, 6)), _uniform(k[4], (nc, 1), 0.05, 2.0)], 1)
    ell = jnp.concatenate([_uniform(k[5], (ne, 6)), _uniform(k[6], (ne, 1), 0.05, 2.0)], 1)
    ground = jnp.concatenate([_uniform(k[7], (nm, 6)), _uniform(k[8], (nm, 1), 0.05, 1.5)], 1)
    elev = _uniform(k[9], (), np.deg2rad(5.0), np.deg2rad(75.0))
    azim = _uniform(k[10], (), 0.0, 2 * np.pi)
    sun_dir = jnp.stack([jnp.cos(elev) * jnp.cos(azim), jnp.cos(elev) * jnp.sin(azim), jnp.sin(elev)])
    return _render.Look(
        box=box,
        cyl=cyl,
        ell=ell,
        ground=ground,
        sky_zenith=_uniform(k[11], (3,)),
        sky_horizon=_uniform(k[12], (3,)),
        sun_dir=sun_dir,
        sun_rgb=_uniform(k[13], (3,), 0.0, 1.0) * _uniform(k[14], (), 0.2, 1.0),
        ambient_rgb=_uniform(k[15], (3,), 0.2, 0.8),
        fog_rgb=_uniform(k[16], (3,)),
        fog_dist=jnp.exp(_uniform(k[17], (), np.log(100.0), np.log(5000.0))),
        gain=_uniform(k[18], (3,), 0.7, 1.3),
        noise=_uniform(k[19], (), 0.0, 0.04),
        backdrop_rgb=_uniform(jax.random.fold_in(key, 99), (3,)),
    )


CAMERA_TILTS = ("random", "terrain")
"""How the depth-training frames' cameras are tilted: ``"random"`` (random pitch and roll) or ``"terrain"`` (following
the ground)."""


@jax.jit
def muted_look(key: jax.Array) -> _render.Look:
    """A random look with natural rather than wild colours: desaturated and drawn towards one palette.

    :func:`random_look` gives every surface its own uniform colour, so neighbouring objects nearly always differ;
    outdoor scenes are mostly low in saturation and share a palette (snow on every roof and lawn, an overcast
    grey sky above grey walls, haze). Here every colour keeps a random share ``s`` of its saturation and moves
    a random share ``k`` of the way to one colour of the frame (both uniform in [0, 1]), and the ambient light
    reaches 0.9 (overcast) with the direct sun as weak as 0.
    """
    return _mute(random_look(key), key)


def _mute(look: _render.Look, key: jax.Array) -> _render.Look:
    """:func:`muted_look` of ``key`` from ``random_look(key)`` already drawn."""
    k1, k2, k3, k4, k5, k6 = jax.random.split(jax.random.fold_in(key, 0x307E), 6)
    sat, pull = _uniform(k1, ()), _uniform(k2, ())
    base = _uniform(k3, (3,))

    def natural(rgb):  # (..., 3)
        grey = rgb.mean(-1, keepdims=True)
        return (1 - pull) * (grey + sat * (rgb - grey)) + pull * jnp.broadcast_to(base, rgb.shape)

    def columns(table, n_rgb):
        parts = [natural(table[:, 3 * i : 3 * i + 3]) for i in range(n_rgb)]
        return jnp.concatenate([*parts, table[:, 3 * n_rgb :]], 1)

    return look._replace(
        box=columns(look.box, 3),
        cyl=columns(look.cyl, 2),
        ell=columns(look.ell, 2),
        ground=columns(look.ground, 2),
        sky_zenith=natural(look.sky_zenith),
        sky_horizon=natural(look.sky_horizon),
        fog_rgb=natural(look.fog_rgb),
        backdrop_rgb=natural(look.backdrop_rgb),
        ambient_rgb=_uniform(k4, (3,), 0.2, 0.9),
        sun_rgb=_uniform(k5, (3,), 0.0, 1.0) * _uniform(k6, (), 0.0, 1.0),
    )


def _hsv(key: jax.Array, shape: tuple[int, ...], value: tuple[float, float] = (0.12, 0.95)) -> jax.Array:
    """Random colours ``shape + (3,)`` of natural saturation: any hue, saturation mostly low (0.7·u², u uniform),
    value uniform in ``value``."""
    kh, ks, kv = jax.random.split(key, 3)
    h, s, v = _uniform(kh, shape), 0.7 * _uniform(ks, shape) ** 2, _uniform(kv, shape, *value)
    k = (jnp.array([5.0, 3.0, 1.0]).reshape((1,) * len(shape) + (3,)) + 6.0 * h[..., None]) % 6.0
    return v[..., None] * (1.0 - s[..., None] * jnp.clip(jnp.minimum(k, 4.0 - k), 0.0, 1.0))


def scene_roles(tables: _seasons.SceneTables) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The role of every box, cylinder and ellipsoid row of a scene's padded tables (padding rows: -1)."""

    def pad(role, n):
        return np.concatenate([np.asarray(role, np.int32), np.full(n - len(role), -1, np.int32)])

    return (
        pad(tables.boxes.role, _seasons.N_BOX),
        pad(tables.cyls.role, _seasons.N_CYL),
        pad(tables.ells.role, _seasons.N_ELL),
    )


def structured_look(key: jax.Array, roles: tuple[jax.Array, jax.Array, jax.Array]) -> _render.Look:
    """A random look with the structure of a real season: surfaces of one kind share a colour.

    :func:`random_look` colours every surface independently; in a real season all lawns are one green (or all under
    snow), all deciduous crowns one colour, all roofs alike, while each building keeps its own walls. Here, from
    ``random_look(key)``'s sun direction, haze distance, noise, textures and window grids: every ground material,
    the crowns, the conifers, the trunks, the poles and the roofs get one colour each (±15 % per object), every
    building's walls and windows their own; with probability 0.3 it is snowing — a near-white on each ground
    material (with probability 0.75 each), on the roofs and in the conifers' speckle; the sky is a light gradient,
    the backdrop a darker colour; ambient light and exposure are near grey (±8 % and ±6 % per channel), the sun of
    low saturation. Colours come from broad natural ranges (:func:`_hsv`: any hue, low saturation), never from the
    evaluation campus's seasons. Signs, landmarks, lamps and dynamic objects keep their wild colours. ``roles`` are
    the scene's :func:`scene_roles`.
    """
    return _structure(random_look(key), key, roles)


def _structure(look: _render.Look, key: jax.Array, roles) -> _render.Look:
    """:func:`structured_look` of ``key`` from ``random_look(key)`` already drawn."""
    box_role, cyl_role, ell_role = (jnp.asarray(r) for r in roles)
    k = jax.random.split(jax.random.fold_in(key, 0x57C), 20)
    snowing = _uniform(k[0], ()) < 0.3
    snow = jnp.clip(_uniform(k[1], (), 0.8, 0.96) + _uniform(k[2], (3,), -0.03, 0.03), 0.0, 1.0)

    def jitter(rgb, kk, n):  # one class colour (3,) → (n, 3), each object within ±15 %
        return jnp.clip(rgb[None, :] * _uniform(kk, (n, 1), 0.85, 1.15), 0.0, 1.0)

    def where(mask, new, old):
        return jnp.where(mask[:, None], new, old)

    nb, nc, ne = box_role.shape[0], cyl_role.shape[0], ell_role.shape[0]
    building = box_role == W.ROLE_BUILDING
    roof = jnp.where(snowing, snow, _hsv(k[3], ()))
    box = look.box
    box = box.at[:, 0:3].set(where(building, _hsv(k[4], (nb,)), box[:, 0:3]))
    box = box.at[:, 3:6].set(where(building, _hsv(k[5], (nb,), (0.05, 0.8)), box[:, 3:6]))
    box = box.at[:, 6:9].set(where(building, jitter(roof, k[6], nb), box[:, 6:9]))

    cyl = look.cyl
    for i, role in enumerate((W.ROLE_TRUNK, W.ROLE_POLE)):
        kk = jax.random.fold_in(k[7], i)
        base = _hsv(kk, (), (0.05, 0.7))
        alt = jnp.clip(base * _uniform(jax.random.fold_in(kk, 1), (), 0.6, 1.4), 0.0, 1.0)
        mask = cyl_role == role
        cyl = cyl.at[:, 0:3].set(where(mask, jitter(base, jax.random.fold_in(kk, 2), nc), cyl[:, 0:3]))
        cyl = cyl.at[:, 3:6].set(where(mask, jitter(alt, jax.random.fold_in(kk, 3), nc), cyl[:, 3:6]))

    ell = look.ell
    crown, conifer = ell_role == W.ROLE_CROWN, ell_role == W.ROLE_CONIFER
    crown_rgb = _hsv(k[8], ())
    crown_alt = 0.5 * (crown_rgb + _hsv(k[9], ()))
    conifer_rgb = _hsv(k[10], (), (0.05, 0.5))
    conifer_alt = jnp.where(snowing, snow, jnp.clip(conifer_rgb * _uniform(k[11], (), 0.6, 1.4), 0.0, 1.0))
    ell = ell.at[:, 0:3].set(where(crown, jitter(crown_rgb, k[12], ne), ell[:, 0:3]))
    ell = ell.at[:, 3:6].set(where(crown, jitter(crown_alt, k[13], ne), ell[:, 3:6]))
    ell = ell.at[:, 0:3].set(where(conifer, jitter(conifer_rgb, k[14], ne), ell[:, 0:3]))
    ell = ell.at[:, 3:6].set(where(conifer, jitter(conifer_alt, k[15], ne), ell[:, 3:6]))

    nm = look.ground.shape[0]
    ground_rgb = _hsv(k[16], (nm,))
    speckle = 0.5 * (ground_rgb + _hsv(k[17], (nm,)))
    covered = snowing & (_uniform(k[18], (nm,)) < 0.75)
    snow_speckle = jnp.broadcast_to(0.92 * snow, (nm, 3))
    ground = jnp.concatenate(
        [where(covered, jnp.broadcast_to(snow, (nm, 3)), ground_rgb), where(covered, snow_speckle, speckle)], 1
    )
    ground = jnp.concatenate([ground, look.ground[:, 6:]], 1)
    kz, kh, kmix, kb, ka, ks, kg = jax.random.split(k[19], 7)
    zenith = _hsv(kz, (), (0.45, 1.0))
    horizon = zenith + _uniform(kmix, (), 0.2, 0.8) * (_uniform(kh, (), 0.7, 1.0) - zenith)

    def near_grey(kk, lo, hi, tint):  # a level in [lo, hi] with each channel within ±tint of it
        k1, k2 = jax.random.split(kk)
        return _uniform(k1, (), lo, hi) * (1.0 + _uniform(k2, (3,), -tint, tint))

    return look._replace(
        box=box,
        cyl=cyl,
        ell=ell,
        ground=ground,
        sky_zenith=zenith,
        sky_horizon=horizon,
        fog_rgb=0.5 * (horizon + look.fog_rgb),
        backdrop_rgb=_hsv(kb, (), (0.1, 0.7)),
        ambient_rgb=near_grey(ka, 0.25, 0.9, 0.08),
        sun_rgb=_hsv(ks, (), (0.0, 1.0)),
        gain=near_grey(kg, 0.8, 1.2, 0.06),
    )


def _per_frame(pick: np.ndarray, a: _render.Look, b: _render.Look) -> _render.Look:
    """Frame i's look from ``a`` where ``pick[i]``, else from ``b`` (looks with a leading batch axis)."""
    pick = jnp.asarray(pick)
    return jax.tree.map(lambda x, y: jnp.where(pick.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), a, b)


def random_poses(
    world: W.World,
    rng: np.random.Generator,
    n: int,
    height_m: tuple[float, float] = (1.0, 2.0),
    tilt: str = "random",
) -> np.ndarray:
    """Camera poses ``(n, 6)`` near the paths, mostly along them, some looking anywhere.

    The camera is ``height_m`` (uniform between the two bounds, metres) above the ground under it. ``tilt``
    sets its pitch and roll: ``"random"``, up to ±6° and ±3° (uniform) whatever the ground does;
    ``"terrain"``, as a wheeled robot's camera sits: nose up on climbs and rolled towards the downhill side by
    the ground's slope under it, plus a 0.5° (sd) wobble — how SimCampus's session cameras are posed.
    """
    if tilt not in CAMERA_TILTS:
        raise ValueError(f"tilt must be one of {CAMERA_TILTS}, got {tilt!r}")
    pts, tans = _seasons.path_frames(world, 1.0)
    i = rng.integers(len(pts), size=n)
    normal = np.stack([-tans[i, 1], tans[i, 0]], -1)
    xy = pts[i] + normal * rng.uniform(-3.0, 3.0, (n, 1))
    yaw = np.arctan2(tans[i, 1], tans[i, 0]) + np.where(
        rng.uniform(size=n) < 0.7,
        rng.uniform(-np.pi / 3, np.pi / 3, n) + np.pi * rng.integers(2, size=n),
        rng.uniform(-np.pi, np.pi, n),
    )
    z = world.height(xy[:, 0], xy[:, 1]) + rng.uniform(height_m[0], height_m[1], n)
    if tilt == "random":
        pitch = np.deg2rad(rng.uniform(-6, 6, n))
        roll = np.deg2rad(rng.uniform(-3, 3, n))
    else:
        pitch, roll = _trajectory.terrain_tilt(world, xy, yaw, rng)
    return np.stack([xy[:, 0], xy[:, 1], z, np.angle(np.exp(1j * yaw)), pitch, roll], -1)


def depth_world_seeds(seed: int, n_worlds: int, exclude_world_seeds=(0,)) -> list[int]:
    """World seeds of the depth-training campuses for `seed`; never one of `exclude_world_seeds`."""
    seeds = [DEPTH_WORLD_SEED_BASE + 1000 * int(seed) + w for w in range(n_worlds)]
    clash = sorted(set(seeds) & {int(s) for s in exclude_world_seeds})
    if clash:
        raise ValueError(f"depth-training world seeds {clash} coincide with evaluation worlds")
    return seeds


# Batched looks, made once: a jit wrapper made per generator (or per batch) would trace and compile again.
_random_looks = jax.jit(jax.vmap(random_look))
_muted_looks = jax.jit(jax.vmap(_mute))
_structured_looks = jax.jit(jax.vmap(_structure, in_axes=(0, 0, None)))


def depth_training_batches(
    seed: int,
    batch_size: int,
    hw: tuple[int, int],
    *,
    n_worlds: int = 4,
    hfov_deg: float = _session.DEFAULT_HFOV_DEG,
    exclude_world_seeds=(0,),
    camera_height_m: tuple[float, float] = (1.0, 2.0),
    camera_tilt: str = "random",
    muted_share: float = 0.0,
    structured_share: float = 0.0,
    paired_looks: bool = False,
) -> Iterator[dict[str, np.ndarray]]:
    """Endless deterministic batches of domain-randomised RGB + depth (batch b comes from world b % n_worlds).

    Each frame's look is :func:`random_look`'s, or with probability ``muted_share`` :func:`muted_look`'s, or
    with probability ``structured_share`` :func:`structured_look`'s (drawn after the muting: it wins). With
    ``paired_looks``, frames ``2k`` and ``2k + 1`` of a batch are one view (same pose, so the same depth) in two
    independent looks (``batch_size`` must be even).

    Yields:
        dict with ``rgb`` uint8 ``(B, H, W, 3)``, ``depth`` float32 ``(B, H, W)`` z-depth (m, sky =
        `SKY_DEPTH`), ``sky`` and ``objects`` bool ``(B, H, W)`` (see ``render_batch``), ``K`` float64 ``(3, 3)``.
    """
    hw = _session._check_hw(hw)
    if paired_looks and batch_size % 2:
        raise ValueError(f"paired_looks needs an even batch_size, got {batch_size}")
    seeds = depth_world_seeds(seed, n_worlds, exclude_world_seeds)
    kmat = _session.intrinsics(hw, hfov_deg)
    kb = jnp.asarray(np.broadcast_to(kmat, (batch_size, 3, 3)), jnp.float32)
    b = 0
    while True:
        w = b % n_worlds
        world = _session.make_world(seeds[w])
        # Geometry variety from the seasons too (foliage volume, snow banks, dynamic objects, the site).
        tables = _seasons.scene_tables(world, _seasons.SEASONS[(b // n_worlds) % len(_seasons.SEASONS)])
        geo = _seasons.geometry_from_tables(world, tables)
        rng = np.random.default_rng([seed, 0xDE97, b])
        if paired_looks:
            poses = np.repeat(random_poses(world, rng, batch_size // 2, camera_height_m, camera_tilt), 2, axis=0)
        else:
            poses = random_poses(world, rng, batch_size, camera_height_m, camera_tilt)
        keys = jax.random.split(jax.random.fold_in(jax.random.key(seed), b), batch_size)
        looks = _random_looks(keys)
        if muted_share > 0:
            muted = _muted_looks(looks, keys)
            looks = _per_frame(rng.uniform(size=batch_size) < muted_share, muted, looks)
        if structured_share > 0:
            structured = _structured_looks(looks, keys, scene_roles(tables))
            looks = _per_frame(rng.uniform(size=batch_size) < structured_share, structured, looks)
        ids = jnp.asarray(b * batch_size + np.arange(batch_size), jnp.int32)
        r = _render.render_batch(geo, looks, jnp.asarray(poses, jnp.float32), kb, ids, hw=hw, look_per_frame=True)
        yield {**{k: np.asarray(v) for k, v in r._asdict().items()}, "K": kmat}
        b += 1


def depth_training_frames(
    seed: int,
    n: int,
    hw: tuple[int, int],
    *,
    batch_size: int = 32,
    n_worlds: int = 4,
    hfov_deg: float = _session.DEFAULT_HFOV_DEG,
    exclude_world_seeds=(0,),
    camera_height_m: tuple[float, float] = (1.0, 2.0),
    camera_tilt: str = "random",
    muted_share: float = 0.0,
    structured_share: float = 0.0,
    paired_looks: bool = False,
    progress: bool = True,
) -> dict[str, np.ndarray]:
    """`n` domain-randomised RGB + depth frames from the depth-training worlds (first `n` of the batches).

    Example:
        >>> d = depth_training_frames(0, 2, (16, 16), batch_size=2, progress=False)
        >>> d["rgb"].shape, d["depth"].shape
        ((2, 16, 16, 3), (2, 16, 16))
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    it = depth_training_batches(
        seed,
        batch_size,
        hw,
        n_worlds=n_worlds,
        hfov_deg=hfov_deg,
        exclude_world_seeds=exclude_world_seeds,
        camera_height_m=camera_height_m,
        camera_tilt=camera_tilt,
        muted_share=muted_share,
        structured_share=structured_share,
        paired_looks=paired_looks,
    )
    parts = []
    with _progress.bar(total=n, desc="depth-training frames", unit="frame", disable=not progress) as bar:
        while sum(len(p["rgb"]) for p in parts) < n:
            parts.append(next(it))
            bar.update(len(parts[-1]["rgb"]))
    out = {k: np.concatenate([p[k] for p in parts])[:n] for k in ("rgb", "depth", "sky", "objects")}
    out["K"] = parts[0]["K"]
    return out
