"""Place-labelled, domain-randomised frames from SimCampus worlds other than the evaluation campus.

The ImageNet stand-in's data: camera poses near the paths of other world seeds (``simcampus`` depth-training
worlds), each frame rendered with its own random look (colours, textures, sky, sun, haze, exposure per object
and frame — never the four season palettes of the evaluation campus, which are the test domain). A frame's place
is its grid cell over its world's paths (an ``n × n`` grid as the paper's §IV workspace grid) and a coarse heading
bin, so its label is determined by geometry alone; appearance carries no information about it.

For a trunk that reads HHA images (``modality="hha"``) a view's two versions are HHA images of its depth in two
seasons' geometry (summer and one of the others: foliage, snow banks, parked cars), each through
:func:`perturb_depth`, which imitates what a monocular depth network gets wrong (objects at the wrong distance,
blur, the far range handed over as sky), so the pretext asks for what cross-season HHA recognition needs. Or,
with ``hha_depth="trained:<preset>"``, through the experiment's own depth network: each version is rendered in its
own random look and its depth is what the trained network (``placejax.depth``) predicts from that RGB image, with
the views and sky step the shipped trunk was pretrained with (:func:`network_depth`), so the trunk sees the errors it
will meet.
"""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from placejax import hha
from placejax import progress as _progress
from placejax.data import simcampus
from placejax.depth import PRESETS, ensure_trained, far_to_sky

# Place-pretraining world seeds: far from the evaluation campuses (small seeds) and from the depth network's
# training worlds (7_000_000 + ...), so neither network has seen the other's worlds.
PLACE_WORLD_SEED_BASE = 8_000_000

TRUNK_MODALITIES = ("rgb", "hha")

# perturb_depth: the depth network's range (it predicts at most 80 m), the spread of its errors (objects off by a
# median factor of 1.3-1.45 on a world it never saw, see docs/research-log.md), log-depth blur and the sky
# step's threshold (the experiment's depth.far_as_sky_m is 60 m; the shipped trunk's recipe hands over from 50 m).
PERTURB_MAX_DEPTH_M = 80.0
PERTURB_LOG_SCALE = 0.3  # amplitude of the smooth log-depth error field
PERTURB_FIELD_PX = 0.125  # its correlation length, as a share of the image width
PERTURB_BLUR_PX = (0.0, 1.5)  # log-depth blur sigma, pixels at 64 x 64 (scaled with the width)
PERTURB_SKY_FROM_M = (40.0, 70.0)

# network_depth's defaults: the depth views and the sky step the shipped HHA trunk was pretrained with (mirror and
# shifts ±2, ±4 px; everything from 50 m on as sky), which differ from the experiment's depth stage (the image and
# its mirror; 60 m): PretrainConfig.hha_depth_shifts and hha_sky_from_m select another stage, these keep the shipped
# trunk's recorded recipe making that trunk (docs/depth-network.md, "Fewer views").
NETWORK_FLIP = True
NETWORK_SHIFTS = (2, 4)
NETWORK_SKY_FROM_M = 50.0
HHA_DEPTH_PERTURBED = "perturbed"
HHA_DEPTH_TRAINED = "trained:"

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


def render_random_looks(
    world_seed: int, poses6: np.ndarray, hw: tuple[int, int], key: jax.Array, batch: int = 32, season: str = "SU"
):
    """Renders ``poses6`` of a world, each frame with its own random look (in ``season``'s geometry).

    Returns:
        dict with ``rgb`` uint8 ``(N, H, W, 3)``, ``depth`` float32 ``(N, H, W)`` (m), ``sky`` bool ``(N, H, W)``.
    """
    world = simcampus.make_world(world_seed)
    geo, _ = simcampus.season_scene(world, season)
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


def perturb_depth(depth_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Rendered depth ``(N, H, W)`` (m, sky at 1000 m) as a monocular depth network might have predicted it.

    Per frame: clamped to the network's range (80 m); multiplied by a smooth random field ``exp(a · g)`` (``g`` a
    unit-variance Gaussian field of correlation length 1/8 of the width, ``a`` = 0.3: objects at the wrong
    distance); blurred in log depth (σ uniform in 0-1.5 px at 64 px width); then everything from a threshold
    uniform in 40-70 m on set to the sky's 1000 m (``placejax.depth.far_to_sky``, as the experiment does).
    """

    depth_m = np.asarray(depth_m, np.float32)
    n, h, w = depth_m.shape
    out = np.empty_like(depth_m)
    corr = PERTURB_FIELD_PX * w
    px = w / 64.0
    for i in range(n):
        field = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), corr)
        field /= field.std() + 1e-6
        log_d = np.log(np.minimum(depth_m[i], PERTURB_MAX_DEPTH_M)) + PERTURB_LOG_SCALE * field
        sigma = rng.uniform(*PERTURB_BLUR_PX) * px
        if sigma > 0.05:
            log_d = cv2.GaussianBlur(log_d, (0, 0), sigma)
        out[i] = far_to_sky(np.exp(log_d), rng.uniform(*PERTURB_SKY_FROM_M), simcampus.SKY_DEPTH)
    return out


def check_hha_depth(hha_depth: str) -> None:
    """ValueError unless ``hha_depth`` is ``"perturbed"`` or ``"trained:<a placejax.depth preset>"``."""

    if hha_depth == HHA_DEPTH_PERTURBED:
        return
    preset = hha_depth.removeprefix(HHA_DEPTH_TRAINED)
    if not hha_depth.startswith(HHA_DEPTH_TRAINED) or preset not in PRESETS:
        raise ValueError(
            f"hha_depth must be {HHA_DEPTH_PERTURBED!r} or {HHA_DEPTH_TRAINED!r} + one of {sorted(PRESETS)}, "
            f"got {hha_depth!r}"
        )


def network_depth(
    hha_depth: str,
    progress: bool = True,
    *,
    shifts: tuple[int, ...] = NETWORK_SHIFTS,
    sky_from_m: float = NETWORK_SKY_FROM_M,
):
    """The depth function ``uint8 (N, H, W, 3) → float32 (N, H, W)`` m that ``hha_depth`` names, or None.

    ``"perturbed"``: None (HHA views then come from :func:`perturb_depth` of rendered depth).
    ``"trained:<preset>"``: that placejax depth network (``placejax.depth.ensure_trained``: loaded from the
    cache, trained there first if missing), its prediction averaged over the image, its mirror and the views
    shifted sideways by ± each of ``shifts`` pixels, and everything from ``sky_from_m`` on handed over as sky. The
    defaults (±2, ±4 px; 50 m) are the depth stage the shipped HHA trunk was pretrained on; the experiment's
    default depth stage is ``shifts=()``, ``sky_from_m=60``.
    """
    check_hha_depth(hha_depth)
    if hha_depth == HHA_DEPTH_PERTURBED:
        return None

    net = ensure_trained(hha_depth.removeprefix(HHA_DEPTH_TRAINED), progress=progress)

    def depth_fn(rgb: np.ndarray) -> np.ndarray:
        d = net.predict_metric(rgb, flip_average=NETWORK_FLIP, shifts=tuple(shifts))
        return far_to_sky(d, sky_from_m, simcampus.SKY_DEPTH)

    return depth_fn


def hha_views(
    world_seed: int,
    poses6: np.ndarray,
    hw: tuple[int, int],
    rng: np.random.Generator,
    season: str,
    depth_fn=None,
) -> np.ndarray:
    """HHA images ``uint8 (N, H, W, 3)`` of ``poses6`` in ``season``'s geometry, through :func:`perturb_depth`, or,
    given ``depth_fn`` (:func:`network_depth`), through what it predicts from each view rendered in a random look
    drawn from ``rng``."""
    if depth_fn is None:
        depth = render_random_looks(world_seed, poses6, hw, jax.random.key(0), season=season)["depth"]
        depth = perturb_depth(depth, rng)
    else:
        key = jax.random.key(int(rng.integers(2**31)))
        rgb = render_random_looks(world_seed, poses6, hw, key, season=season)["rgb"]
        depth = np.concatenate([depth_fn(rgb[i : i + 256]) for i in range(0, len(rgb), 256)])
    k = simcampus.intrinsics(hw)
    return np.concatenate([np.asarray(hha.encode(depth[i : i + 128], k)) for i in range(0, len(depth), 128)])


def other_season_views(world_seed: int, poses6: np.ndarray, hw, rng: np.random.Generator, depth_fn=None) -> np.ndarray:
    """HHA of each view in one of the non-summer seasons' geometry (view i: season i mod 3); ``depth_fn`` as in
    :func:`hha_views`."""
    out = np.empty((len(poses6), *hw, 3), np.uint8)
    for j, season in enumerate(("WI", "SP", "AU")):
        idx = np.arange(j, len(poses6), 3)
        if len(idx):
            out[idx] = hha_views(world_seed, poses6[idx], hw, rng, season, depth_fn)
    return out


def place_frames(
    seed: int,
    frames_per_world: int,
    hw: tuple[int, int],
    *,
    n_worlds: int,
    grid: int = 10,
    headings: int = 4,
    exclude_world_seeds=(0,),
    modality: str = "rgb",
    hha_depth: str = HHA_DEPTH_PERTURBED,
    hha_depth_shifts: tuple[int, ...] = NETWORK_SHIFTS,
    hha_sky_from_m: float = NETWORK_SKY_FROM_M,
    progress: bool = True,
) -> dict[str, np.ndarray]:
    """Place-labelled views of ``n_worlds`` pretraining worlds, each in two versions.

    ``modality="rgb"``: the two versions are renderings with independent random looks. ``"hha"``: HHA images of
    the view's depth in summer's geometry and in another season's, each through :func:`perturb_depth`
    (``hha_depth="perturbed"``) or predicted by a trained depth network (``"trained:<preset>"``,
    :func:`network_depth` with ``hha_depth_shifts`` and ``hha_sky_from_m``).
    Classes are numbered world by world (``world · grid² · headings + place_labels``); only some are occupied.

    Returns:
        dict with ``image`` and ``image2`` uint8 ``(N, H, W, 3)`` (the view's two versions), ``label`` int32
        ``(N,)``, ``world`` int32 ``(N,)`` (index into the seeds), ``poses6`` ``(N, 6)``,
        N = ``n_worlds · frames_per_world``.

    Example:
        >>> f = place_frames(0, 2, (16, 16), n_worlds=1, progress=False)
        >>> f["image"].shape, f["image2"].shape, f["label"].shape
        ((2, 16, 16, 3), (2, 16, 16, 3), (2,))
    """
    if modality not in TRUNK_MODALITIES:
        raise ValueError(f"modality must be one of {TRUNK_MODALITIES}, got {modality!r}")
    seeds = place_world_seeds(seed, n_worlds, exclude_world_seeds)
    depth_fn = None
    if modality == "hha":
        depth_fn = network_depth(hha_depth, progress, shifts=hha_depth_shifts, sky_from_m=hha_sky_from_m)
    parts = []
    per_world = grid * grid * headings
    for w, ws in enumerate(_progress.bar(seeds, desc="pretraining worlds", unit="world", disable=not progress)):
        world = simcampus.make_world(ws)
        rng = np.random.default_rng([seed, 0x91ACE, w])
        poses = simcampus.random_poses(world, rng, frames_per_world)
        if modality == "hha":
            noise = np.random.default_rng([seed, 0x44A, w])
            r = {
                "image": hha_views(ws, poses, hw, noise, "SU", depth_fn),
                "image2": other_season_views(ws, poses, hw, noise, depth_fn),
            }
        else:
            key = jax.random.fold_in(jax.random.key(seed), w)
            r = {
                "image": render_random_looks(ws, poses, hw, jax.random.fold_in(key, 0))["rgb"],
                "image2": render_random_looks(ws, poses, hw, jax.random.fold_in(key, 1))["rgb"],
            }
        r["label"] = w * per_world + place_labels(poses, path_box(ws), grid, headings)
        r["world"] = np.full(frames_per_world, w, np.int32)
        r["poses6"] = poses
        parts.append(r)
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
