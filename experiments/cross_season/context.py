"""What every stage of the experiment shares: the run context (config, folders, meshes, stage timer) and the
per-session record that the stages fill in."""

from __future__ import annotations

import dataclasses
import resource
import sys
import time
from pathlib import Path
from typing import Any

import jax
import ml_collections
import numpy as np

from placejax.classify.run_layout import CACHE_DIR
from placejax.training import data_mesh


@dataclasses.dataclass
class Context:
    """What every stage needs: the config, folders, the meshes and the stage timer.

    ``mesh`` spans every device of every process: training runs on it (all processes take part in each step).
    ``local_mesh`` spans this process's devices: cached inference stages run on it, so that one process can build
    a cache while the others wait for its file lock (a collective there would deadlock). With one process the
    two are the same mesh.
    """

    config: ml_collections.ConfigDict
    workdir: Path
    mesh: jax.sharding.Mesh
    local_mesh: jax.sharding.Mesh | None = None  # default: this process's devices
    timings: dict[str, float] = dataclasses.field(default_factory=dict)
    # stage -> the process's peak resident memory so far (MiB) when that stage last ended (a stage may run once
    # per seed or session): where the run's peak was reached, read with the timings' order.
    peak_rss_mib: dict[str, float] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if self.local_mesh is None:
            self.local_mesh = data_mesh(jax.local_devices())

    @property
    def cache_root(self) -> Path:
        """The run's array caches (``placejax.classify.run_layout``)."""
        return self.workdir / CACHE_DIR

    @property
    def progress(self) -> bool:
        """Whether stages show progress bars (``config.progress``)."""
        return bool(self.config.progress)

    def timed(self, stage: str):
        """A context manager adding its block's wall time to ``timings[stage]`` (seconds) and recording the peak
        resident memory so far in ``peak_rss_mib[stage]``."""
        ctx = self

        class _Timer:
            def __enter__(self):
                self.t0 = time.perf_counter()

            def __exit__(self, *exc):
                ctx.timings[stage] = ctx.timings.get(stage, 0.0) + time.perf_counter() - self.t0
                ctx.peak_rss_mib[stage] = peak_rss_mib()

        return _Timer()


@dataclasses.dataclass
class SessionData:
    """One session through the stages: cached RGB, labels and (after the depth stages) depth and HHA."""

    name: str
    cached: Any  # CachedSession
    source: Any  # the original Session (SimCampus: renders true depth)
    labels: np.ndarray | None = None
    depth: Any = None  # ArrayCache float32 (N, H, W)
    hha: Any = None  # ArrayCache uint8 (N, H, W, 3)

    def __len__(self) -> int:
        return len(self.cached)


def peak_rss_mib() -> float:
    """This process's peak resident memory so far, MiB (``getrusage``: kB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (2**20 if sys.platform == "darwin" else 2**10), 1)


def seed_context(ctx: Context, seed: int) -> Context:
    """``ctx`` with ``config.seed = seed`` (a copy of the config; the timings, peak memory, workdir and meshes are
    shared)."""
    cfg = ctx.config.copy_and_resolve_references()
    cfg.seed = seed
    return dataclasses.replace(ctx, config=cfg)
