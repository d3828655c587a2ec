"""placejax.evaluation: top-1, seed means and paired bootstrap intervals against independent, loop-by-loop
recomputations."""

from __future__ import annotations

import numpy as np
import pytest

from placejax import evaluation


def _reference(pairs, seed, n_boot):
    """Plain loops, one resample at a time, with the same random stream."""
    rng = np.random.default_rng(seed)
    boots = []
    for a, b in pairs:
        s, n = a.shape
        g = [(sum(a[k, f] for k in range(s)) - sum(b[k, f] for k in range(s))) / s for f in range(n)]
        idx = rng.integers(0, n, size=(n_boot, n))
        boots.append([sum(g[i] for i in row) / n for row in idx])
    return boots


def test_intervals_match_a_loop_recomputation():
    rng = np.random.default_rng(1)
    pairs = [
        (rng.random((3, n)) < pa, rng.random((3, n)) < pb)
        for n, pa, pb in ((50, 0.6, 0.4), (70, 0.3, 0.3), (40, 0.5, 0.2))
    ]
    per_pair, mean = evaluation.gain_intervals([evaluation.frame_gains(a, b) for a, b in pairs], seed=7, n_boot=300)
    ref = _reference(pairs, 7, 300)
    for (a, b), r, got in zip(pairs, ref, per_pair, strict=True):
        assert got["gain"] == pytest.approx(a.mean() - b.mean())
        assert got["lo"] == pytest.approx(np.percentile(r, 2.5))
        assert got["hi"] == pytest.approx(np.percentile(r, 97.5))
        assert got["excludes_zero"] == (got["lo"] > 0 or got["hi"] < 0)
    mean_boot = np.mean(ref, axis=0)
    assert mean["gain"] == pytest.approx(np.mean([a.mean() - b.mean() for a, b in pairs]))
    assert mean["lo"] == pytest.approx(np.percentile(mean_boot, 2.5))
    assert mean["hi"] == pytest.approx(np.percentile(mean_boot, 97.5))


def test_interval_behaviour():
    n = 400
    same = np.zeros((3, n), bool)
    better = np.ones((3, n), bool)
    per_pair, _ = evaluation.gain_intervals([evaluation.frame_gains(better, same)], n_boot=200)
    assert per_pair[0] == {"gain": 1.0, "lo": 1.0, "hi": 1.0, "excludes_zero": True}
    rng = np.random.default_rng(0)
    # Two methods right on as many frames, but on different ones: a zero gain whose interval straddles zero.
    a = rng.random((3, n)) < 0.5
    b = a[:, rng.permutation(n)]
    per_pair, _ = evaluation.gain_intervals([evaluation.frame_gains(a, b)], n_boot=500)
    assert per_pair[0]["lo"] < 0 < per_pair[0]["hi"]
    assert not per_pair[0]["excludes_zero"]
    assert evaluation.mean_sd([0.2, 0.4]) == pytest.approx((0.3, np.std([0.2, 0.4], ddof=1)))
    assert evaluation.mean_sd([0.5]) == (0.5, 0.0)
    with pytest.raises(ValueError, match="seeds, frames"):
        evaluation.frame_gains(np.zeros(3), np.zeros(3))


def test_top1_and_softmax_against_loops():
    """top-1 against a frame-by-frame count; softmax against its definition, unchanged by a per-row shift."""
    rng = np.random.default_rng(3)
    logits = rng.normal(size=(40, 6))
    labels = rng.integers(-1, 6, size=40)  # -1: a place the classifier cannot output, always an error
    right = sum(1 for row, y in zip(logits, labels, strict=True) if max(range(6), key=lambda c: row[c]) == y)
    assert evaluation.top1(logits, labels) == right / 40
    p = evaluation.softmax(logits)
    np.testing.assert_allclose(p, np.exp(logits) / np.exp(logits).sum(1, keepdims=True), rtol=1e-12)
    np.testing.assert_allclose(evaluation.softmax(logits + rng.normal(size=(40, 1)) * 100), p, rtol=1e-9)
    assert evaluation.top1(p, labels) == evaluation.top1(logits, labels)
    with pytest.raises(ValueError, match=r"logits \(N, C\) and labels \(N,\)"):
        evaluation.top1(logits, labels[:-1])
