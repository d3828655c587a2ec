"""Place-labelled, domain-randomised frames from SimCampus worlds other than the evaluation campus.

The ImageNet stand-in's data: camera poses near the paths of other world seeds (``simcampus`` depth-training
worlds), each frame rendered with its own random look (colours, textures, sky, sun, haze, exposure per object
and frame — never the four season palettes of the evaluation campus, which are the test domain). A frame's place
is its grid cell over its world's paths (an ``n × n`` grid as the paper's §IV workspace grid) and a coarse heading
bin, so its label is determined by geometry alone; appearance carries no information about it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import tqdm

from placejax.data import simcampus

# Place-pretraining world seeds: far from the evaluation campuses (small seeds) and from the depth network's
# training worlds (7_000_000 + ...), so neither network has seen the other's worlds.
PLACE_WORLD_SEED_BASE = 8_000_000

# One random look per frame (created once: a fresh jit wrapper per call would recompile every time).
_random_looks = jax.jit(jax.vmap(simcampus.random_look))


def place_world_seeds(seed: int, n_worlds: int, exclude_world_seeds=(0,)) -> list[int]:
    """World seeds of pretraining (or held-out validation) campuses; never one of ``exclude_world_seeds``."""
    seeds = [PLACE_WORLD_SEED_BASE + 1000 * int(seed) + w for w in range(n_worlds)]
    clash = sorted(set(seeds) & {int(s) for s in exclude_world_seeds})
    if clash:
        raise ValueError(f"pretraining world seeds {clash} coincide with evaluation worlds")
    return seeds


def path_box(world_seed: int) -> tuple[float, float, float, float]:
    """``(x_min, x_max, y_min, y_max)`` (m) of a world's path points, the box of its place grid."""
    pts, _ = simcampus.path_frames(simcampus.make_world(world_seed), 1.0)
    return float(pts[:, 0].min()), float(pts[:, 0].max()), float(pts[:, 1].min()), float(pts[:, 1].max())


def place_labels(poses6: np.ndarray, box, grid: int, headings: int) -> np.ndarray:
    """Class ids ``int32 (N,)`` of poses in one world: ``(cell_row · grid + cell_col) · headings + heading_bin``.

    Args:
        poses6: ``(N, 6)`` x, y, z, yaw, pitch, roll.
        box: ``(x_min, x_max, y_min, y_max)`` of the grid (points outside are clipped to the border cells).
        grid: cells per axis.
        headings: yaw bins (1: position only); bin 0 is centred on +x.
    """
    x0, x1, y0, y1 = box
    row = np.clip(((poses6[:, 0] - x0) / (x1 - x0) * grid).astype(int), 0, grid - 1)
    col = np.clip(((poses6[:, 1] - y0) / (y1 - y0) * grid).astype(int), 0, grid - 1)
    yaw = np.mod(poses6[:, 3] + np.pi / headings, 2 * np.pi)
    hbin = np.minimum((yaw / (2 * np.pi) * headings).astype(int), headings - 1)
    return ((row * grid + col) * headings + hbin).astype(np.int32)


def render_random_looks(world_seed: int, poses6: np.ndarray, hw: tuple[int, int], key: jax.Array, batch: int = 32):
    """Renders ``poses6`` of a world, each frame with its own random look (season geometry of summer).

    Returns:
        dict with ``rgb`` uint8 ``(N, H, W, 3)``, ``depth`` float32 ``(N, H, W)`` (m), ``sky`` bool ``(N, H, W)``.
    """
    world = simcampus.make_world(world_seed)
    geo, _ = simcampus.season_scene(world, "SU")
    kmat = jnp.asarray(simcampus.intrinsics(hw), jnp.float32)
    out = {"rgb": [], "depth": [], "sky": []}
    for lo in range(0, len(poses6), batch):
        p = np.asarray(poses6[lo : lo + batch], np.float32)
        n = len(p)
        pad = batch - n
        p = np.concatenate([p, np.repeat(p[-1:], pad, 0)])
        keys = jax.random.split(jax.random.fold_in(key, lo), batch)
        ids = jnp.asarray(lo + np.arange(batch), jnp.int32)
        r = simcampus.render_batch(
            geo,
            _random_looks(keys),
            jnp.asarray(p),
            jnp.broadcast_to(kmat, (batch, 3, 3)),
            ids,
            hw=hw,
            look_per_frame=True,
        )
        for k in out:
            out[k].append(np.asarray(getattr(r, k))[:n])
    return {k: np.concatenate(v) for k, v in out.items()}


def place_frames(
    seed: int,
    frames_per_world: int,
    hw: tuple[int, int],
    *,
    n_worlds: int,
    grid: int = 10,
    headings: int = 4,
    exclude_world_seeds=(0,),
    progress: bool = True,
) -> dict[str, np.ndarray]:
    """Place-labelled views of ``n_worlds`` pretraining worlds, each rendered twice with independent random looks.

    Classes are numbered world by world (``world · grid² · headings + place_labels``); only some are occupied.

    Returns:
        dict with ``rgb`` and ``rgb2`` uint8 ``(N, H, W, 3)`` (the same view in two random looks),
        ``label`` int32 ``(N,)``, ``world`` int32 ``(N,)`` (index into the seeds), ``poses6`` ``(N, 6)``,
        N = ``n_worlds · frames_per_world``.

    Example:
        >>> f = place_frames(0, 2, (16, 16), n_worlds=1, progress=False)
        >>> f["rgb"].shape, f["rgb2"].shape, f["label"].shape
        ((2, 16, 16, 3), (2, 16, 16, 3), (2,))
    """
    seeds = place_world_seeds(seed, n_worlds, exclude_world_seeds)
    parts = []
    per_world = grid * grid * headings
    for w, ws in enumerate(tqdm.tqdm(seeds, desc="pretraining worlds", disable=not progress)):
        world = simcampus.make_world(ws)
        rng = np.random.default_rng([seed, 0x91ACE, w])
        poses = simcampus.random_poses(world, rng, frames_per_world)
        key = jax.random.fold_in(jax.random.key(seed), w)
        r = {
            "rgb": render_random_looks(ws, poses, hw, jax.random.fold_in(key, 0))["rgb"],
            "rgb2": render_random_looks(ws, poses, hw, jax.random.fold_in(key, 1))["rgb"],
        }
        r["label"] = w * per_world + place_labels(poses, path_box(ws), grid, headings)
        r["world"] = np.full(frames_per_world, w, np.int32)
        r["poses6"] = poses
        parts.append(r)
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
