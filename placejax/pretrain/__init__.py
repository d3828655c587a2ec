"""The ImageNet stand-in: pretraining of the VGG16 trunk on domain-randomised SimCampus worlds.

The paper fine-tunes fc6–fc8 of an ImageNet VGG16 with frozen convolutions. Here the trunk is pretrained on
SimCampus worlds other than the evaluation campus (random looks per object and frame, never the season
palettes), on :class:`PretextObjective`, through ``placejax.training``'s one engine; its held-out quality is
cross-look place retrieval on worlds it never saw (:func:`heldout_report`). The result of the ``default`` preset
is shipped as ``placejax/pretrain/weights/<SHIPPED>.npz`` (:func:`load_shipped`), because a fresh machine cannot
afford to pretrain; :func:`ensure_trained` reproduces it into the cache. ``PretrainConfig.modality="hha"``
pretrains the trunk of the HHA net on HHA images of perturbed rendered depth (:func:`perturb_depth`), or, with
``hha_depth="trained:<preset>"``, of what a trained placejax depth network predicts (:func:`network_depth`).
"""

from placejax.pretrain._data import (
    network_depth,
    perturb_depth,
    place_frames,
    place_labels,
    place_world_seeds,
    render_random_looks,
)
from placejax.pretrain._evaluate import (
    baselines,
    evaluate_trunk,
    gradient_thumbnail,
    heldout_frames,
    recall_at_1,
    trunk_descriptor,
)
from placejax.pretrain._lifecycle import (
    CHECK_FRAMES,
    SHIPPED,
    SHIPPED_HHA,
    SHIPPED_HHA_PREDICTED,
    SHIPPED_HHA_PREDICTED_DEPTH,
    SHIPPED_PREFIX,
    ensure_trained,
    export_params,
    heldout_report,
    load_shipped,
    modality_weights,
    pretrained_vgg16,
    quick_check,
    read_npz,
    run_dir,
    save_npz,
    shipped_file,
)
from placejax.pretrain._shape import trunk_map_size
from placejax.pretrain._train import (
    PRESETS,
    PretextObjective,
    PretrainConfig,
    init_params,
    load_trained,
    num_classes,
    train,
    training_frames,
)

__all__ = [
    "CHECK_FRAMES",
    "PRESETS",
    "SHIPPED",
    "SHIPPED_HHA",
    "SHIPPED_HHA_PREDICTED",
    "SHIPPED_HHA_PREDICTED_DEPTH",
    "SHIPPED_PREFIX",
    "PretextObjective",
    "PretrainConfig",
    "baselines",
    "ensure_trained",
    "evaluate_trunk",
    "export_params",
    "gradient_thumbnail",
    "heldout_frames",
    "heldout_report",
    "init_params",
    "load_shipped",
    "load_trained",
    "modality_weights",
    "network_depth",
    "num_classes",
    "perturb_depth",
    "place_frames",
    "place_labels",
    "place_world_seeds",
    "pretrained_vgg16",
    "quick_check",
    "read_npz",
    "recall_at_1",
    "render_random_looks",
    "run_dir",
    "save_npz",
    "shipped_file",
    "train",
    "training_frames",
    "trunk_descriptor",
    "trunk_map_size",
]
