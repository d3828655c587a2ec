"""The ImageNet stand-in: pretraining of the VGG16 trunk on domain-randomised SimCampus worlds.

The paper fine-tunes fc6–fc8 of an ImageNet VGG16 with frozen convolutions. Here the trunk is pretrained on
SimCampus worlds other than the evaluation campus (random looks per object and frame, never the season
palettes), on :class:`PretextObjective`, through ``placejax.training``'s one engine; its held-out quality is
cross-look place retrieval on worlds it never saw (`placejax.pretrain.evaluation`). The result of the ``default``
preset ships as ``placejax/pretrain/weights/<SHIPPED_RGB>.npz`` (``placejax.weights.resolve("shipped:" +
SHIPPED_RGB)``), because a fresh machine cannot afford to pretrain; :func:`ensure_trained` reproduces it into the cache.
``PretrainConfig.modality="hha"`` pretrains the trunk of the HHA net on HHA images of perturbed rendered depth, or,
with ``hha_depth="trained:<preset>"``, of what a trained placejax depth network predicts
(`placejax.pretrain.data`).

Public surface:
    PretrainConfig, PRESETS, PretextObjective: the recipe.
    train_trunk, ensure_trained, load_trained, run_dir: training into a folder or once into the cache.
    pretrained_vgg16, modality_weights: VGG16 parameters from a weights spec, for the place classifiers.
    save_trunk, read_trunk, export_params: trunk files (what the shipped ones are).
    SHIPPED_RGB, SHIPPED_HHA, SHIPPED_HHA_PREDICTED, SHIPPED_HHA_PREDICTED_DEPTH: the shipped trunks' names.
    trunk_map_size: the trunk's last map for an input size.
    data, evaluation: the pretraining data and the held-out evaluation.
"""

from placejax.pretrain import data, evaluation
from placejax.pretrain._lifecycle import (
    SHIPPED_HHA,
    SHIPPED_HHA_PREDICTED,
    SHIPPED_HHA_PREDICTED_DEPTH,
    SHIPPED_RGB,
    ensure_trained,
    export_params,
    modality_weights,
    pretrained_vgg16,
    read_trunk,
    run_dir,
    save_trunk,
)
from placejax.pretrain._shape import trunk_map_size
from placejax.pretrain._train import PRESETS, PretextObjective, PretrainConfig, load_trained, train_trunk

__all__ = [
    "PRESETS",
    "SHIPPED_HHA",
    "SHIPPED_HHA_PREDICTED",
    "SHIPPED_HHA_PREDICTED_DEPTH",
    "SHIPPED_RGB",
    "PretextObjective",
    "PretrainConfig",
    "data",
    "ensure_trained",
    "evaluation",
    "export_params",
    "load_trained",
    "modality_weights",
    "pretrained_vgg16",
    "read_trunk",
    "run_dir",
    "save_trunk",
    "train_trunk",
    "trunk_map_size",
]
