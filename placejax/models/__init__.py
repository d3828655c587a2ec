"""Flax Linen models: MiDaS v2.1 small, Depth Anything V2, VGG16 (torchvision layout) and the fusion MLP, plus
exact resizes, CPU inference compiler options, from-scratch initialisation and the ImageNet input normalisation."""

from placejax.models._cpu import cpu_compiler_options
from placejax.models._dav2 import (
    DAV2_CONFIGS,
    DAV2_PATCH,
    DepthAnythingV2,
    DinoV2Encoder,
    DPTHead,
    dav2_apply,
    dav2_input_size,
)
from placejax.models._fusion import FusionMLP
from placejax.models._init import (
    IMAGENET_MEAN,
    IMAGENET_MEAN_255,
    IMAGENET_STD,
    IMAGENET_STD_255,
    he_init,
    imagenet_normalise,
)
from placejax.models._midas import EfficientNetLite3Encoder, MidasSmall, fold_batch_norm
from placejax.models._resize import interpolation_matrix, resize, upsample2x_align_corners
from placejax.models._vgg import (
    CONV_NAMES,
    VGG16,
    VGG16Head,
    VGG16Trunk,
    adaptive_avg_pool,
    fold_adaptive_pool,
)

__all__ = [
    "CONV_NAMES",
    "DAV2_CONFIGS",
    "DAV2_PATCH",
    "IMAGENET_MEAN",
    "IMAGENET_MEAN_255",
    "IMAGENET_STD",
    "IMAGENET_STD_255",
    "VGG16",
    "DPTHead",
    "DepthAnythingV2",
    "DinoV2Encoder",
    "EfficientNetLite3Encoder",
    "FusionMLP",
    "MidasSmall",
    "VGG16Head",
    "VGG16Trunk",
    "adaptive_avg_pool",
    "cpu_compiler_options",
    "dav2_apply",
    "dav2_input_size",
    "fold_adaptive_pool",
    "fold_batch_norm",
    "he_init",
    "imagenet_normalise",
    "interpolation_matrix",
    "resize",
    "upsample2x_align_corners",
]
