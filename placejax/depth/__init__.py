"""Monocular depth: MiDaS preprocessing and inference, the scale- and shift-invariant training objective,
training of MidasSmall on the depth-training worlds (on ``placejax.training``'s engine), its train-once-and-cache
lifecycle (:func:`ensure_trained`; the default preset's network ships with the package, :func:`load_shipped`),
and depth-quality metrics.

:func:`apply` is the pure, jittable MiDaS forward pass (uint8 ``(N, H, W, 3)`` → float32 ``(N, H, W)`` relative
inverse depth, a ``jax.Array``); :func:`predict` computes the same on the host (OpenCV resize, NumPy out).
"""

from placejax.depth._evaluate import baseline_predictions, evaluate, evaluation_frames
from placejax.depth._inference import apply, network_size, predict, preprocess
from placejax.depth._lifecycle import (
    SHIPPED,
    ensure_trained,
    load_shipped,
    quick_check,
    report_markdown,
    run_dir,
    save_shipped,
    shipped_network,
    write_report,
)
from placejax.depth._losses import (
    LOG_DEPTH_UNIT_M,
    align_least_squares,
    depth_from_log,
    far_to_sky,
    gradient_matching,
    log_depth,
    log_metric_loss,
    midas_loss,
    normal_loss,
    normalise_median_mad,
    ssi_mse,
    ssi_trimmed_mae,
    window_normals,
)
from placejax.depth._metrics import aligned_depth, depth_metrics
from placejax.depth._sources import SOURCE_NAMES, DepthSource, DepthSourceConfig, depth_source, register_source
from placejax.depth._train import (
    PRESETS,
    DepthObjective,
    DepthTrainConfig,
    TrainedDepth,
    load_trained,
    permute_channels,
    train,
)
from placejax.depth._views import average_views, shift_columns, validate_shifts

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
    "align_least_squares",
    "aligned_depth",
    "apply",
    "average_views",
    "baseline_predictions",
    "depth_from_log",
    "depth_metrics",
    "depth_source",
    "ensure_trained",
    "evaluate",
    "evaluation_frames",
    "far_to_sky",
    "gradient_matching",
    "load_shipped",
    "load_trained",
    "log_depth",
    "log_metric_loss",
    "midas_loss",
    "network_size",
    "normal_loss",
    "normalise_median_mad",
    "permute_channels",
    "predict",
    "preprocess",
    "quick_check",
    "register_source",
    "report_markdown",
    "run_dir",
    "save_shipped",
    "shift_columns",
    "shipped_network",
    "ssi_mse",
    "ssi_trimmed_mae",
    "train",
    "validate_shifts",
    "window_normals",
    "write_report",
]
