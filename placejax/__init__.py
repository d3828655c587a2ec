"""placejax: pseudo multi-modal (RGB + monocular-depth HHA) visual place classification in JAX/Flax.

Iwasaki, Tanaka & Tsukahara, "A Multi-modal Approach to Single-modal Visual Place Classification".

Public surface (every subpackage is imported on first attribute access, so ``import placejax`` stays light: no
JAX, Flax or OpenCV until a subpackage is used):

- `placejax.hha`: depth in metres + intrinsics → uint8 HHA images, jitted and batched.
- `placejax.depth`: MiDaS preprocessing and inference (`placejax.depth.apply`, jittable), the depth losses,
  the depth-network trainer and its train-once-and-cache lifecycle.
- `placejax.models`: Flax Linen MiDaS v2.1 small, Depth Anything V2, VGG16 and the fusion MLP.
- `placejax.weights`: named weights (`placejax.weights.resolve` for ``registry:NAME``, ``shipped:NAME`` or a
  path), the safe ``torch.save`` reader and the converters.
- `placejax.pretrain`: the VGG16 trunk pretrained on domain-randomised SimCampus worlds.
- `placejax.data`: sessions (NCLT, SimCampus, in-memory arrays), the place grid, caches and grain pipelines.
- `placejax.route`: a Bayes filter over the place cells along a route, fed by the classifier and odometry.
- `placejax.training`: the one training engine every network uses.
- `placejax.stages`: the method's stages as functions (sessions, depth and HHA, the place nets, the fusion MLP),
  what ``experiments.cross_season`` drives.
- `placejax.config`: how every stage's settings are stated (one dataclass per section).
- `placejax.classify`: `PlaceClassifier` (uint8 RGB ``(N, H, W, 3)`` → places), the pure end-to-end
  `placejax.classify.forward` and unseen-place scores.
- `placejax.evaluation`: top-1 accuracy, seed means and paired bootstrap intervals of a gain.
- `placejax.io`: atomic file writes and the npz-record reader.
- `placejax.progress`: progress as live bars in a terminal and timestamped lines in a log.
- `PlaceClassifier`, `Prediction`: shortcuts for `placejax.classify.PlaceClassifier` and
  `placejax.classify.Prediction`.
"""

import importlib as _importlib
import importlib.metadata as _metadata
from typing import TYPE_CHECKING as _TYPE_CHECKING

try:  # the installed distribution's version (pyproject.toml is the one place it is written)
    __version__ = _metadata.version("placejax")
except _metadata.PackageNotFoundError:  # a source tree that was not installed
    __version__ = "unknown"

__all__ = [
    "PlaceClassifier",
    "Prediction",
    "classify",
    "config",
    "data",
    "depth",
    "evaluation",
    "hha",
    "io",
    "models",
    "pretrain",
    "progress",
    "route",
    "stages",
    "training",
    "weights",
]
# A literal list above, so static tools read the surface; the lazy loader below takes its names from it.
_FROM_CLASSIFY = ("PlaceClassifier", "Prediction")
_SUBMODULES = tuple(name for name in __all__ if name not in _FROM_CLASSIFY)

if _TYPE_CHECKING:  # what IDEs and type checkers see; at run time the same names load lazily (__getattr__)
    from placejax import (
        classify,
        config,
        data,
        depth,
        evaluation,
        hha,
        io,
        models,
        pretrain,
        progress,
        route,
        stages,
        training,
        weights,
    )
    from placejax.classify import PlaceClassifier, Prediction


def __getattr__(name: str):
    # PEP 562: subpackages and the classifier are imported on first use, so ``import placejax`` stays light.
    if name in _SUBMODULES:
        value = _importlib.import_module(f"placejax.{name}")
    elif name in _FROM_CLASSIFY:
        value = getattr(_importlib.import_module("placejax.classify"), name)
    else:
        raise AttributeError(f"module 'placejax' has no attribute {name!r}")
    globals()[name] = value  # later look-ups are plain attribute reads (and tools that read __dict__ see it)
    return value


def __dir__() -> list[str]:
    return sorted({*__all__, *(k for k in globals() if k.startswith("__"))})
