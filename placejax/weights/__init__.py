"""Pretrained weights: safe ``torch.save`` reading, PyTorch → Flax converters and a named registry."""

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
from placejax.weights._torch_checkpoint import (
    DEFAULT_MAX_BYTES,
    TorchCheckpointError,
    UnsafeCheckpointError,
    read_torch_checkpoint,
)

__all__ = [
    "DEFAULT_MAX_BYTES",
    "REGISTRY",
    "Preprocessing",
    "PretrainedWeights",
    "TorchCheckpointError",
    "UnsafeCheckpointError",
    "WeightsUnavailableError",
    "cache_dir",
    "convert_depth_anything_v2",
    "convert_midas_small",
    "convert_vgg16",
    "fetch",
    "load",
    "read_torch_checkpoint",
]
