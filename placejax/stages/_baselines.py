"""Ceilings and trivial baselines for the cross-season table: how far each column is from what the world allows.

Ceilings (from poses and labels alone):
    seen_class_fraction  share of test frames whose class the training session visited: a perfect recogniser
                         trained on that session cannot do better (the rest can only be errors).
    heading_ceiling      share of test frames for which the training session has a frame of the same class whose
                         heading is within ``max_heading_deg`` (45°): a recogniser that must also have seen the
                         place from a similar direction (a forward camera sees another scene when turned around)
                         cannot do better.
Baselines (nearest neighbour, no learning):
    nn_rgb       1-NN on ``size × size`` RGB thumbnails.
    nn_gradient  1-NN on thumbnails of the gray image's gradient magnitude (edges survive colour changes).
    nn_hha       1-NN on HHA thumbnails of the run's depth source (``depth.source``).
    nn_hha_true  1-NN on HHA thumbnails of rendered depth (SimCampus only): what geometry alone allows.
Each thumbnail is area-resized, then standardised per image (zero mean, unit norm), so the 1-NN distance is
1 − the Pearson correlation of the two thumbnails.
"""

from __future__ import annotations

import cv2
import numpy as np

from placejax.depth import DepthSourceConfig, depth_source
from placejax.stages._depth import depth_and_hha, has_true_depth
from placejax.stages._workspace import SessionData

__all__ = [
    "MAX_HEADING_DEG",
    "THUMB_SIZES",
    "gradient_thumbnails",
    "heading_ceiling",
    "nearest_neighbour_labels",
    "pair_ceilings_and_baselines",
    "rgb_baseline_features",
    "thumbnails",
]
THUMB_SIZES = {"nn_rgb": 12, "nn_gradient": 12, "nn_hha": 16, "nn_hha_true": 16}
"""Baseline name → the side of its square thumbnails, pixels."""
MAX_HEADING_DEG = 45.0


def _standardise(x: np.ndarray) -> np.ndarray:
    x = x.reshape(len(x), -1).astype(np.float32)
    x = x - x.mean(axis=1, keepdims=True)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-6)


def thumbnails(images: np.ndarray, size: int, *, chunk: int = 512) -> np.ndarray:
    """uint8 ``(N, H, W, C)`` → float32 ``(N, size·size·C)`` standardised area-resized thumbnails."""
    out = []
    for lo in range(0, len(images), chunk):
        block = np.asarray(images[lo : lo + chunk])
        small = np.stack([cv2.resize(im, (size, size), interpolation=cv2.INTER_AREA) for im in block])
        out.append(_standardise(small.reshape(len(block), size, size, -1)))
    return np.concatenate(out)


def gradient_thumbnails(images: np.ndarray, size: int, *, chunk: int = 512) -> np.ndarray:
    """uint8 RGB ``(N, H, W, 3)`` → standardised thumbnails of the gray image's Sobel gradient magnitude."""
    out = []
    for lo in range(0, len(images), chunk):
        mags = []
        for im in np.asarray(images[lo : lo + chunk]):
            gray = cv2.cvtColor(im, cv2.COLOR_RGB2GRAY).astype(np.float32)
            mag = cv2.magnitude(cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1))
            mags.append(cv2.resize(mag, (size, size), interpolation=cv2.INTER_AREA))
        out.append(_standardise(np.stack(mags)))
    return np.concatenate(out)


def nearest_neighbour_labels(train: np.ndarray, train_labels: np.ndarray, test: np.ndarray, *, chunk: int = 1024):
    """The label of each test row's nearest training row (largest dot product of standardised rows).

    Args:
        train: float ``(N, D)`` standardised training rows (:func:`thumbnails`).
        train_labels: int ``(N,)`` their labels.
        test: float ``(M, D)`` standardised test rows.
        chunk: test rows per matrix product.

    Returns:
        int32 ``(M,)`` labels.
    """
    out = np.empty(len(test), np.int32)
    for lo in range(0, len(test), chunk):
        out[lo : lo + chunk] = train_labels[np.argmax(test[lo : lo + chunk] @ train.T, axis=1)]
    return out


def heading_ceiling(
    train_poses: np.ndarray,
    train_labels: np.ndarray,
    test_poses: np.ndarray,
    test_labels: np.ndarray,
    max_heading_deg: float = MAX_HEADING_DEG,
) -> float:
    """Share of test frames with a training frame of the same class within ``max_heading_deg`` of heading.

    Poses are ``(N, ≥3)`` with yaw in radians in column 2; labels −1 (outside the grid) never match.
    """
    ok = np.zeros(len(test_labels), bool)
    cos_max = np.cos(np.radians(max_heading_deg))
    for c in np.unique(test_labels[test_labels >= 0]):
        tr = train_poses[train_labels == c, 2]
        if len(tr) == 0:
            continue
        te_idx = np.flatnonzero(test_labels == c)
        # cos of the heading difference, for every (test, train) pair of this class.
        cos = np.cos(test_poses[te_idx, 2][:, None] - tr[None, :])
        ok[te_idx] = (cos >= cos_max - 1e-12).any(axis=1)
    return float(ok.mean())


def rgb_baseline_features(sessions: list[SessionData]) -> dict[str, dict[str, np.ndarray]]:
    """Standardised RGB and gradient-magnitude thumbnails of every session (the RGB-only baselines): baseline name
    → session name → ``(N, D)``."""
    return {
        "nn_rgb": {s.name: thumbnails(s.cached.images, THUMB_SIZES["nn_rgb"]) for s in sessions},
        "nn_gradient": {s.name: gradient_thumbnails(s.cached.images, THUMB_SIZES["nn_gradient"]) for s in sessions},
    }


def pair_ceilings_and_baselines(s: SessionData, t: SessionData, thumbs: dict) -> dict[str, float]:
    """Pose ceilings and 1-NN baselines of training session ``s`` on test session ``t`` (``thumbs``: name →
    session → standardised thumbnails)."""
    # The best any classifier trained on s can do: test frames in classes s never visited are errors.
    row = {
        "seen_class_fraction": float(np.isin(t.labels, np.unique(s.labels)).mean()),
        "heading_ceiling": heading_ceiling(s.cached.poses, s.labels, t.cached.poses, t.labels),
    }
    for name, feats in thumbs.items():
        guess = nearest_neighbour_labels(feats[s.name], s.labels, feats[t.name])
        row[name] = float(np.mean(guess == t.labels))
    return row


def baseline_features(ws, sessions: list[SessionData], depth_batch_size: int) -> dict[str, dict[str, np.ndarray]]:
    """Standardised thumbnails of every session for every nearest-neighbour baseline: RGB, gradient, HHA of the
    run's depth and, where every session has true depth, HHA of that depth (cached like ``depth.source=true``).

    Args:
        ws: the run's ``Workspace``.
        sessions: every session, after the depth stages (``SessionData.hha``).
        depth_batch_size: images per call when the true-depth HHA caches are built.
    """

    feats = rgb_baseline_features(sessions)
    feats["nn_hha"] = {s.name: thumbnails(s.hha.data, THUMB_SIZES["nn_hha"]) for s in sessions}
    if has_true_depth(sessions):
        # Geometry alone: HHA of rendered depth (the same caches as depth.source=true, built once).
        true = depth_and_hha(ws, sessions, depth_source(DepthSourceConfig(source="true")), depth_batch_size)
        feats["nn_hha_true"] = {
            s.name: thumbnails(h.data, THUMB_SIZES["nn_hha_true"]) for s, (_, h) in zip(sessions, true, strict=True)
        }
    return feats
