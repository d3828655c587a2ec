"""The NCLT rehearsal's multi-host projection: the busiest host's share of a cache and the arithmetic of
``project_hosts``, on made-up numbers checked by hand."""

from __future__ import annotations

import pytest

from benchmarks.nclt_rehearsal import GPU_ROW, SHARDED_STAGES, busiest_share, project_hosts
from placejax.data.cache import shard_rows


def test_busiest_share_is_the_largest_share_the_cache_deals_out():
    for frames, chunk, hosts in [(26_000, 64, 16), (26_000, 256, 16), (100, 32, 4), (10, 64, 4), (64, 64, 2)]:
        shares = [shard_rows(frames, chunk, i, hosts) for i in range(hosts)]
        assert busiest_share(frames, chunk, hosts) == max(hi - lo for lo, hi in shares)
    assert busiest_share(26_000, 64, 1) == 26_000
    assert busiest_share(26_000, 64, 16) == 64 * 26  # 407 chunks: 26 on the busiest host, 25 on others
    assert busiest_share(10, 64, 4) == 10  # one chunk: one host does it all


def test_project_hosts_arithmetic():
    cfg = {"depth": {"batch_size": 50}, "eval": {"batch_size": 25}}
    assert {k: f(cfg) for k, f in SHARDED_STAGES.items()} == {
        "sessions": 64,
        "depth": 50,
        "hha": 50,
        "features": 25,
        "outputs": 256,
    }
    projection = {
        "target_frames": 1000,
        "stages": {
            "depth": {"fixed": 10.0, "per_frame": 2.0, "projected": 2010.0},
            "features": {"fixed": 5.0, "per_frame": 1.0, "projected": 1005.0},
            "nets": {"fixed": 100.0, "per_frame": 0.5, "projected": 600.0},
            "evaluate": {"fixed": 0.0, "per_frame": 0.01, "quadratic_extra": 40.0, "projected": 50.0},
        },
    }
    p = project_hosts(projection, cfg, (1, 4), cache_mb=1000.0, copy_mb_s=500.0, hash_mb_s=250.0, overhead_s=60.0)
    one, four = p["rows"]
    # One host: the projection itself.
    assert one["total_s"] == pytest.approx(2010 + 1005 + 600 + 50)
    assert one["assembly_s"] == one["overhead_s"] == 0
    # Four hosts: depth 20 chunks of 50 → 5 each; features 40 chunks of 25 → 10 each; nets, evaluate as they were.
    assert four["sharded_s"] == pytest.approx(10 + 2.0 * 250 + 5 + 1.0 * 250)
    assert four["other_s"] == pytest.approx(650.0)
    assert four["assembly_s"] == pytest.approx(1000 / 500 + 1000 / 250)
    assert four["overhead_s"] == 60.0
    assert four["total_s"] == pytest.approx(765 + 650 + 6 + 60)
    assert four["total_h"] == pytest.approx(1481 / 3600)
    assert four["speedup"] == pytest.approx(one["total_s"] / four["total_s"])
    assert one["speedup"] == 1.0
    assert p["gpu"] == GPU_ROW
    assert "not run here" in GPU_ROW["status"]
