"""Monocular depth: the depth-source registry, MiDaS preprocessing and inference, the placejax depth network's
training (on ``placejax.training``'s engine) and its train-once-and-cache lifecycle.

The registry is what a pipeline calls: :func:`depth_source` turns a :class:`DepthSourceConfig` into a
:class:`DepthSource` (uint8 RGB → metric depth, plus the identity its caches are keyed by); :func:`register_source`
adds one. :func:`apply` is the pure, jittable MiDaS forward pass (uint8 ``(N, H, W, 3)`` → float32 ``(N, H, W)``
relative inverse depth); :func:`predict` computes the same on the host. The default preset's network ships with the
package (``placejax.weights.resolve("shipped:…")`` reads its record; :func:`shipped_network` makes it a network);
:func:`ensure_trained` trains any other preset once per machine.

Submodules: :mod:`placejax.depth.losses` (the training objectives and log depth), :mod:`placejax.depth.metrics`
(depth-quality metrics), :mod:`placejax.depth.evaluation` (the held-out evaluation frames and report) and
:mod:`placejax.depth.views` (averaging a network over mirrored and shifted views).
"""

from placejax.depth import evaluation, losses, metrics, views
from placejax.depth._config import PRESETS, DepthTrainConfig
from placejax.depth._inference import apply, network_on_images, network_size, predict, preprocess
from placejax.depth._lifecycle import (
    SHIPPED,
    ensure_trained,
    quick_check,
    report_markdown,
    run_dir,
    save_shipped,
    shipped_network,
    write_report,
)
from placejax.depth._sources import (
    SOURCE_NAMES,
    DepthSource,
    DepthSourceConfig,
    classifier_entry,
    depth_source,
    register_source,
)
from placejax.depth._train import DepthObjective, TrainedDepth, load_trained, train_network
from placejax.depth.losses import LOG_DEPTH_UNIT_M, depth_from_log, far_to_sky, log_depth

__all__ = [
    "LOG_DEPTH_UNIT_M",
    "PRESETS",
    "SHIPPED",
    "SOURCE_NAMES",
    "DepthObjective",
    "DepthSource",
    "DepthSourceConfig",
    "DepthTrainConfig",
    "TrainedDepth",
    "apply",
    "classifier_entry",
    "depth_from_log",
    "depth_source",
    "ensure_trained",
    "evaluation",
    "far_to_sky",
    "load_trained",
    "log_depth",
    "losses",
    "metrics",
    "network_on_images",
    "network_size",
    "predict",
    "preprocess",
    "quick_check",
    "register_source",
    "report_markdown",
    "run_dir",
    "save_shipped",
    "shipped_network",
    "train_network",
    "views",
    "write_report",
]
