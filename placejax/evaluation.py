"""Scoring a place classifier: top-1 accuracy, seed means, and paired bootstrap intervals of a gain.

A gain (method A − method B) is measured on the same test frames for both methods, so its uncertainty is that of a
*paired* difference: the bootstrap resamples test frames (with replacement) and keeps each frame's two outcomes
together, averaging over the seeds that were trained. For the mean over several test sets (e.g. the season pairs of
``experiments.cross_season``), frames are resampled within each set independently and the resampled gains averaged.
An interval is the 2.5th and 97.5th percentile of ``n_boot`` resamples; a gain "excludes zero" when the whole
interval is on one side of it.

Example:
    >>> import numpy as np
    >>> from placejax import evaluation
    >>> logits = np.array([[2.0, 0.1], [0.3, 1.0], [0.9, 0.2]])
    >>> evaluation.top1(logits, np.array([0, 1, 1]))  # doctest: +ELLIPSIS
    0.666...
    >>> a = np.array([[1, 1, 0, 1]], bool)  # (seeds, frames): method A right?
    >>> b = np.array([[0, 1, 0, 0]], bool)  # method B right?
    >>> evaluation.frame_gains(a, b)
    array([1., 0., 0., 1.])
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "N_BOOT",
    "bootstrap_means",
    "frame_gains",
    "gain_intervals",
    "log_linear_pool",
    "log_softmax",
    "mean_sd",
    "softmax",
    "top1",
]

N_BOOT = 2000
"""Bootstrap resamples of :func:`gain_intervals` by default."""


def top1(logits: np.ndarray, labels: np.ndarray) -> float:
    """Top-1 accuracy: the share of frames whose arg-max class is the ground truth.

    Args:
        logits: ``(N, C)`` scores (logits or probabilities; only their arg-max counts).
        labels: int ``(N,)`` true classes; a label the classifier cannot output (e.g. a place never seen in
            training, or ``-1``) is an error.

    Returns:
        A fraction in [0, 1] (not %).
    """
    logits = np.asarray(logits)
    labels = np.asarray(labels)
    if logits.ndim != 2 or labels.shape != logits.shape[:1]:
        raise ValueError(f"expected logits (N, C) and labels (N,), got {logits.shape} and {labels.shape}")
    return float(np.mean(np.argmax(logits, axis=1) == labels))


def softmax(logits: np.ndarray) -> np.ndarray:
    """Class probabilities of ``(N, C)`` logits (row-wise, stabilised by the row maximum): ``(N, C)``, rows sum to 1."""
    z = logits - logits.max(axis=1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=1, keepdims=True)


def log_softmax(logits: np.ndarray) -> np.ndarray:
    """Row-wise log softmax of ``(N, C)`` logits, float64 (stable: the row maximum subtracted first)."""
    x = np.asarray(logits, np.float64)
    x = x - x.max(axis=1, keepdims=True)
    return x - np.log(np.exp(x).sum(axis=1, keepdims=True))


def log_linear_pool(rgb_logits: np.ndarray, hha_logits: np.ndarray, rgb_weight: float) -> np.ndarray:
    """The log-linear (geometric) pool of two classifiers' beliefs: ``w · log p_rgb + (1 − w) · log p_hha``.

    Its softmax is the normalised weighted geometric mean of the two nets' class probabilities; weight 1 is RGB-Net
    alone, 0 HHA-Net alone, 0.5 their geometric mean. Returns float64 ``(N, C)`` scores (log-probabilities up to a
    per-row constant; their arg-max is the pool's class).

    >>> a = np.log(np.array([[0.7, 0.3]]))  # RGB-Net fairly sure of class 0
    >>> b = np.log(np.array([[0.2, 0.8]]))  # HHA-Net surer of class 1
    >>> softmax(log_linear_pool(a, b, 0.5)).round(3)
    array([[0.433, 0.567]])
    """
    if not 0.0 <= rgb_weight <= 1.0:
        raise ValueError(f"rgb_weight={rgb_weight!r}: expected a number in [0, 1]")
    return rgb_weight * log_softmax(rgb_logits) + (1.0 - rgb_weight) * log_softmax(hha_logits)


def mean_sd(values) -> tuple[float, float]:
    """Mean and sample standard deviation (``ddof=1``; 0 for a single value) of a 1-D sequence, e.g. per-seed
    accuracies."""
    v = np.asarray(values, np.float64)
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else 0.0


def frame_gains(correct_a: np.ndarray, correct_b: np.ndarray) -> np.ndarray:
    """Per test frame, the mean over seeds of ``correct_a − correct_b``.

    Args:
        correct_a: bool or 0/1 ``(S, N)``: whether method A got frame ``n`` right in seed ``s``.
        correct_b: the same for method B, same shape.

    Returns:
        float64 ``(N,)`` in [-1, 1].
    """
    a = np.asarray(correct_a, np.float64)
    b = np.asarray(correct_b, np.float64)
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(f"expected two (seeds, frames) arrays of one shape, got {a.shape} and {b.shape}")
    return (a - b).mean(axis=0)


def bootstrap_means(gains: np.ndarray, rng: np.random.Generator, n_boot: int = N_BOOT) -> np.ndarray:
    """``n_boot`` means of ``gains`` ``(N,)`` over frames resampled with replacement: ``(n_boot,)``."""
    n = len(gains)
    idx = rng.integers(0, n, size=(n_boot, n))
    return gains[idx].mean(axis=1)


def gain_intervals(
    pairs_gains: list[np.ndarray], *, seed: int = 0, n_boot: int = N_BOOT, level: float = 0.95
) -> tuple[list[dict], dict]:
    """Paired bootstrap intervals of each test set's gain and of the mean gain over the sets.

    Args:
        pairs_gains: per test set (pair), :func:`frame_gains` ``(N_pair,)``.
        seed: bootstrap seed (the intervals are reproducible).
        n_boot: resamples.
        level: coverage of the interval.

    Returns:
        ``(per_pair, mean)``, each ``{"gain", "lo", "hi", "excludes_zero"}`` (fractions, not %).
    """
    rng = np.random.default_rng(seed)
    q = [(1 - level) / 2 * 100, (1 + level) / 2 * 100]
    per_pair, boots = [], []
    for g in pairs_gains:
        b = bootstrap_means(np.asarray(g, np.float64), rng, n_boot)
        boots.append(b)
        per_pair.append(_interval(float(np.mean(g)), b, q))
    mean_boot = np.mean(boots, axis=0)
    mean = _interval(float(np.mean([np.mean(g) for g in pairs_gains])), mean_boot, q)
    return per_pair, mean


def _interval(gain: float, boot: np.ndarray, q: list[float]) -> dict:
    lo, hi = np.percentile(boot, q)
    return {"gain": gain, "lo": float(lo), "hi": float(hi), "excludes_zero": bool(lo > 0 or hi < 0)}
