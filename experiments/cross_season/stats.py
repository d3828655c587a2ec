"""Seeds and intervals: mean ± sd over seeds, and paired bootstrap intervals of the gains.

A gain (Ours − baseline) is computed on the same test frames for both methods, so its uncertainty is that of a
*paired* difference: the bootstrap resamples test frames (with replacement) and keeps each frame's two outcomes
together, averaging over the seeds the run trained. For the mean over pairs, frames are resampled within each pair
independently (pairs are different test sessions) and the resampled pair gains averaged. The interval is the 2.5th
and 97.5th percentile of ``n_boot`` resamples; a gain "excludes zero" when the whole interval is on one side.
"""

from __future__ import annotations

import numpy as np

N_BOOT = 2000


def mean_sd(values) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof=1; 0 for a single value)."""
    v = np.asarray(values, np.float64)
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else 0.0


def frame_gains(correct_a: np.ndarray, correct_b: np.ndarray) -> np.ndarray:
    """Per test frame, the mean over seeds of ``correct_a − correct_b``: ``(S, N)`` bool/0-1 each → ``(N,)``."""
    a = np.asarray(correct_a, np.float64)
    b = np.asarray(correct_b, np.float64)
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(f"expected two (seeds, frames) arrays of one shape, got {a.shape} and {b.shape}")
    return (a - b).mean(axis=0)


def bootstrap_means(gains: np.ndarray, rng: np.random.Generator, n_boot: int = N_BOOT) -> np.ndarray:
    """``n_boot`` means of ``gains`` over frames resampled with replacement."""
    n = len(gains)
    idx = rng.integers(0, n, size=(n_boot, n))
    return gains[idx].mean(axis=1)


def gain_intervals(
    pairs_gains: list[np.ndarray], *, seed: int = 0, n_boot: int = N_BOOT, level: float = 0.95
) -> tuple[list[dict], dict]:
    """Paired bootstrap intervals of each pair's gain and of the mean gain over pairs.

    Args:
        pairs_gains: per pair, :func:`frame_gains` ``(N_pair,)``.
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
