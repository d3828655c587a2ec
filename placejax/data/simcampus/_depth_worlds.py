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
import tqdm

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
    paired_looks: bool = False,
) -> Iterator[dict[str, np.ndarray]]:
    """Endless deterministic batches of domain-randomised RGB + depth (batch b comes from world b % n_worlds).

    Each frame's look is :func:`random_look`'s, or with probability ``muted_share`` :func:`muted_look`'s. With
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
    random_looks = jax.jit(jax.vmap(random_look))
    muted_looks = jax.jit(jax.vmap(_mute))  # once per generator: a wrapper made per batch would recompile
    b = 0
    while True:
        w = b % n_worlds
        world = _session.make_world(seeds[w])
        # Geometry variety from the seasons too (foliage volume, snow banks, dynamic objects, the site).
        geo, _ = _session.season_scene(world, _seasons.SEASONS[(b // n_worlds) % len(_seasons.SEASONS)])
        rng = np.random.default_rng([seed, 0xDE97, b])
        if paired_looks:
            poses = np.repeat(random_poses(world, rng, batch_size // 2, camera_height_m, camera_tilt), 2, axis=0)
        else:
            poses = random_poses(world, rng, batch_size, camera_height_m, camera_tilt)
        keys = jax.random.split(jax.random.fold_in(jax.random.key(seed), b), batch_size)
        looks = random_looks(keys)
        if muted_share > 0:
            muted = muted_looks(looks, keys)
            looks = _per_frame(rng.uniform(size=batch_size) < muted_share, muted, looks)
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
        paired_looks=paired_looks,
    )
    parts = []
    with tqdm.tqdm(total=n, desc="depth-training frames", unit="frame", disable=not progress) as bar:
        while sum(len(p["rgb"]) for p in parts) < n:
            parts.append(next(it))
            bar.update(len(parts[-1]["rgb"]))
    out = {k: np.concatenate([p[k] for p in parts])[:n] for k in ("rgb", "depth", "sky", "objects")}
    out["K"] = parts[0]["K"]
    return out
