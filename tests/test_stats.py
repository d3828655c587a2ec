"""Seed means and paired bootstrap intervals against an independent, loop-by-loop recomputation."""

from __future__ import annotations

import numpy as np
import pytest

from experiments.cross_season import stats


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
    per_pair, mean = stats.gain_intervals([stats.frame_gains(a, b) for a, b in pairs], seed=7, n_boot=300)
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
    per_pair, _ = stats.gain_intervals([stats.frame_gains(better, same)], n_boot=200)
    assert per_pair[0] == {"gain": 1.0, "lo": 1.0, "hi": 1.0, "excludes_zero": True}
    rng = np.random.default_rng(0)
    # Two methods right on as many frames, but on different ones: a zero gain whose interval straddles zero.
    a = rng.random((3, n)) < 0.5
    b = a[:, rng.permutation(n)]
    per_pair, _ = stats.gain_intervals([stats.frame_gains(a, b)], n_boot=500)
    assert per_pair[0]["lo"] < 0 < per_pair[0]["hi"] and not per_pair[0]["excludes_zero"]
    assert stats.mean_sd([0.2, 0.4]) == pytest.approx((0.3, np.std([0.2, 0.4], ddof=1)))
    assert stats.mean_sd([0.5]) == (0.5, 0.0)
    with pytest.raises(ValueError, match="seeds, frames"):
        stats.frame_gains(np.zeros(3), np.zeros(3))
