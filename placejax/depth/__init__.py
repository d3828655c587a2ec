"""Monocular depth: MiDaS preprocessing and inference, the scale- and shift-invariant training objective,
training of MidasSmall on the depth-training worlds, and depth-quality metrics."""

from placejax.depth._evaluate import baseline_predictions, evaluate, evaluation_frames
from placejax.depth._inference import network_size, predict, preprocess
from placejax.depth._losses import (
    align_least_squares,
    gradient_matching,
    midas_loss,
    normalise_median_mad,
    ssi_mse,
    ssi_trimmed_mae,
)
from placejax.depth._metrics import aligned_depth, depth_metrics
from placejax.depth._train import PRESETS, DepthTrainConfig, TrainedDepth, load_trained, train, train_step

__all__ = [
    "PRESETS",
    "DepthTrainConfig",
    "TrainedDepth",
    "align_least_squares",
    "aligned_depth",
    "baseline_predictions",
    "depth_metrics",
    "evaluate",
    "evaluation_frames",
    "gradient_matching",
    "load_trained",
    "midas_loss",
    "network_size",
    "normalise_median_mad",
    "predict",
    "preprocess",
    "ssi_mse",
    "ssi_trimmed_mae",
    "train",
    "train_step",
]
