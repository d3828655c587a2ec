"""The pretraining data: places on worlds other than the evaluation campus, rendered in random looks, and the depth
the HHA trunk's images are made from (perturbed rendered depth, or a trained depth network's predictions)."""

from placejax.pretrain._data import (
    network_depth,
    perturb_depth,
    place_frames,
    place_labels,
    place_world_seeds,
    render_random_looks,
)
from placejax.pretrain._train import training_frames

__all__ = [
    "network_depth",
    "perturb_depth",
    "place_frames",
    "place_labels",
    "place_world_seeds",
    "render_random_looks",
    "training_frames",
]
