"""Held-out validation of a trunk: cross-look place retrieval on campuses it was never trained on.

A held-out world's views are rendered twice, each time with independent random looks per frame (colours,
textures, sky, light: the randomisation of the pretraining data, never the evaluation campus's seasons). For
every view of the *query* rendering, the nearest neighbour (cosine) among the *gallery* rendering's views is
looked up; it is a hit when it is the same view (``view recall@1``) or a view of the same place (same 10 × 10
grid cell of the world and the same 90° heading bin, ``place recall@1``). This is cross-season place recognition
in miniature — same geometry, unrelated appearance — measured where nothing is tuned.

Baselines on the same frames: raw pixels, 12 × 12 gradient thumbnails, 16 × 16 colour thumbnails (the
experiment's HHA nearest-neighbour baseline) and a randomly initialised trunk.

For an HHA trunk (``modality="hha"``) the two renderings are HHA images of perturbed depth in summer's geometry
and in another season's (``placejax.pretrain._data.place_frames``), drawn with a validation seed.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from placejax.data import simcampus
from placejax.models import VGG16, imagenet_normalise
from placejax.pretrain import _data
from placejax.training import map_batches


def heldout_frames(
    seed: int, n: int, hw: tuple[int, int], *, world: int = 0, modality: str = "rgb", depth_fn=None
) -> dict[str, np.ndarray]:
    """``n`` views of held-out world ``world`` of validation seed ``seed``, rendered with two independent look sets
    (``modality="hha"``: as HHA of perturbed depth in summer's and in other seasons' geometry, or of ``depth_fn``'s
    prediction, ``placejax.pretrain.data.network_depth``).

    Validation worlds use seeds ``place_world_seeds(seed, ...)``; pick a ``seed`` no pretraining run uses.

    Returns:
        dict with ``gallery``, ``query`` uint8 ``(n, H, W, 3)``, ``label`` int32 ``(n,)`` (place: cell and
        heading bin) and ``poses6`` ``(n, 6)``.
    """
    ws = _data.place_world_seeds(seed, world + 1)[world]
    rng = np.random.default_rng([seed, 0xE7A1, world])
    poses = simcampus.random_poses(simcampus.make_world(ws), rng, n)
    label = _data.place_labels(poses, _data.path_box(ws), 10, 4)
    if modality == "hha":
        noise = np.random.default_rng([seed, 0x44A, world])
        gallery = _data.hha_views(ws, poses, hw, noise, "SU", depth_fn)
        query = _data.other_season_views(ws, poses, hw, noise, depth_fn)
        return {"gallery": gallery, "query": query, "label": label, "poses6": poses}
    key = jax.random.key(seed)
    a = _data.render_random_looks(ws, poses, hw, jax.random.fold_in(key, 1))
    b = _data.render_random_looks(ws, poses, hw, jax.random.fold_in(key, 2))
    return {"gallery": a["rgb"], "query": b["rgb"], "label": label, "poses6": poses}


def recall_at_1(gallery: np.ndarray, query: np.ndarray, label: np.ndarray) -> dict[str, float]:
    """Cosine nearest neighbour of each query row among the gallery rows (row i of both = the same view).

    Args:
        gallery, query: ``(n, D)`` descriptors.
        label: ``(n,)`` place of each view.

    Returns:
        ``{"view": share whose neighbour is the same view, "place": share whose neighbour has the same label}``.
    """
    g = np.asarray(gallery, np.float64).reshape(len(gallery), -1)
    q = np.asarray(query, np.float64).reshape(len(query), -1)
    g = g / (np.linalg.norm(g, axis=1, keepdims=True) + 1e-12)
    q = q / (np.linalg.norm(q, axis=1, keepdims=True) + 1e-12)
    nn = np.argmax(q @ g.T, axis=1)
    return {"view": float(np.mean(nn == np.arange(len(q)))), "place": float(np.mean(label[nn] == label))}


def pixel_descriptor(rgb: np.ndarray) -> np.ndarray:
    """Raw pixels, per image centred: ``(n, H·W·3)``."""
    x = np.asarray(rgb, np.float32).reshape(len(rgb), -1)
    return x - x.mean(1, keepdims=True)


def gradient_thumbnail(rgb: np.ndarray, size: int = 12) -> np.ndarray:
    """Grey-level 12 × 12 thumbnail's x/y finite differences of ``rgb`` ``(n, H, W, 3)``, per image centred:
    ``(n, 2·size·(size−1))``."""
    grey = np.asarray(rgb, np.float32).mean(-1)
    n, h, w = grey.shape
    thumb = grey[:, : h // size * size, : w // size * size].reshape(n, size, h // size, size, w // size).mean((2, 4))
    d = np.concatenate([np.diff(thumb, axis=1).reshape(n, -1), np.diff(thumb, axis=2).reshape(n, -1)], 1)
    return d - d.mean(1, keepdims=True)


def colour_thumbnail(images: np.ndarray, size: int = 16) -> np.ndarray:
    """Area-averaged ``size × size`` thumbnail of every channel, per image centred: ``(n, size·size·C)``."""
    x = np.asarray(images, np.float32)
    n, h, w, c = x.shape
    x = x[:, : h // size * size, : w // size * size].reshape(n, size, h // size, size, w // size, c).mean((2, 4))
    x = x.reshape(n, -1)
    return x - x.mean(1, keepdims=True)


@functools.partial(jax.jit, static_argnames=("width",))
def _trunk_map(trunk_params, x, width: float):
    """The last conv block's max-pooled map (before adaptive pooling), flattened: what fc6 really sees."""
    pooled = VGG16(width=width).apply({"params": {"trunk": trunk_params}}, x, method=VGG16.conv_features)
    return pooled.reshape(len(x), -1)


def trunk_descriptor(trunk_params, rgb: np.ndarray, width: float, batch: int = 64) -> np.ndarray:
    """Frozen conv features of uint8 RGB frames, flattened ``(n, 7·7·512·width)`` (the pooled map fc6 reads)."""
    return map_batches(lambda x: _trunk_map(trunk_params, jnp.asarray(imagenet_normalise(x)), width), rgb, batch)


def evaluate_trunk(trunk_params, frames: dict[str, np.ndarray], width: float) -> dict[str, float]:
    """Cross-look recall@1 of a trunk's conv features on held-out frames (:func:`heldout_frames`)."""
    g = trunk_descriptor(trunk_params, frames["gallery"], width)
    q = trunk_descriptor(trunk_params, frames["query"], width)
    return recall_at_1(g, q, frames["label"])


def baselines(frames: dict[str, np.ndarray], width: float, seed: int = 0) -> dict[str, dict[str, float]]:
    """Recall@1 of raw pixels, gradient and colour thumbnails and a He-initialised (untrained) trunk on the same
    frames."""
    from placejax.models import he_init

    h, w = frames["gallery"].shape[1:3]
    params = VGG16(width=width).init(jax.random.key(seed), jnp.zeros((1, h, w, 3)))["params"]
    random_trunk = he_init(params, jax.random.key(seed + 1))["trunk"]
    lab = frames["label"]
    return {
        "pixels": recall_at_1(pixel_descriptor(frames["gallery"]), pixel_descriptor(frames["query"]), lab),
        "gradient_thumbnail": recall_at_1(
            gradient_thumbnail(frames["gallery"]), gradient_thumbnail(frames["query"]), lab
        ),
        "colour_thumbnail": recall_at_1(colour_thumbnail(frames["gallery"]), colour_thumbnail(frames["query"]), lab),
        "random_trunk": evaluate_trunk(random_trunk, frames, width),
    }
