"""Weights: one way to name them, the registry of official ones, the records of placejax-trained ones.

Public surface:
    resolve: ``registry:NAME``, ``shipped:NAME`` or a path → :class:`WeightsRecord` ``(variables, meta)``; every
        network placejax loads goes through it. ``identity`` says what a spec names, for cache keys.
    WeightsRecord, read_record, load_shipped, shipped_names, shipped_file, run_dir, announce_training,
        training_lock: the one lifecycle of the networks placejax trains itself (the depth network, the pretrained
        trunks): trained once into the cache (one process at a time), recorded as an ``.npz`` with its ``meta``,
        shipped (SHA-256 in ``SHIPPED_SHA256``, else ``ShippedWeightsError``), verified, loaded.
    REGISTRY, load, fetch, cache_dir: official pretrained weights (MiDaS, Depth Anything V2, VGG16), downloaded
        once and converted.
    read_torch_checkpoint and the converters: a torch-free safe reader of ``torch.save`` files → Flax variables.
"""

from placejax.weights._convert import convert_depth_anything_v2, convert_midas_small, convert_vgg16
from placejax.weights._registry import (
    REGISTRY,
    Preprocessing,
    PretrainedWeights,
    WeightsUnavailableError,
    cache_dir,
    fetch,
    load,
)
from placejax.weights._resolve import REGISTRY_PREFIX, SHIPPED_PREFIX, identity, resolve
from placejax.weights._shipped import (
    SHIPPED_PACKAGES,
    SHIPPED_SHA256,
    ShippedWeightsError,
    WeightsRecord,
    announce_training,
    load_shipped,
    read_record,
    run_dir,
    shipped_file,
    shipped_names,
    training_lock,
)
from placejax.weights._torch_checkpoint import (
    DEFAULT_MAX_BYTES,
    TorchCheckpointError,
    UnsafeCheckpointError,
    read_torch_checkpoint,
)

__all__ = [
    "DEFAULT_MAX_BYTES",
    "REGISTRY",
    "REGISTRY_PREFIX",
    "SHIPPED_PACKAGES",
    "SHIPPED_PREFIX",
    "SHIPPED_SHA256",
    "Preprocessing",
    "PretrainedWeights",
    "ShippedWeightsError",
    "TorchCheckpointError",
    "UnsafeCheckpointError",
    "WeightsRecord",
    "WeightsUnavailableError",
    "announce_training",
    "cache_dir",
    "convert_depth_anything_v2",
    "convert_midas_small",
    "convert_vgg16",
    "fetch",
    "identity",
    "load",
    "load_shipped",
    "read_record",
    "read_torch_checkpoint",
    "resolve",
    "run_dir",
    "shipped_file",
    "shipped_names",
    "training_lock",
]
