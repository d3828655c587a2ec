""" "This image is from no place I was trained on": scores, a threshold from training frames, and its evaluation.

Every score is computed from the classifier's logits and is *larger for less familiar images*; an image is
rejected ("unknown place") when its score exceeds a threshold. The threshold is a quantile of the scores of the
training session's own frames (training data only): ``target_frr`` of them would be rejected. Those frames were
seen in training, so on another season the realised rejection rate of seen places is higher; the evaluation
reports it (``rejected_seen``) rather than assuming the target.

Scores (Hendrycks & Gimpel, ICLR 2017, maximum softmax probability; Liu et al., NeurIPS 2020, energy):
    msp: 1 − max softmax probability.
    entropy: entropy of the softmax (nats).
    energy: −logsumexp(logits).
    margin: −(p₁ − p₂), the gap between the two most probable classes, negated.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "DEFAULT_SCORE",
    "DEFAULT_TARGET_FRR",
    "SCORES",
    "auroc",
    "detection_metrics",
    "fit_threshold",
    "unknown_score",
]

SCORES = ("msp", "entropy", "energy", "margin")
"""The names :func:`unknown_score` knows (see the module's docstring)."""
DEFAULT_SCORE = "msp"
"""The score a classifier's rejection threshold is fitted on."""
DEFAULT_TARGET_FRR = 0.05
"""The share of the training session's own frames the threshold rejects."""


def unknown_score(logits, score: str = DEFAULT_SCORE) -> jax.Array:
    """Unfamiliarity of each image, float32 ``(N,)`` from logits ``(N, C)``; larger = less like a known place."""
    z = jnp.asarray(logits, jnp.float32)
    if score == "energy":
        return -jax.nn.logsumexp(z, axis=-1)
    p = jax.nn.softmax(z, axis=-1)
    if score == "msp":
        return 1.0 - p.max(axis=-1)
    if score == "entropy":
        return -jnp.sum(p * jnp.log(jnp.maximum(p, 1e-30)), axis=-1)
    if score == "margin":
        top2 = jax.lax.top_k(p, min(2, p.shape[-1]))[0]
        second = top2[..., 1] if p.shape[-1] > 1 else jnp.zeros_like(top2[..., 0])
        return -(top2[..., 0] - second)
    raise ValueError(f"unknown-place score must be one of {SCORES}, got {score!r}")


def fit_threshold(train_scores: np.ndarray, target_frr: float = DEFAULT_TARGET_FRR) -> float:
    """The score above which ``target_frr`` of the training frames lie (their ``1 − target_frr`` quantile), from
    their scores, float ``(N,)``."""
    s = np.asarray(train_scores, np.float64)
    if s.ndim != 1 or len(s) == 0:
        raise ValueError(f"need a non-empty 1-D array of training scores, got shape {s.shape}")
    if not 0.0 <= target_frr < 1.0:
        raise ValueError(f"target_frr must be in [0, 1), got {target_frr}")
    return float(np.quantile(s, 1.0 - target_frr, method="higher"))


def auroc(scores: np.ndarray, positive: np.ndarray) -> float:
    """Area under the ROC curve of ``scores`` (float ``(N,)``) for ``positive`` (bool ``(N,)``; ties count one
    half); NaN without both kinds.

    >>> auroc(np.array([0.1, 0.4, 0.35, 0.8]), np.array([False, False, True, True]))
    0.75
    """
    s = np.asarray(scores, np.float64)
    pos = np.asarray(positive, bool)
    n_pos, n_neg = int(pos.sum()), int((~pos).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    # Mann–Whitney U from average ranks (ties share their mean rank).
    order = np.argsort(s, kind="mergesort")
    ranks = np.empty(len(s), np.float64)
    sorted_s = s[order]
    _, first, counts = np.unique(sorted_s, return_index=True, return_counts=True)
    mean_rank = first + (counts + 1) / 2.0
    ranks[order] = np.repeat(mean_rank, counts)
    u = ranks[pos].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))


def detection_metrics(
    logits: np.ndarray,
    labels: np.ndarray,
    seen_classes: np.ndarray,
    threshold: float,
    score: str = DEFAULT_SCORE,
) -> dict[str, float]:
    """How well ``score`` separates test frames of unseen classes (positives) from frames of seen classes.

    Args:
        logits: ``(N, C)`` classifier outputs on the test session.
        labels: ``(N,)`` true classes (−1: outside the grid, counted as unseen).
        seen_classes: classes the training session visited.
        threshold: reject when the score is above it (from :func:`fit_threshold` on training frames).
        score: one of :data:`SCORES`.

    Returns:
        ``auroc``; ``rejected_unseen`` and ``rejected_seen`` (shares rejected); ``seen_accuracy_accepted``: top-1
        among accepted seen frames (NaN when none is accepted); ``unseen_fraction``.
    """
    s = np.asarray(unknown_score(logits, score))
    unseen = ~np.isin(labels, seen_classes)
    reject = s > threshold
    accepted_seen = ~unseen & ~reject
    correct = np.argmax(logits, axis=1) == labels
    nan = float("nan")
    return {
        "auroc": auroc(s, unseen),
        "rejected_unseen": float(reject[unseen].mean()) if unseen.any() else nan,
        "rejected_seen": float(reject[~unseen].mean()) if (~unseen).any() else nan,
        "seen_accuracy_accepted": float(correct[accepted_seen].mean()) if accepted_seen.any() else nan,
        "unseen_fraction": float(unseen.mean()),
    }
