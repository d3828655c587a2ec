"""Monocular depth: MiDaS preprocessing and batched inference."""

from placejax.depth._inference import network_size, predict, preprocess

__all__ = ["network_size", "predict", "preprocess"]
